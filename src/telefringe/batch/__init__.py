"""Many scans at once: decode -> reconstruct -> measure for every scan folder, on Dask
(dask.distributed: a LocalCluster by default, any running cluster by its address), with
a table of results, resumable outputs and per-scan errors.

Sits on top with the CLI (``telefringe batch``); nothing in telefringe imports it, and
Dask is imported only when a batch runs on it.

- :func:`measure_many` (:mod:`.run`): the whole batch, returns a pandas DataFrame;
- :mod:`.scans`: which folders (folders, glob patterns, list files) and their names;
- :mod:`.job`: one scan (:class:`BatchOptions`, :func:`run_scan`);
- :mod:`.table`: the table's columns, Parquet / CSV, the journal.
"""

from telefringe.batch.job import FIXED_COLUMNS, MEASURES, BatchOptions
from telefringe.batch.run import measure_many
from telefringe.batch.table import FIXED_TYPES

__all__ = ["measure_many", "BatchOptions", "MEASURES", "FIXED_COLUMNS", "FIXED_TYPES"]
