"""The acceptance test's files: ``acceptance.json`` (which scan shows which artefact,
format ``telefringe-acceptance-set`` v1), ``artefacts.json`` (the artefacts'
certificate, format ``telefringe-artefacts`` v1) and ``result.json`` (what
``telefringe accept`` found). See docs/acceptance.md."""

from __future__ import annotations

from pathlib import Path, PurePosixPath
from typing import NamedTuple

import numpy as np

from telefringe.io._manifest import (
    check_fields,
    check_rel_path,
    is_num,
    open_manifest,
    parse_header,
    read_json,
)
from telefringe.io._manifest import short_repr as _r
from telefringe.io.atomic import write_json_atomic
from telefringe.io.errors import InputError
from telefringe.metrology.acceptance import ARTEFACT_KINDS, Artefacts

__all__ = ["SET_FORMAT", "ARTEFACTS_FORMAT", "RESULT_FORMAT", "SetEntry", "load_acceptance_set",
           "write_acceptance_set", "load_artefacts", "write_artefacts", "result_to_json"]

SET_FORMAT = "telefringe-acceptance-set"
ARTEFACTS_FORMAT = "telefringe-artefacts"
RESULT_FORMAT = "telefringe-acceptance-result"


class SetEntry(NamedTuple):
    """One position of an acceptance set: its ``scan`` folder (relative to the set),
    ``artefact``, ``description`` and, for a two-camera rig, the ``second`` camera's scan
    folder of the same patterns (else None), as ``reconstruct --second`` takes it."""

    scan: str
    artefact: str
    description: str = ""
    second: str | None = None

    @property
    def name(self) -> str:
        """The position's name: the scan folder, or with a second camera the folder both
        scans share (``sphere_00`` for ``sphere_00/camera`` + ``sphere_00/camera_2``)."""
        if self.second is not None:
            a, b = PurePosixPath(self.scan), PurePosixPath(self.second)
            if a.parent == b.parent and str(a.parent) not in ("", "."):
                return str(a.parent)
        return self.scan


def load_acceptance_set(folder) -> list[SetEntry]:
    """Read ``folder/acceptance.json``: one :class:`SetEntry` per position.

    Every scan (and ``second`` scan, where given) is a sub-folder of ``folder`` holding a
    ``scan.json``; every artefact is "sphere", "ball_bar" or "plane".
    """
    folder, path = open_manifest(folder, "acceptance.json", "acceptance set")
    doc = read_json(path)
    probs = parse_header(doc, SET_FORMAT, {"format", "version", "scans", "meta"}, str(path))
    scans = doc.get("scans")
    out = []
    if not isinstance(scans, list) or not scans:
        probs.add(f"'scans' must be a non-empty list, got {_r(scans)}")
        scans = []
    seen = set()
    for i, s in enumerate(scans):
        what = f"scans[{i}]"
        if not isinstance(s, dict):
            probs.add(f"{what} must be an object {{\"scan\": ..., \"artefact\": ...}}")
            continue
        check_fields(s, {"scan", "artefact", "description", "second"}, f"{what}.", probs)
        if s.get("artefact") not in ARTEFACT_KINDS:
            probs.add(f"{what}.artefact must be one of {', '.join(ARTEFACT_KINDS)}, got "
                      f"{_r(s.get('artefact'))}")
        keys = ("scan", "second") if s.get("second") is not None else ("scan",)
        bad = False
        for key in keys:
            ok = check_rel_path(folder, s.get(key), f"{what}.{key}", probs, kind="folder")
            if ok is None:
                bad = True
                continue
            if ok[1] in seen:
                probs.add(f"{what}: {_r(s[key])} is listed twice")
                bad = True
                continue
            seen.add(ok[1])
            if not (folder / s[key] / "scan.json").is_file():
                probs.add(f"{what}: {_r(s[key])} is not a scan folder (no scan.json)")
        if bad:
            continue
        out.append(SetEntry(str(s["scan"]), str(s.get("artefact")),
                            str(s.get("description", "")),
                            None if s.get("second") is None else str(s["second"])))
    probs.raise_if_any()
    return out


def write_acceptance_set(folder, scans) -> None:
    """Write ``folder/acceptance.json``; ``scans``: ``(scan folder, artefact,
    description)`` or ``(scan folder, artefact, description, second camera's scan folder
    or None)`` per position."""
    rows = []
    for e in scans:
        e = SetEntry(*e)
        row = {"scan": e.scan, "artefact": e.artefact, "description": e.description}
        if e.second is not None:
            row["second"] = e.second
        rows.append(row)
    doc = {"format": SET_FORMAT, "version": 1, "scans": rows}
    write_json_atomic(Path(folder) / "acceptance.json", doc, force=True)


_ART_KEYS = {
    "sphere": {"diameter_mm", "u_diameter_mm", "form_mm", "u_form_mm"},
    "ball_bar": {"distance_mm", "u_distance_mm", "sphere_diameters_mm"},
    "plane": {"flatness_mm", "u_flatness_mm", "length_mm", "width_mm"},
}


def load_artefacts(path) -> Artefacts:
    """Read and check ``artefacts.json`` (the certificate; every length in mm)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: not found (the artefacts' certificate, artefacts.json)")
    doc = read_json(path)
    probs = parse_header(doc, ARTEFACTS_FORMAT, {"format", "version", "meta", *_ART_KEYS},
                         str(path))
    vals = {}
    for kind, keys in _ART_KEYS.items():
        d = doc.get(kind)
        if not isinstance(d, dict):
            probs.add(f"'{kind}' must be an object with {', '.join(sorted(keys))}")
            continue
        check_fields(d, keys, f"{kind}.", probs)
        for k in sorted(keys):
            v = d.get(k)
            if k == "sphere_diameters_mm":
                if (not isinstance(v, list) or len(v) != 2
                        or not all(is_num(x) and x > 0 for x in v)):
                    probs.add(f"'{kind}.{k}' must be two positive numbers, got {_r(v)}")
                else:
                    vals[(kind, k)] = (float(v[0]), float(v[1]))
            elif k in ("length_mm", "width_mm") and v is None:
                vals[(kind, k)] = float("nan")
            elif not is_num(v) or v < 0 or (k in ("diameter_mm", "distance_mm") and v <= 0):
                probs.add(f"'{kind}.{k}' must be a {'positive' if k in ('diameter_mm', 'distance_mm') else 'non-negative'} number (mm), got {_r(v)}")  # noqa: E501
            else:
                vals[(kind, k)] = float(v)
    probs.raise_if_any()
    return Artefacts(
        sphere_diameter=vals["sphere", "diameter_mm"],
        u_sphere_diameter=vals["sphere", "u_diameter_mm"],
        sphere_form=vals["sphere", "form_mm"], u_sphere_form=vals["sphere", "u_form_mm"],
        bar_distance=vals["ball_bar", "distance_mm"],
        u_bar_distance=vals["ball_bar", "u_distance_mm"],
        bar_diameters=vals["ball_bar", "sphere_diameters_mm"],
        plane_flatness=vals["plane", "flatness_mm"],
        u_plane_flatness=vals["plane", "u_flatness_mm"],
        plane_length=vals["plane", "length_mm"], plane_width=vals["plane", "width_mm"])


def write_artefacts(path, art: Artefacts, *, meta: dict | None = None,
                    force: bool = True) -> None:
    """Write ``artefacts.json`` (atomically)."""
    doc = {"format": ARTEFACTS_FORMAT, "version": 1,
           "sphere": {"diameter_mm": art.sphere_diameter,
                      "u_diameter_mm": art.u_sphere_diameter, "form_mm": art.sphere_form,
                      "u_form_mm": art.u_sphere_form},
           "ball_bar": {"distance_mm": art.bar_distance, "u_distance_mm": art.u_bar_distance,
                        "sphere_diameters_mm": list(art.bar_diameters)},
           "plane": {"flatness_mm": art.plane_flatness,
                     "u_flatness_mm": art.u_plane_flatness, "length_mm": art.plane_length,
                     "width_mm": art.plane_width}}
    if meta:
        doc["meta"] = meta
    write_json_atomic(Path(path), doc, force=force)


def _f(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def result_to_json(result, *, rig: str = "", folder: str = "") -> dict:
    """The JSON document of an AcceptanceResult: one entry per characteristic ("PF",
    "PS", "SD", "F") with its per-position values and maximum (mm), and the positions'
    details."""
    from telefringe.metrology.acceptance import SpacingTest, SphereTest

    doc = {"format": RESULT_FORMAT, "version": 1, "units": "mm", "folder": folder,
           "rig": rig, "excluded_fraction": result.excluded_fraction,
           "decision_rule": result.decision_rule, "verdict": result.verdict or None}
    by_name = {p.name: p for p in result.positions}
    for q, qr in result.quantities.items():
        entries = []
        for k, name in enumerate(qr.positions):
            e = {"position": name, "value": _f(qr.values[k]), "U": _f(qr.U[k])}
            if qr.decisions:
                e["decision"] = qr.decisions[k]
            t = by_name[name].test
            if isinstance(t, SphereTest):
                e.update(diameter=_f(t.diameter), cap_half_angle_deg=_f(t.cap_half_angle_deg),
                         n_points=t.n_points, n_excluded=t.n_excluded,
                         rms=_f(np.sqrt(np.mean(t.fit.residuals ** 2))))
                sp = by_name[name].spread
                if q == "PS" and sp is not None:
                    e["spread_model"] = {"value": _f(sp.PS),
                                         "u_fit_diameter": _f(sp.u_fit_diameter),
                                         "n_points": sp.n_points,
                                         "psf_variance_px2": [_f(v) for v in sp.variances_px2],
                                         "differs_from_PS": by_name[name].spread_bias()}
            elif isinstance(t, SpacingTest):
                e.update(distance=_f(t.distance),
                         cap_half_angle_deg=[_f(s.cap_half_angle_deg) for s in t.spheres],
                         n_points=[s.n_points for s in t.spheres],
                         n_excluded=[s.n_excluded for s in t.spheres])
            else:
                e.update(n_points=t.n_points, n_excluded=t.n_excluded,
                         rms=_f(np.sqrt(np.mean(t.fit.residuals ** 2))))
            entries.append(e)
        doc[q] = {"positions": entries, "max": _f(qr.max_value),
                  "max_position": qr.max_position, "mpe": qr.mpe,
                  "verdict": qr.verdict or None}
    return doc
