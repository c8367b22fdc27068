"""The acceptance test over all positions: the artefacts' certificate, the points of each
artefact in a scan, the characteristics per position, their maxima and the decisions."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from telefringe.metrology._common import MetrologyError, _components
from telefringe.metrology.acceptance.decision import DECISION_RULE, combine, decide
from telefringe.metrology.acceptance.fits import point_noise
from telefringe.metrology.acceptance.quantities import (
    EXCLUDED_FRACTION,
    FlatnessTest,
    SpacingTest,
    SphereTest,
    flatness_error,
    probing_errors,
    sphere_spacing_error,
)

__all__ = ["ARTEFACT_KINDS", "EDGE_PX", "QUANTITIES", "Artefacts", "Position", "QuantityResult",
           "AcceptanceResult", "SpreadSize", "artefact_regions", "evaluate_position",
           "spread_probing_size", "summarize"]

#: The artefacts of the test, as named in acceptance.json.
ARTEFACT_KINDS = ("sphere", "ball_bar", "plane")
#: The characteristics, in the order reported, and the artefact each is measured on.
QUANTITIES = {"PF": "sphere", "PS": "sphere", "SD": "ball_bar", "F": "plane"}


@dataclass(frozen=True)
class Artefacts:
    """The artefacts' certificate (calibrated values and standard uncertainties, mm).

    Attributes
    ----------
    sphere_diameter, u_sphere_diameter : the test sphere's diameter.
    sphere_form, u_sphere_form : its form deviation (peak to valley).
    bar_distance, u_bar_distance : the ball bar's centre distance.
    bar_diameters : (2,) its spheres' diameters (their PS is reported, not tested).
    plane_flatness, u_plane_flatness : the plane's flatness deviation.
    plane_length, plane_width : its size (information).
    """

    sphere_diameter: float
    u_sphere_diameter: float
    sphere_form: float
    u_sphere_form: float
    bar_distance: float
    u_bar_distance: float
    bar_diameters: tuple[float, float]
    plane_flatness: float
    u_plane_flatness: float
    plane_length: float = float("nan")
    plane_width: float = float("nan")

    def u_of(self, quantity: str) -> float:
        """Standard uncertainty (mm) the artefact adds to ``quantity``'s test value: its
        calibration's u, and for the form characteristics its own form deviation F_a as a
        rectangular distribution over [0, F_a] about its mean (F_a / sqrt(3) around 0),
        in quadrature."""
        if quantity == "PF":
            return float(np.hypot(self.u_sphere_form, self.sphere_form / np.sqrt(3.0)))
        if quantity == "PS":
            return float(self.u_sphere_diameter)
        if quantity == "SD":
            return float(self.u_bar_distance)
        if quantity == "F":
            return float(np.hypot(self.u_plane_flatness, self.plane_flatness / np.sqrt(3.0)))
        raise KeyError(quantity)


@dataclass(frozen=True)
class SpreadSize:
    """The test sphere's size error through the cameras' point-spread model: what PS
    would be if the points were free of the blur's bias on the sphere's curvature
    (:func:`spread_probing_size`). Reported beside PS, never in its place: PS is the
    guideline's, the size error of the points the instrument gives.

    Attributes
    ----------
    PS : float, mm, the model fit's diameter minus the calibrated one.
    u_fit_diameter : float, mm, the model fit's standard uncertainty of the diameter (the
        spread variances' uncertainty in it).
    n_points : int, the points the model fitted (those facing the cameras).
    variances_px2 : tuple of float, each camera's estimated spread variance, px^2.
    """

    PS: float
    u_fit_diameter: float
    n_points: int
    variances_px2: tuple


@dataclass(frozen=True, eq=False)
class Position:
    """One scan of the test: its artefact, what was measured, and where (pixels).

    Attributes
    ----------
    name : str, the scan's name.   kind : "sphere", "ball_bar" or "plane".
    test : SphereTest, SpacingTest or FlatnessTest.
    pixels : list of (k, 2) int arrays (row, col) of the points of each artefact region
        (one for a sphere or plane, two for a ball bar), in the order of the fit's points.
    shape : (rows, cols) of the camera image.
    """

    name: str
    kind: str
    test: SphereTest | SpacingTest | FlatnessTest
    pixels: list = field(default_factory=list)
    shape: tuple[int, int] = (0, 0)
    spread: SpreadSize | None = None

    def spread_bias(self) -> bool | None:
        """The test sphere's PS and its point-spread model's differ by more than 2 x the
        root sum of squares of their fit uncertainties (k = 2; the two fits share their
        points, so the difference's true uncertainty is smaller and the flag errs on the
        quiet side): the points' blur bias is a significant part of PS. None without the
        model."""
        if self.spread is None or self.kind != "sphere":
            return None
        u = np.hypot(self.test.u_fit_diameter, self.spread.u_fit_diameter)
        return bool(abs(self.test.PS - self.spread.PS) > 2.0 * u)

    def value(self, quantity: str) -> float:
        t = self.test
        return float(getattr(t, quantity))

    def u_fit(self, quantity: str) -> float:
        """Standard uncertainty (mm) of the value from the fit's own scatter (PS, SD);
        0 for the ranges PF and F."""
        if quantity == "PS":
            return float(self.test.u_fit_diameter)
        if quantity == "SD":
            return float(self.test.u_fit_distance)
        return 0.0

    def residual_map(self) -> np.ndarray:
        """(rows, cols) mm: each artefact point's residual (radial for spheres, normal
        for the plane); NaN elsewhere and at excluded points."""
        out = np.full(self.shape, np.nan)
        tests = self.test.spheres if isinstance(self.test, SpacingTest) else (self.test,)
        for t, px in zip(tests, self.pixels, strict=True):
            kept_px = px[t.kept]
            res = (t.fit.residuals if isinstance(t, SphereTest)
                   else t.residuals[t.kept])
            out[kept_px[:, 0], kept_px[:, 1]] = res
        return out


@dataclass(frozen=True, eq=False)
class QuantityResult:
    """One characteristic over its positions (mm).

    Attributes
    ----------
    name : "PF", "PS", "SD" or "F".
    positions : names of the scans.   values : (n,) per position.
    U : (n,) expanded uncertainty (k = 2) of each value as a test value.
    max_value : the largest value (PF, F) or the value of largest magnitude (PS, SD,
        sign kept); max_position : its scan.
    mpe : float or None.   decisions : per position, or () without an MPE.
    verdict : "PASS", "FAIL", "UNDECIDED" or "" without an MPE.
    """

    name: str
    positions: tuple[str, ...]
    values: np.ndarray
    U: np.ndarray
    max_value: float
    max_position: str
    mpe: float | None = None
    decisions: tuple[str, ...] = ()
    verdict: str = ""


@dataclass(frozen=True, eq=False)
class AcceptanceResult:
    """The whole test: one :class:`QuantityResult` per characteristic, the positions, the
    exclusion used and the decision rule."""

    quantities: dict
    positions: tuple[Position, ...]
    excluded_fraction: float
    decision_rule: str = DECISION_RULE

    @property
    def verdict(self) -> str:
        """Over all characteristics that have an MPE ("" when none has)."""
        v = [q.verdict for q in self.quantities.values() if q.verdict]
        return combine(v) if v else ""


#: Pixels taken off the border of every artefact region by default (see
#: :func:`evaluate_position`).
EDGE_PX = 2


def artefact_regions(mask, count: int, *, erode_px: int = EDGE_PX, min_pixels: int = 20):
    """The ``count`` largest connected regions (8-neighbourhood) of valid pixels, each
    shrunk by ``erode_px`` pixels (silhouette pixels mix the artefact with what lies
    behind it), ordered by their mean column (left to right).

    Parameters
    ----------
    mask : (rows, cols) bool, the pixels with a valid point.
    count : 1 (sphere, plane) or 2 (ball bar).

    Returns
    -------
    list of (rows, cols) bool

    Raises
    ------
    MetrologyError
        Fewer than ``count`` regions of at least ``min_pixels`` pixels.
    """
    from scipy import ndimage

    labels, n = _components(np.asarray(mask, dtype=bool))
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    order = np.argsort(sizes)[::-1][:count]
    regions = []
    for k in order:
        r = labels == (k + 1)
        if erode_px > 0:
            r = ndimage.binary_erosion(r, iterations=int(erode_px))
        if r.sum() >= min_pixels:
            regions.append(r)
    if len(regions) < count:
        raise MetrologyError(f"{count} artefact region(s) of at least {min_pixels} pixels "
                             f"needed, found {len(regions)}")
    return sorted(regions, key=lambda r: float(np.nonzero(r)[1].mean()))


def evaluate_position(name: str, kind: str, xyz, mask, artefacts: Artefacts, *,
                      exclude: float = EXCLUDED_FRACTION, erode_px: int = EDGE_PX,
                      noise=None, directions=None) -> Position:
    """The characteristics of one scan.

    Parameters
    ----------
    name : the scan's name.   kind : "sphere", "ball_bar" or "plane".
    xyz : (rows, cols, 3) mm, the scan's points per camera pixel.
    mask : (rows, cols) bool, valid points.
    artefacts : the certificate.
    exclude : share of points that may be excluded (0.3 %).
    erode_px : pixels taken off each region's border: there the camera's blur mixes the
        artefact with what lies behind it (on the virtual rigs a 1-pixel border left
        outliers of 100 um in F and a PS bias of +37 um, 2 pixels none; docs/acceptance.md).
    noise : StereoNoise, optional, a two-camera scan's: the matches' noise split
        (:func:`telefringe.reconstruction.stereo.match_noise`, on the grid of ``xyz``),
        with ``directions`` ((3,) or (rows, cols, 3), the cloud's viewing directions).
        Neighbouring matches share the second camera's pixels; with it the spheres' fit
        uncertainty (PS, SD) holds that correlation, without it the points count as
        independent (which understates it). PF and F, ranges, are the same either way.

    Returns
    -------
    Position
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool) & np.all(np.isfinite(xyz), axis=-1)
    if kind not in ARTEFACT_KINDS:
        raise MetrologyError(f"unknown artefact {kind!r} (known: {', '.join(ARTEFACT_KINDS)})")
    if (noise is None) != (directions is None):
        raise MetrologyError("noise and directions go together (the points' noise moves "
                             "them along their viewing directions)")
    regions = artefact_regions(mask, 2 if kind == "ball_bar" else 1, erode_px=erode_px)
    pixels = [np.argwhere(r) for r in regions]
    pts = [xyz[px[:, 0], px[:, 1]] for px in pixels]
    nz = [None] * len(pixels)
    if noise is not None and kind != "plane":
        if np.shape(noise.var_own) != mask.shape:
            raise MetrologyError(f"noise has shape {np.shape(noise.var_own)}, the scan "
                                 f"{mask.shape}")
        nz = [point_noise(noise, directions, px) for px in pixels]
    if kind == "sphere":
        test = probing_errors(pts[0], artefacts.sphere_diameter, exclude=exclude,
                              noise=nz[0])
    elif kind == "ball_bar":
        test = sphere_spacing_error(pts[0], pts[1], artefacts.bar_distance,
                                    artefacts.bar_diameters, exclude=exclude,
                                    noise=None if nz[0] is None else tuple(nz))
    else:
        test = flatness_error(pts[0], exclude=exclude)
    return Position(name=name, kind=kind, test=test, pixels=pixels, shape=mask.shape)


def spread_probing_size(position: Position, cloud, artefacts: Artefacts, rig, image, *,
                        image_2=None, fringe_periods=None, noise=None) -> Position:
    """The test sphere's size error through the cameras' point-spread model, added to
    its position (``spread``).

    The same points as PS (the eroded region) are fitted through the model of
    :func:`telefringe.metrology.spheres.measure_sphere` (each camera's spread variance
    estimated with the sphere; only points facing the cameras within 60 deg). A camera
    averages the fringes over its point spread, which on a curved surface moves every
    point along its line, inward near the top and outward toward the limb; a
    free-radius fit of a cap turns that into a too-large diameter. On the ``stereo``
    preset binned 4 x 4 (true rig, 10 spheres) PS was +13.1 to +24.3 um for U 3.4-4.3 um
    and the model's -6.0 to +5.6 um (mean +0.6) for its 2u 6.8-8.5 um (both with the
    matches' correlated noise); on the ``mixed``
    rig -1.1 to +6.7 um (mean +2.5) and -4.7 to +5.2 um (mean +0.2)
    (``benchmarks/acceptance_ps_bias.py``).

    Parameters
    ----------
    position : Position of a test sphere (``kind`` "sphere").
    cloud : PointCloud the position was evaluated on (mm).
    artefacts : the certificate.
    rig, image, image_2, fringe_periods, noise : as for
        :func:`telefringe.metrology.spheres.measure_sphere` (one camera and the projector,
        or two cameras and the projector; ``image`` the first camera's brightness).

    Returns
    -------
    Position, with ``spread`` set.

    Raises
    ------
    MetrologyError
        Not a test sphere, or what the model refuses.
    """
    from dataclasses import replace

    from telefringe.metrology.spheres import measure_sphere_region

    if position.kind != "sphere":
        raise MetrologyError(f"the point-spread size is the test sphere's, not a "
                             f"{position.kind}'s")
    region = np.zeros(position.shape, dtype=bool)
    px = position.pixels[0]
    region[px[:, 0], px[:, 1]] = True
    m = measure_sphere_region(cloud, region, rig, image, image_2=image_2,
                              fringe_periods=fringe_periods, noise=noise)
    sp = m.spread
    var = (sp.variance_px2,) if sp.variance_2_px2 is None else (sp.variance_px2,
                                                                sp.variance_2_px2)
    size = SpreadSize(PS=float(2.0 * m.sphere.radius - artefacts.sphere_diameter),
                      u_fit_diameter=float(2.0 * m.sphere.sigma_radius),
                      n_points=int(m.fitted.sum()), variances_px2=tuple(map(float, var)))
    return replace(position, spread=size)


def summarize(positions, artefacts: Artefacts, mpe: dict | None = None, *,
              exclude: float = EXCLUDED_FRACTION) -> AcceptanceResult:
    """Per characteristic: the values at every position of its artefact, their maximum,
    the test uncertainty of each (artefact certificate and fit, k = 2) and, with an MPE,
    the decisions (:data:`~telefringe.metrology.acceptance.decision.DECISION_RULE`).

    Parameters
    ----------
    positions : sequence of Position.
    artefacts : Artefacts.
    mpe : {"PF": mm, "PS": mm, "SD": mm, "F": mm}, any subset, or None.

    Returns
    -------
    AcceptanceResult
    """
    mpe = dict(mpe or {})
    bad = set(mpe) - set(QUANTITIES)
    if bad:
        raise ValueError(f"unknown MPE {sorted(bad)} (known: {', '.join(QUANTITIES)})")
    out = {}
    for q, kind in QUANTITIES.items():
        pos = [p for p in positions if p.kind == kind]
        if not pos:
            continue
        vals = np.array([p.value(q) for p in pos])
        U = 2.0 * np.hypot(artefacts.u_of(q), np.array([p.u_fit(q) for p in pos]))
        i = int(np.argmax(np.abs(vals)))
        decisions, verdict, m = (), "", mpe.get(q)
        if m is not None:
            decisions = tuple(decide(v, u, m) for v, u in zip(vals, U, strict=True))
            verdict = combine(decisions)
        out[q] = QuantityResult(name=q, positions=tuple(p.name for p in pos), values=vals,
                                U=U, max_value=float(vals[i]), max_position=pos[i].name,
                                mpe=None if m is None else float(m), decisions=decisions,
                                verdict=verdict)
    return AcceptanceResult(quantities=out, positions=tuple(positions),
                            excluded_fraction=float(exclude))
