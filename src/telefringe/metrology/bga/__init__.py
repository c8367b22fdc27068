"""BGA inspection, a module per stage.

- :mod:`.nominal`: the nominal grid (:class:`BGANominal`);
- :mod:`.measure`: :func:`measure_bga`, the stages in order, and :class:`BGAOptions`;
- :mod:`.segment`: the substrate, the ball regions and their cap points;
- :mod:`.caps`: one cap fitted on its own; :mod:`.psf`: all caps through a point-spread
  model; :mod:`.highlights`: centres from specular highlights;
- :mod:`.grid`: registration on the nominal grid; :mod:`.coplanarity`: the JEDEC
  seating plane; :mod:`.result`: :class:`BGAMeasurement`;
- :mod:`.stereo`: the cap fits' covariance with a two-camera match's correlated noise.
"""

from telefringe.metrology.bga.coplanarity import Coplanarity, seating_plane_coplanarity
from telefringe.metrology.bga.measure import BGAOptions, measure_bga
from telefringe.metrology.bga.nominal import BGANominal
from telefringe.metrology.bga.psf import PSFConvergenceWarning, PSFSolveWarning
from telefringe.metrology.bga.result import NOT_MEASURED_REASONS, BGAMeasurement
from telefringe.metrology.bga.stereo import StereoCorrelationWarning

__all__ = ["BGANominal", "BGAOptions", "BGAMeasurement", "Coplanarity", "NOT_MEASURED_REASONS",
           "PSFConvergenceWarning",
           "PSFSolveWarning", "StereoCorrelationWarning", "measure_bga",
           "seating_plane_coplanarity"]
