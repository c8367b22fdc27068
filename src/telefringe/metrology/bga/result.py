"""The result of a BGA inspection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import _freeze
from telefringe.metrology.bga.coplanarity import Coplanarity
from telefringe.metrology.bga.nominal import BGANominal
from telefringe.metrology.planes import PlaneFit

#: Why a ball that is seen (something stands above the substrate at its grid position)
#: could not be measured.
NOT_MEASURED_REASONS = {
    "region_too_small": "the region standing above the substrate is smaller than "
                        "min_fraction of a ball's footprint (shadowed, or few valid pixels)",
    "region_too_large": "the region is wider than two ball diameters or larger than three "
                        "footprints (merged with a neighbour or with debris)",
    "too_few_points": "fewer than 10 valid cap points are left after the edge, height and "
                      "highlight cuts",
    "too_few_points_facing_camera": "fewer than 10 cap points face the camera within "
                                    "max_view_angle_deg",
    "fit_failed": "the sphere fit raised (degenerate points) or its linearisation is "
                  "singular",
    "not_in_view": "no ball region, and valid points on less than a quarter of a ball's "
                   "footprint around the nominal position (outside the field of view, or "
                   "invalid there): it cannot be told missing",
    "fit_rms_too_large": "the fit's RMS residual is 10 % of the diameter or more: not a cap "
                         "of the nominal ball",
}


@dataclass(frozen=True, eq=False)
class BGAMeasurement:
    """A BGA inspection.

    Per ball (n found balls, in row-major grid order):

    index : (n, 2) int, (row i, column j) on the nominal grid.
    centre : (n, 3) world mm, fitted sphere centre.
    sigma_centre : (n, 3) mm, its standard uncertainty (from the cap fit's residuals, or
        from the highlight fit for refined balls).
    refined : (n,) bool, the centre's position on the substrate comes from the ball's
        specular highlight (see :func:`measure_bga`).
    apex : (n, 3) world mm, top of the ball (farthest from the substrate).
    height : (n,) mm, apex height above the substrate plane.
    sigma_height : (n,) mm, its standard uncertainty: ``sigma_height_noise`` and
        ``sigma_height_model`` in quadrature (the noise alone where the model term is
        NaN). It does not hold the calibration's uncertainty.
    sigma_height_noise : (n,) mm, the part from the pixels' noise (a repeatability: on
        the virtual paper rig the scatter of each ball's height over noise seeds is
        0.99 of it over 4 seeds of one window, 0.87 over seed pairs of 136 balls). A
        two-camera cloud measured with its matches' noise (``measure_bga(..., noise=)``)
        has it and ``sigma_centre`` from the sandwich of the caps' correlated points
        (tests/test_stereo_noise_bga.py).
    sigma_height_model : float, mm, the per-ball error of the cap model, which varies
        from ball to ball but not with the noise: ``SIGMA_HEIGHT_MODEL_PX`` (0.023) camera
        pixels on the object for cap model "psf" with an image, measured on the virtual
        paper rig (0.76 um there; against the truth the normalised error is then 0.99,
        1.4-1.5 without it; see :data:`telefringe.metrology.bga.measure.SIGMA_HEIGHT_MODEL_PX`
        for the method). NaN (not measured) for the other cap models and without an
        image: ``sigma_height`` is then the noise part alone and too small against the
        truth on a real scan.
    diameter : (n,) mm, of the fitted sphere; NaN where the cap did not determine it
        (the fit then used the nominal diameter).
    position : (n, 2) mm, ball centre on the substrate plane, in the grid's frame
        (x' along the columns, y' along the rows, origin at the grid's first position).
    rms : (n,) mm, RMS radial residual of the cap fit.   n_points : (n,) int.

    Grid-wide:

    substrate : PlaneFit.
    found : (rows, cols) bool, positions with a measured ball.
    not_measured : (((i, j), reason), ...), positions where a ball is seen (a region
        stands above the substrate there) but could not be measured; ``reason`` is a key
        of :data:`NOT_MEASURED_REASONS`. Such a ball is neither ``found`` nor ``missing``.
    missing : ((i, j), ...) populated positions where no ball is seen at all.
    unexpected : ((i, j), ...) balls measured where the nominal grid has none (a ball
        seen there but not measured is listed in ``not_measured`` only).
    pitch_x : (rows, cols - 1) mm, in-plane distance between neighbouring ball centres
        along the columns (NaN where one is missing); pitch_y : (rows - 1, cols).
    pitch_error_max : float, mm, largest |pitch - nominal|.
    coplanarity : Coplanarity (JEDEC seating plane).
    grid_angle_deg : float, the grid's rotation on the substrate.
    psf_variance, sigma_psf_variance : float, mm^2, the camera's point-spread variance
        (per axis, on the object) estimated from the caps and its standard uncertainty,
        when the caps were fitted with it (cap model "psf"); else NaN (also when the
        solve failed: see :class:`~telefringe.metrology.bga.psf.PSFSolveWarning`).
    psf_balls : int, balls the point-spread parameters were estimated from (0 without
        the model).   psf_converged : bool, the Gauss-Newton rounds of that estimate
        converged (step below 5 % of its sigma); None without the model.
    uncertainty : dict of str -> Uncertainty, or None: ``"height"``, ``"position"``,
        ``"pitch_x"``, ``"pitch_y"``, ``"pitch_error_max"``, ``"coplanarity"`` with the
        noise and calibration parts (set by
        :func:`telefringe.metrology.uncertainty.bga_uncertainty`; None until then).
    """

    index: np.ndarray
    centre: np.ndarray
    sigma_centre: np.ndarray
    refined: np.ndarray
    apex: np.ndarray
    height: np.ndarray
    sigma_height: np.ndarray
    diameter: np.ndarray
    position: np.ndarray
    rms: np.ndarray
    n_points: np.ndarray
    substrate: PlaneFit
    found: np.ndarray
    missing: tuple
    unexpected: tuple
    pitch_x: np.ndarray
    pitch_y: np.ndarray
    pitch_error_max: float
    coplanarity: Coplanarity
    grid_angle_deg: float
    nominal: BGANominal
    psf_variance: float = np.nan
    sigma_psf_variance: float = np.nan
    not_measured: tuple = ()
    psf_balls: int = 0
    psf_converged: bool | None = None
    sigma_height_noise: np.ndarray | None = None
    sigma_height_model: float = np.nan
    uncertainty: dict | None = None

    def __post_init__(self):
        for key, reason in self.not_measured:
            if reason not in NOT_MEASURED_REASONS:
                raise ValueError(f"not_measured {key}: unknown reason {reason!r}")
        if self.sigma_height_noise is None:
            object.__setattr__(self, "sigma_height_noise", self.sigma_height)
        _freeze(self, "index", "centre", "sigma_centre", "refined", "apex", "height",
                  "sigma_height", "sigma_height_noise", "diameter", "position", "rms",
                  "n_points", "found", "pitch_x", "pitch_y")

    @property
    def n_balls(self) -> int:
        return int(self.index.shape[0])
