"""The acceptance test of VDI/VDE 2634 Part 2 for area-scanning optical 3D systems:
probing errors PF and PS (test sphere), sphere-spacing error SD (ball bar) and flatness
error F (plane), per position, their maxima and PASS/FAIL against the MPE with the
test's uncertainty (docs/acceptance.md)."""

from telefringe.metrology.acceptance.decision import DECISION_RULE, combine, decide
from telefringe.metrology.acceptance.evaluate import (
    ARTEFACT_KINDS,
    EDGE_PX,
    QUANTITIES,
    AcceptanceResult,
    Artefacts,
    Position,
    QuantityResult,
    SpreadSize,
    artefact_regions,
    evaluate_position,
    spread_probing_size,
    summarize,
)
from telefringe.metrology.acceptance.fits import LSPlane, LSSphere, ls_plane, ls_sphere
from telefringe.metrology.acceptance.quantities import (
    EXCLUDED_FRACTION,
    FlatnessTest,
    SpacingTest,
    SphereTest,
    cap_half_angle,
    flatness_error,
    probing_errors,
    sphere_spacing_error,
)

__all__ = ["ARTEFACT_KINDS", "DECISION_RULE", "EDGE_PX", "EXCLUDED_FRACTION", "QUANTITIES",
           "AcceptanceResult", "Artefacts", "FlatnessTest", "LSPlane", "LSSphere", "Position",
           "QuantityResult", "SpacingTest", "SphereTest", "SpreadSize", "artefact_regions",
           "cap_half_angle", "combine", "decide", "evaluate_position", "flatness_error",
           "ls_plane", "ls_sphere", "probing_errors", "sphere_spacing_error",
           "spread_probing_size", "summarize"]
