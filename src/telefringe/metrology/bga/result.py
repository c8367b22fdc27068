"""The result of a BGA inspection."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from telefringe.metrology._common import _readonly
from telefringe.metrology.bga.coplanarity import Coplanarity
from telefringe.metrology.bga.nominal import BGANominal
from telefringe.metrology.planes import PlaneFit


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
    sigma_height : (n,) mm, its standard uncertainty.
    diameter : (n,) mm, of the fitted sphere; NaN where the cap did not determine it
        (the fit then used the nominal diameter).
    position : (n, 2) mm, ball centre on the substrate plane, in the grid's frame
        (x' along the columns, y' along the rows, origin at the grid's first position).
    rms : (n,) mm, RMS radial residual of the cap fit.   n_points : (n,) int.

    Grid-wide:

    substrate : PlaneFit.
    found : (rows, cols) bool.   missing : ((i, j), ...) populated positions not found.
    unexpected : ((i, j), ...) balls found where the nominal grid has none.
    pitch_x : (rows, cols - 1) mm, in-plane distance between neighbouring ball centres
        along the columns (NaN where one is missing); pitch_y : (rows - 1, cols).
    pitch_error_max : float, mm, largest |pitch - nominal|.
    coplanarity : Coplanarity (JEDEC seating plane).
    grid_angle_deg : float, the grid's rotation on the substrate.
    psf_variance, sigma_psf_variance : float, mm^2, the camera's point-spread variance
        (per axis, on the object) estimated from the caps and its standard uncertainty,
        when the caps were fitted with it (``psf_model``); else NaN.
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

    def __post_init__(self):
        _readonly(self.index, self.centre, self.sigma_centre, self.refined, self.apex,
                  self.height, self.sigma_height, self.diameter, self.position, self.rms,
                  self.n_points, self.found, self.pitch_x, self.pitch_y)

    @property
    def n_balls(self) -> int:
        return int(self.index.shape[0])
