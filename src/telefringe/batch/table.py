"""The results table of a batch: a row per scan (pandas DataFrame), written as Parquet and
CSV, and the journal that keeps the finished rows of an interrupted batch."""

from __future__ import annotations

import json
import os
from pathlib import Path

from telefringe.batch.job import FIXED_COLUMNS

__all__ = ["FIXED_TYPES", "to_frame", "write_table", "Journal", "TABLE_NAMES"]

#: pandas dtypes of the fixed columns (the measurement's columns: float64 for numbers,
#: boolean for flags, string for text; missing values are NA)
FIXED_TYPES = {
    "scan": "string", "path": "string", "status": "string", "error": "string",
    "reused": "boolean", "measure": "string", "points": "Int64",
    "valid_fraction": "float64", "sigma_z_median_mm": "float64", "warnings": "string",
    "t_read_s": "float64", "t_reconstruct_s": "float64", "t_measure_s": "float64",
    "t_write_s": "float64", "t_total_s": "float64", "worker": "string", "output": "string",
    "key": "string",
}
TABLE_NAMES = ("results.parquet", "results.csv")
JOURNAL_NAME = "results.partial.jsonl"


def _column_type(values) -> str:
    vals = [v for v in values if v is not None]
    if vals and all(isinstance(v, bool) for v in vals):
        return "boolean"
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
        return "float64"
    return "string"


def to_frame(rows):
    """The rows (dicts) as a DataFrame: the fixed columns first (:data:`FIXED_TYPES`),
    then every measurement column in order of appearance; NA where a row has none."""
    import pandas as pd

    rows = list(rows)
    extra: dict[str, None] = {}
    for r in rows:
        for k in r:
            if k not in FIXED_TYPES:
                extra.setdefault(k)
    cols = list(FIXED_COLUMNS) + list(extra)
    data = {}
    for c in cols:
        vals = [r.get(c) for r in rows]
        t = FIXED_TYPES.get(c) or _column_type(vals)
        if t == "float64":
            vals = [float("nan") if v is None else float(v) for v in vals]
        elif t == "string":
            vals = [None if v is None else str(v) for v in vals]
        data[c] = pd.array(vals, dtype=t)
    return pd.DataFrame(data, columns=cols)


def write_table(folder, frame) -> dict:
    """Write ``frame`` as ``folder/results.parquet`` and ``folder/results.csv``, each
    atomically (replacing older ones). Returns name -> Path."""
    from telefringe.io.atomic import atomic_file

    folder = Path(folder)
    out = {}
    with atomic_file(folder / "results.parquet", force=True) as tmp:
        frame.to_parquet(tmp, index=False)
    out["parquet"] = folder / "results.parquet"
    with atomic_file(folder / "results.csv", force=True) as tmp:
        frame.to_csv(tmp, index=False)
    out["csv"] = folder / "results.csv"
    return out


class Journal:
    """``folder/results.partial.jsonl``: every finished row appended as one JSON line and
    flushed to disk, so an interrupted batch leaves the rows it finished (a line cut by a
    crash is skipped by :meth:`read`). Started empty by each batch; removed once the
    final table is written."""

    def __init__(self, folder):
        self.path = Path(folder) / JOURNAL_NAME
        self._f = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()

    def append(self, row: dict) -> None:
        from telefringe.io.jsonable import to_jsonable

        self._f.write(json.dumps(to_jsonable(row)) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())

    def close(self, *, remove: bool) -> None:
        self._f.close()
        if remove:
            self.path.unlink(missing_ok=True)

    @staticmethod
    def read(path) -> list[dict]:
        rows = []
        for line in Path(path).read_text(encoding="utf-8").splitlines():
            try:
                rows.append(json.loads(line))
            except ValueError:
                continue
        return rows
