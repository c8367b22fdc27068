"""File formats and file access. The only package (with ``cli``) that touches files.

One module per format (see docs/formats.md):

- ``scan_json``: scan folders (``scan.json`` + images); ``calibration_json``:
  calibration sets (``calibration.json``); ``_manifest``: what the two manifests share;
- ``images``: reading and writing the images themselves (PNG, TIFF, ...);
- ``rig_json``: ``rig.json``, a calibrated rig; ``truth``: the virtual rig's ground truth;
- ``coords_npz``: decoded projector coordinates; ``points_npz``: point clouds;
  ``ply``: ``cloud.ply``; ``tiff``: float height maps + sidecar JSON;
  ``reconstruction_folder``: everything a reconstruction leaves;
- ``reports``: JSON-ready summaries of results (the BGA's included); ``jsonable``: the one
  converter of results to JSON values; ``bga_csv``: the BGA's per-ball table;
- ``figures``: one module per figure (height-map preview, BGA map, calibration report,
  histograms of the paper re-run);
- ``atomic``: writes that leave a complete file or nothing; ``errors``: ``InputError``.

io may import the dataclasses of the numerical packages (and the simulator's); none of
them imports io (checked by the import contracts in ``make test``).
"""

from telefringe.io.errors import InputError

__all__ = ["InputError"]
