"""Measurements on point clouds: planes, circle-marker spacing, spheres, BGA, step heights.

Every fit returns a small frozen result with its uncertainty; degenerate input raises
:class:`MetrologyError` (a ``ValueError``) with a message that says what is missing.
Point arrays are (n, 3) in mm (world frame); organised clouds are
:class:`telefringe.reconstruction.cloud.PointCloud` (one point per camera pixel,
NaN = invalid).

Conventions
-----------
- Plane normals point toward the camera (``normal[2] > 0``), so distances above a plane
  (heights) are positive toward the camera.
- ``rms`` and form errors are computed from the inliers of robust fits.
- Standard uncertainties come from the residuals of each fit (the noise level is
  estimated, not assumed), through the fit's linearised normal equations.

Modules: :mod:`.planes`, :mod:`.plate` (circle-marker plates), :mod:`.spheres`,
:mod:`.steps` and the :mod:`.bga` package (a stage per module).
"""

from telefringe.metrology._common import MetrologyError
from telefringe.metrology.bga import (
    NOT_MEASURED_REASONS,
    BGAMeasurement,
    BGANominal,
    BGAOptions,
    Coplanarity,
    PSFConvergenceWarning,
    PSFSolveWarning,
    measure_bga,
    seating_plane_coplanarity,
)
from telefringe.metrology.planes import Plane, PlaneDistance, PlaneFit, fit_plane, plane_distance
from telefringe.metrology.plate import (
    GridSpacing,
    MarkerCentres,
    PlateMeasurement,
    grid_spacing,
    marker_centres_3d,
    measure_plate,
)
from telefringe.metrology.spheres import SphereFit, SphereMeasurement, fit_sphere, measure_sphere
from telefringe.metrology.steps import StepMeasurement, measure_steps

__all__ = [
    "MetrologyError",
    "Plane",
    "PlaneFit",
    "PlaneDistance",
    "fit_plane",
    "plane_distance",
    "MarkerCentres",
    "GridSpacing",
    "PlateMeasurement",
    "marker_centres_3d",
    "grid_spacing",
    "measure_plate",
    "SphereFit",
    "SphereMeasurement",
    "fit_sphere",
    "measure_sphere",
    "BGANominal",
    "BGAOptions",
    "NOT_MEASURED_REASONS",
    "PSFConvergenceWarning",
    "PSFSolveWarning",
    "Coplanarity",
    "BGAMeasurement",
    "seating_plane_coplanarity",
    "measure_bga",
    "StepMeasurement",
    "measure_steps",
]
