"""Interpretation-tree matching of scene patches to a priori model features (the paper's section 4).

Scene side: every patch labelled PLAN, CYL, CONE or SPH with a successful dedicated fit becomes a
:class:`SceneItem` (sensor frame) with its uncertainties inflated to tolerances (DESIGN 6.3: fit covariances
are overconfident, so ``k`` times the propagated sigma with a floor that grows as patches shrink). Model
side: :func:`model_elements` turns the a priori :class:`scenes.model.SceneModel` into arrays of elements
(world frame): plane faces and cylinder caps (PLAN), cylinder sides (CYL), cones (CONE), spheres (SPH).

The search (:func:`match`) assigns each item a model element or a wildcard (spurious, changed or
misclassified patch). It is an interpretation tree cut at the depth where the pose is fixed (DESIGN 6.3):

* unary constraints: type, invariants within tolerance (radius, half-angle), a visible length or extent
  no larger than the model's, an area no larger than the model face's; with a pose prior, the item moved
  by the prior must lie near the candidate;
* binary constraints against every earlier pair, tested for all candidates of a node at once on arrays:
  angles between normals/axes, distances between parallel planes, from axes and centres to planes,
  between axes, between centres, and between the two items' positions, which must both lie on their
  elements (a face, an axis segment: ``ModelElements.bound_centre`` and ``bound_radius``);
* items ordered by fewest candidates (tempered by size: small patches are the likeliest spurious); seeds
  of 2-3 items are enumerated by their last item - (0,1), (0,2), (1,2), (0,3), ... - so a spurious item
  costs a few seeds, never a whole subtree, and every item is tried early;
* as soon as a seed's pairs constrain 6 DOF (a cheap model-frame test, then the closed form of
  :mod:`recognition.pose`), every other item is tested against that pose at once, on flat arrays of all
  (item, candidate) pairs, taking its best consistent element or a wildcard: a *leaf*. Leaves with more
  than ``max_wildcard_fraction * n + extra_wildcards`` wildcards are dropped; a pose seen before is not
  tested again;
* a node budget and a time budget (CPU, with a wall-clock cap): the search stops with what it has and says
  why (``MatchResult.stop_reason``); it also stops once a leaf explains ``stop_fraction`` of the items;
* the best leaves are then refined with all their pairs (weighted Gauss-Newton) and completed again.
  When no seed fixes 6 DOF, the largest partial assignments are returned as underconstrained hypotheses.

Hypotheses are deduplicated by pose and ranked by the summed ``log(pixels)`` of their matched items; the
list handed to the caller, who verifies them (:mod:`recognition.verify`), holds the best half by that score
and, for every item, the best hypothesis that explains it (:func:`_diverse`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from recognition.describe import SceneDescription
from recognition.pose import AxisPair, Pair, PlanePair, PointPair, PoseEstimate, estimate_pose, pose_hypotheses
from recognition.primitives import ConeFit, CylinderFit, PlaneFit, SphereFit
from scenes.features import Cone, Cylinder, Plane, Sphere
from scenes.geometry import perpendicular_basis
from scenes.model import SceneModel

__all__ = [
    "MatchParams",
    "ModelElements",
    "SceneItem",
    "Hypothesis",
    "MatchResult",
    "model_elements",
    "scene_items",
    "make_pair",
    "match",
    "pose_consistency",
]

KINDS = ("PLAN", "CYL", "CONE", "SPH")
_GEOM = {"PLAN": 0, "CYL": 1, "CONE": 1, "SPH": 2}  # 0 plane, 1 line, 2 point
_DIMS = {"PLAN": 3, "CYL": 4, "CONE": 5, "SPH": 3}  # constraints a pair gives (at most)


@dataclass(frozen=True)
class MatchParams:
    """Tolerances and limits of the interpretation tree.

    Attributes
    ----------
    min_pixels : patches smaller than this are not matched in the first stage.
    max_items : at most this many items (largest first) enter the tree.
    k_sigma : tolerance = ``k_sigma`` x the propagated sigma, combined with the floors below.
    angle_floor_rad : floor of the angle tolerance for a large patch (radians).
    angle_floor_px_rad : floor term growing as patches shrink: ``angle_floor_px_rad * sqrt(1000 / n_px)``.
    dist_floor_m, dist_floor_rel : floor of distance tolerances, ``dist_floor_m + dist_floor_rel * range``.
    radius_rel_tol : relative floor of the radius tolerance.
    half_angle_tol_rad : floor of the cone half-angle tolerance.
    length_slack : visible lengths/extents may exceed the model's by this factor (segmentation bleed).
    width_test : a plane patch's least in-plane width (over directions 5 deg apart) must also be within
        ``length_slack`` of its face's short side: a wall patch 1.5 m high pairs with no wall top or
        partition end 0.2 m deep, which the length and area tests let through (of a Kinect-like view's
        wall, 8 of its 17 candidates). On the calibration suite: constrained pose success 15/19 -> 16/19,
        the same 4 trials ok but wrong.
    width_trim : quantiles ``width_trim`` and ``1 - width_trim`` of the projections bound each width.
    max_wildcard_fraction, extra_wildcards : at most ``fraction * n_items + extra`` wildcards.
    max_nodes : node budget of the search (the limit that binds on ordinary scenes: deterministic).
    max_hypotheses : at most this many hypotheses are returned (half by score, half the best per item).
    max_time_s : CPU time budget of the search (seconds of this process), a safety net for pathological
        inputs (the node budget binds first otherwise, so results do not depend on the machine's load): it
        stops with the best hypotheses found so far ... The default suite's slowest searches take 0.6 s of
        CPU on an idle machine for the node budget, and up to twice that under the benchmark's two workers:
        with 1 s one of them stopped on time, at a load-dependent node.
    max_wall_s : ... and a wall-clock cap, whatever the load.
    size_weight : items are taken in order of ``log(candidates + 1) - size_weight * log(pixels)`` (fewest
        candidates first, small patches - the likeliest spurious - later; items without candidates are
        dropped before the search: they can only be wildcards). 0.5 put a factory view's large walls (9
        candidates each) before its one-candidate pipes, whose pair fixes the pose at once, and spent the
        node budget on plane triples (a wall's far face won by 0.33 m); 0.25 keeps mock-up and factory
        constrained trials at 100 % and leaves the Kinect-like ones unchanged.
    max_seed_size : at most this many pairs in a seed (the pairs that fix the pose before the others are
        tested against it).
    stop_fraction : the search stops once a hypothesis explains this fraction of the items' summed weight
        (after every pairing of the items seen so far has been tried, at least four items).
    bound_ratio : kept for compatibility (the depth-limited search has no branch-and-bound step).
    pose_chi2_factor : a pose fit is accepted when its whitened cost <= factor x residual count (+ 10).
    length_m : characteristic length (m) for the free-DOF test; 0 = the median range of the items.
    max_free_sigma : a direction with a larger sigma (rad, or ``length_m`` units) counts as free.
    prior_angle_rad, prior_dist_m : tolerances of the unary test against a pose prior (None: no prior test).
    """

    min_pixels: int = 150
    max_items: int = 30
    k_sigma: float = 3.0
    angle_floor_rad: float = math.radians(1.0)
    angle_floor_px_rad: float = math.radians(1.5)
    dist_floor_m: float = 0.002
    dist_floor_rel: float = 0.004
    radius_rel_tol: float = 0.08
    half_angle_tol_rad: float = math.radians(3.0)
    length_slack: float = 1.15
    width_test: bool = True
    width_trim: float = 0.01
    max_wildcard_fraction: float = 0.4
    extra_wildcards: int = 2
    max_nodes: int = 1500
    max_hypotheses: int = 12
    bound_ratio: float = 0.7
    max_time_s: float = 3.0
    max_wall_s: float = 6.0
    size_weight: float = 0.25
    max_seed_size: int = 3
    stop_fraction: float = 0.9
    pose_chi2_factor: float = 9.0
    length_m: float = 0.0
    max_free_sigma: float = 0.1
    prior_angle_rad: float | None = None
    prior_dist_m: float | None = None

    def __post_init__(self):
        for name in ("k_sigma", "dist_floor_rel", "radius_rel_tol", "length_slack", "pose_chi2_factor",
                     "max_free_sigma", "max_time_s", "max_wall_s", "stop_fraction"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("min_pixels", "max_items", "max_nodes", "max_hypotheses", "max_seed_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0 <= self.max_wildcard_fraction <= 1:
            raise ValueError(f"max_wildcard_fraction must be in [0, 1], got {self.max_wildcard_fraction}")
        if self.extra_wildcards < 0 or self.length_m < 0:
            raise ValueError("extra_wildcards and length_m must be >= 0")
        if not 0 <= self.width_trim < 0.5:
            raise ValueError(f"width_trim must be in [0, 0.5), got {self.width_trim}")


# ---------------------------------------------------------------------------------------------------------
# model side


@dataclass(frozen=True)
class ModelElements:
    """Matchable model surfaces as arrays (world frame, metres, radians).

    Attributes
    ----------
    kind : ndarray of shape (E,) of str, PLAN/CYL/CONE/SPH.
    feature_id, part : ndarray of shape (E,) of str.
    direction : ndarray of shape (E, 3), outward plane normal or axis (cone: from the apex); zeros for spheres.
    position : ndarray of shape (E, 3), plane/cap centre, axis segment centre, cone apex, sphere centre.
    radius : ndarray of shape (E,), cylinder/sphere radius, disc radius of a cap; NaN otherwise.
    half_angle : ndarray of shape (E,), cone half-angle; NaN otherwise.
    length : ndarray of shape (E,), axis length (cylinder, cone frustum); NaN otherwise.
    start : ndarray of shape (E,), cone start distance from the apex (0 for cylinders: centred segment).
    u_axis : ndarray of shape (E, 3), in-plane axis of rectangles (NaN for discs).
    half_size : ndarray of shape (E, 2), rectangle half sizes (disc: radius, radius).
    area : ndarray of shape (E,), m².
    diag : ndarray of shape (E,), largest in-plane extent of a plane element (metres).
    bound_centre, bound_radius : ndarray of shape (E, 3) and (E,), a ball holding every place a scene item's
        ``position`` can take on the element: a plane's face, a cylinder's or cone's axis segment, a
        sphere's centre (metres). Bounds the distance between two items' positions (:func:`binary_ok`).
    """

    kind: np.ndarray
    feature_id: np.ndarray
    part: np.ndarray
    direction: np.ndarray
    position: np.ndarray
    radius: np.ndarray
    half_angle: np.ndarray
    length: np.ndarray
    start: np.ndarray
    u_axis: np.ndarray
    half_size: np.ndarray
    area: np.ndarray
    diag: np.ndarray
    bound_centre: np.ndarray
    bound_radius: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)

    def of_kind(self, kind: str) -> np.ndarray:
        return np.flatnonzero(self.kind == kind)


def model_elements(model: SceneModel) -> ModelElements:
    """The a priori model's matchable elements (tori are left to the second, proximity stage)."""
    rows: list[dict] = []
    nan3 = np.full(3, np.nan)
    for f in model.features:
        if isinstance(f, Plane):
            hu, hv = f.half_size
            rows.append(dict(kind="PLAN", fid=f.id, part="face", d=f.normal, p=f.centre, r=np.nan, ha=np.nan,
                             L=np.nan, s=0.0, u=f.u_axis, hs=(hu, hv), area=4 * hu * hv,
                             diag=2 * math.hypot(hu, hv), bc=f.centre, br=math.hypot(hu, hv)))
        elif isinstance(f, Cylinder):
            rows.append(dict(kind="CYL", fid=f.id, part="side", d=f.axis, p=f.centre, r=f.radius, ha=np.nan,
                             L=f.length, s=0.0, u=nan3, hs=(np.nan, np.nan), area=f.area(), diag=np.nan,
                             bc=f.centre, br=0.5 * f.length))
            for sign, part in ((-1.0, "cap_start"), (1.0, "cap_end")):
                cap = f.centre + sign * 0.5 * f.length * f.axis
                rows.append(dict(kind="PLAN", fid=f.id, part=part, d=sign * f.axis, p=cap, r=f.radius,
                                 ha=np.nan, L=np.nan, s=0.0, u=nan3, hs=(f.radius, f.radius),
                                 area=math.pi * f.radius**2, diag=2 * f.radius, bc=cap, br=f.radius))
        elif isinstance(f, Cone):
            rows.append(dict(kind="CONE", fid=f.id, part="side", d=f.axis, p=f.apex, r=np.nan, ha=f.half_angle,
                             L=f.end - f.start, s=f.start, u=nan3, hs=(np.nan, np.nan), area=f.area(),
                             diag=np.nan, bc=f.apex + 0.5 * (f.start + f.end) * f.axis, br=0.5 * (f.end - f.start)))
        elif isinstance(f, Sphere):
            rows.append(dict(kind="SPH", fid=f.id, part="surface", d=np.zeros(3), p=f.centre, r=f.radius,
                             ha=np.nan, L=np.nan, s=0.0, u=nan3, hs=(np.nan, np.nan), area=f.area(),
                             diag=np.nan, bc=f.centre, br=0.0))

    def col(key, dtype=np.float64):
        return np.array([r[key] for r in rows], dtype=dtype)

    if not rows:
        z = np.zeros(0)
        return ModelElements(z.astype(str), z.astype(str), z.astype(str), np.zeros((0, 3)), np.zeros((0, 3)), z,
                             z, z, z, np.zeros((0, 3)), np.zeros((0, 2)), z, z, np.zeros((0, 3)), z)
    return ModelElements(col("kind", object).astype(str), col("fid", object).astype(str),
                         col("part", object).astype(str), col("d").reshape(-1, 3), col("p").reshape(-1, 3),
                         col("r"), col("ha"), col("L"), col("s"), col("u").reshape(-1, 3),
                         col("hs").reshape(-1, 2), col("area"), col("diag"), col("bc").reshape(-1, 3), col("br"))


# ---------------------------------------------------------------------------------------------------------
# scene side


@dataclass(frozen=True)
class SceneItem:
    """A matchable scene patch (sensor frame), with tolerances.

    Attributes
    ----------
    patch_index : index into ``description.patches``; ``patch_id`` its id.
    kind : PLAN/CYL/CONE/SPH.
    direction : ndarray of shape (3,), plane normal facing the sensor, axis (cone: from the apex); zeros
        for spheres.
    position : ndarray of shape (3,), plane centroid, axis point nearest the data centroid, sphere centre.
    n_pixels : int; weight : ``log(n_pixels)``.
    radius, radius_tol : metres (cylinder, sphere; cone: radius at ``position``); NaN when not applicable.
    half_angle, half_angle_tol : radians (cone).
    length : visible extent along the axis (cylinder, cone) or largest in-plane extent (plane), metres.
    area : visible area estimate (plane), m².
    sigma_angle : per-component direction sigma used by the pose (radians, inflated).
    sigma_pos : per-component position sigma used by the pose (metres, inflated).
    angle_tol, dist_tol : tolerances of the tests (radians, metres).
    range_m : distance of the item from the sensor (metres).
    width : least in-plane width of a plane patch (metres, :func:`_min_width`); NaN for other kinds.
    """

    patch_index: int
    patch_id: int
    kind: str
    direction: np.ndarray
    position: np.ndarray
    n_pixels: int
    weight: float
    radius: float
    radius_tol: float
    half_angle: float
    half_angle_tol: float
    length: float
    area: float
    sigma_angle: float
    sigma_pos: float
    angle_tol: float
    dist_tol: float
    range_m: float
    width: float = float("nan")


def scene_items(description: SceneDescription, pixel_pitch_rad: float, params: MatchParams = MatchParams()
                ) -> list[SceneItem]:
    """Matchable items from the description's PLAN/CYL/CONE/SPH patches with a successful fit, largest
    first (at most ``params.max_items``)."""
    out: list[SceneItem] = []
    patches = sorted(range(len(description.patches)), key=lambda i: -description.patches[i].n_pixels)
    for i in patches:
        p = description.patches[i]
        fit = p.classification.primitive
        if p.label not in KINDS or fit is None or not getattr(fit, "ok", False) or p.n_pixels < params.min_pixels:
            continue
        item = _item(i, p, fit, pixel_pitch_rad, params)
        if item is not None:
            out.append(item)
        if len(out) >= params.max_items:
            break
    return out


def _item(index, patch, fit, pitch, params: MatchParams) -> SceneItem | None:
    pts = np.asarray(patch.points, dtype=np.float64)
    n = len(pts)
    centroid = pts.mean(axis=0)
    rng_m = float(np.linalg.norm(centroid))
    k = params.k_sigma
    floor_a = params.angle_floor_rad + params.angle_floor_px_rad * math.sqrt(1000.0 / max(n, 1))
    floor_d = params.dist_floor_m + params.dist_floor_rel * rng_m
    nan = float("nan")
    if patch.label == "PLAN" and isinstance(fit, PlaneFit):
        nv = np.asarray(fit.normal, dtype=np.float64)
        if nv @ centroid > 0:
            nv = -nv
        # offset sigma at the centroid (the tilt is about the weighted centroid: nearly uncorrelated)
        C = np.asarray(fit.cov)
        var_c = C[3, 3] - 2 * centroid @ C[:3, 3] + centroid @ C[:3, :3] @ centroid
        s_off = math.sqrt(max(var_c, 0.0)) if np.isfinite(var_c) else fit.offset_sigma
        s_ang = fit.normal_sigma_rad / math.sqrt(2)
        d = pts - centroid
        inplane = d - np.outer(d @ nv, nv)
        ev, evec = np.linalg.eigh(inplane.T @ inplane)
        proj = inplane @ evec[:, 2]
        extent = float(proj.max() - proj.min())
        rr = np.linalg.norm(pts, axis=1)
        cos_i = np.abs(pts @ nv) / np.maximum(rr, 1e-12)
        area = float(np.sum((rr * pitch) ** 2 / np.maximum(cos_i, 0.2)))
        return SceneItem(index, patch.id, "PLAN", nv, centroid, n, math.log(n), nan, nan, nan, nan, extent, area,
                         max(s_ang, floor_a / k), max(s_off, floor_d / k), k * s_ang + floor_a,
                         k * s_off + floor_d, rng_m, _min_width(inplane @ evec[:, 1:], params.width_trim))
    if patch.label == "CYL" and isinstance(fit, CylinderFit):
        C = np.asarray(fit.cov)
        s_pos = math.sqrt(max(np.trace(C[:3, :3]) / 2.0, 0.0)) if np.all(np.isfinite(C[:3, :3])) else floor_d
        s_ang = fit.axis_sigma_rad / math.sqrt(2)
        return SceneItem(index, patch.id, "CYL", np.asarray(fit.axis, float), np.asarray(fit.point, float), n,
                         math.log(n), fit.radius, k * fit.radius_sigma + params.radius_rel_tol * fit.radius,
                         nan, nan, fit.length, nan, max(s_ang, floor_a / k), max(s_pos, floor_d / k),
                         k * s_ang + floor_a, k * s_pos + floor_d + params.radius_rel_tol * fit.radius, rng_m)
    if patch.label == "CONE" and isinstance(fit, ConeFit):
        C = np.asarray(fit.cov)
        s_pos = math.sqrt(max(np.trace(C[:3, :3]) / 2.0, 0.0)) if np.all(np.isfinite(C[:3, :3])) else floor_d
        s_ang = fit.axis_sigma_rad / math.sqrt(2)
        return SceneItem(index, patch.id, "CONE", np.asarray(fit.axis, float), np.asarray(fit.point, float), n,
                         math.log(n), fit.radius_at_point,
                         k * math.sqrt(max(C[6, 6], 0.0)) + params.radius_rel_tol * fit.radius_at_point,
                         fit.half_angle, k * fit.half_angle_sigma + params.half_angle_tol_rad, fit.length, nan,
                         max(s_ang, floor_a / k), max(s_pos, floor_d / k), k * s_ang + floor_a,
                         k * s_pos + floor_d + params.radius_rel_tol * fit.radius_at_point, rng_m)
    if patch.label == "SPH" and isinstance(fit, SphereFit):
        C = np.asarray(fit.cov)
        s_pos = math.sqrt(max(np.trace(C[:3, :3]) / 3.0, 0.0)) if np.all(np.isfinite(C[:3, :3])) else floor_d
        return SceneItem(index, patch.id, "SPH", np.zeros(3), np.asarray(fit.centre, float), n, math.log(n),
                         fit.radius, k * fit.radius_sigma + params.radius_rel_tol * fit.radius, nan, nan, nan, nan,
                         floor_a / k, max(s_pos, floor_d / k), floor_a,
                         k * s_pos + floor_d + params.radius_rel_tol * fit.radius, rng_m)
    return None


# ---------------------------------------------------------------------------------------------------------
# constraints


_WIDTH_DIRECTIONS = 36  # in-plane directions (5 deg apart) over which the least width is sought
# the least of those widths exceeds the true least width by at most this share of the patch's extent
_WIDTH_STEP_ERROR = math.sin(math.pi / (2 * _WIDTH_DIRECTIONS))


def _min_width(uv: np.ndarray, trim: float, max_points: int = 2000) -> float:
    """Least width (metres) of in-plane points ``uv`` (N, 2) over ``_WIDTH_DIRECTIONS`` directions, each span
    taken between the ``trim`` and ``1 - trim`` quantiles (stray pixels off the face do not widen it); NaN
    for fewer than 3 points. A patch inside a rectangle is never wider than its short side."""
    if len(uv) < 3:
        return float("nan")
    if len(uv) > max_points:
        uv = uv[np.linspace(0, len(uv) - 1, max_points).astype(np.int64)]
    a = np.linspace(0.0, np.pi, _WIDTH_DIRECTIONS, endpoint=False)
    proj = uv @ np.stack([np.cos(a), np.sin(a)])  # (N, directions)
    lo, hi = np.quantile(proj, [trim, 1.0 - trim], axis=0)
    return float(np.min(hi - lo))


def unary_candidates(item: SceneItem, el: ModelElements, params: MatchParams,
                     prior: np.ndarray | None = None) -> np.ndarray:
    """Indices of the elements that pass the unary tests for ``item`` (and the pose prior test, if given)."""
    idx = el.of_kind(item.kind)
    if len(idx) == 0:
        return idx
    ok = np.ones(len(idx), dtype=bool)
    slack = params.length_slack
    if item.kind == "PLAN":
        ok &= item.length <= slack * el.diag[idx] + item.dist_tol
        ok &= item.area <= slack**2 * el.area[idx] + item.length * item.dist_tol
        if params.width_test and np.isfinite(item.width):
            ok &= item.width <= (slack * 2.0 * el.half_size[idx].min(axis=1) + item.dist_tol
                                 + _WIDTH_STEP_ERROR * item.length)
    elif item.kind in ("CYL", "SPH"):
        # a radius not known to within its own size (a wall strip fitted as a cylinder of 20 m) pairs with no
        # pipe or tank: any of them would pass, and its axis or centre would then fix the pose at random
        ok &= (np.abs(el.radius[idx] - item.radius) <= item.radius_tol) & (item.radius_tol < item.radius)
        if item.kind == "CYL":
            ok &= item.length <= slack * el.length[idx] + item.dist_tol
    elif item.kind == "CONE":
        ok &= np.abs(el.half_angle[idx] - item.half_angle) <= item.half_angle_tol
        ok &= item.length <= slack * el.length[idx] + item.dist_tol
        # the fitted radius must occur within the frustum
        h = item.radius / np.tan(np.maximum(el.half_angle[idx], 1e-6))
        ok &= (h >= el.start[idx] - item.dist_tol / np.maximum(np.tan(el.half_angle[idx]), 1e-3) - item.length)
        ok &= (h <= el.start[idx] + el.length[idx] + item.length
               + item.dist_tol / np.maximum(np.tan(el.half_angle[idx]), 1e-3))
    idx = idx[ok]
    if prior is not None and len(idx) and params.prior_angle_rad is not None and params.prior_dist_m is not None:
        res = pose_consistency(item, el, idx, prior, params.prior_angle_rad + item.angle_tol,
                               params.prior_dist_m + item.range_m * params.prior_angle_rad + item.dist_tol)
        idx = idx[np.isfinite(res)]
    return idx


def _row_norms(x: np.ndarray) -> np.ndarray:
    """Euclidean norms of the rows of ``x`` (N, 3): ``np.linalg.norm(x, axis=1)`` without its per-call overhead
    (the same arithmetic, so the same values)."""
    return np.sqrt(np.add.reduce(x * x, axis=1))


def _line_distance(p1, a1, p2, a2):
    """Distance between lines (p1, a1) (3,) and (P2, A2) (N, 3); parallel lines use the perpendicular."""
    c = np.cross(a1, a2)
    cn = np.linalg.norm(c, axis=-1)
    d = p2 - p1
    par = cn < 1e-3
    with np.errstate(invalid="ignore", divide="ignore"):
        skew_d = np.abs(np.sum(d * c, axis=-1)) / np.where(par, 1.0, cn)
    perp = d - np.outer(d @ a1, a1) if d.ndim == 2 else d - (d @ a1) * a1
    par_d = np.linalg.norm(perp, axis=-1)
    return np.where(par, par_d, skew_d)


def _point_line_distance(p, a, q):
    d = q - p
    along = d @ a if d.ndim == 1 else np.sum(d * a, axis=-1)
    perp = d - (along[..., None] * a if np.ndim(along) else along * a)
    return np.linalg.norm(perp, axis=-1)


def binary_ok(i_item: SceneItem, e_i: int, j_item: SceneItem, cand: np.ndarray, el: ModelElements,
              length_slack: float = MatchParams.length_slack) -> np.ndarray:
    """Boolean mask over ``cand`` (element indices for ``j_item``) consistent with the pair
    ``(i_item, e_i)``: angle between directions, a distance measure, and the distance between the items'
    positions within the bounds of their elements (``length_slack``: segmentation bleed, as in the unary
    tests), all vectorised over ``cand``."""
    gi, gj = _GEOM[i_item.kind], _GEOM[j_item.kind]
    ang_tol = math.hypot(i_item.angle_tol, j_item.angle_tol)
    dm = el.direction[cand]
    di_m = el.direction[e_i]
    pi_m, pj_m = el.position[e_i], el.position[cand]
    ds_i, ds_j = i_item.direction, j_item.direction
    ps_i, ps_j = i_item.position, j_item.position
    lever = float(np.linalg.norm(ps_j - ps_i))
    dist_tol = math.hypot(i_item.dist_tol, j_item.dist_tol) + lever * ang_tol
    # each position lies on its element (a face, an axis segment, a centre): within the elements' balls
    bleed = 0.5 * (length_slack - 1.0) * sum(it.length for it in (i_item, j_item) if np.isfinite(it.length))
    gap = _row_norms(el.bound_centre[cand] - el.bound_centre[e_i])
    ok = np.abs(gap - lever) <= el.bound_radius[cand] + el.bound_radius[e_i] + dist_tol + bleed
    if gi < 2 and gj < 2:
        cs = float(ds_i @ ds_j)
        cm = dm @ di_m
        if gi == 0 and gj == 0:  # signed: plane normals both face the sensor / outward
            ang_s, ang_m = math.acos(np.clip(cs, -1, 1)), np.arccos(np.clip(cm, -1, 1))
        else:
            ang_s, ang_m = math.acos(min(abs(cs), 1.0)), np.arccos(np.clip(np.abs(cm), 0, 1))
        ok &= np.abs(ang_m - ang_s) <= ang_tol
    # distances
    if gi == 0 and gj == 0:
        par_m = np.abs(dm @ di_m) > math.cos(math.radians(2.0))
        s_d = float(ds_i @ (ps_j - ps_i))
        m_d = (pj_m - pi_m) @ di_m
        ok &= ~par_m | (np.abs(m_d - s_d) <= dist_tol)
    elif {gi, gj} == {0, 1} or {gi, gj} == {0, 2}:
        if gi == 0:
            n_s, q_s, q_sp = ds_i, ps_i, ps_j
            n_m, q_m, q_mp = np.broadcast_to(di_m, dm.shape), np.broadcast_to(pi_m, pj_m.shape), pj_m
            line_dir_m = dm
        else:
            n_s, q_s, q_sp = ds_j, ps_j, ps_i
            n_m, q_m, q_mp = dm, pj_m, np.broadcast_to(pi_m, pj_m.shape)
            line_dir_m = np.broadcast_to(di_m, dm.shape)
        s_d = float(n_s @ (q_sp - q_s))
        m_d = np.sum(n_m * (q_mp - q_m), axis=1)
        if 1 in (gi, gj):
            applies = np.abs(np.sum(n_m * line_dir_m, axis=1)) < math.sin(math.radians(2.0))
        else:
            applies = np.ones(len(cand), dtype=bool)
        ok &= ~applies | (np.abs(m_d - s_d) <= dist_tol)
    elif gi == 1 and gj == 1:
        s_d = float(_line_distance(ps_i, ds_i, ps_j[None, :], ds_j[None, :])[0])
        m_d = _line_distance(pi_m, di_m, pj_m, dm)
        ok &= np.abs(m_d - s_d) <= dist_tol
    elif {gi, gj} == {1, 2}:
        if gi == 1:
            s_d = float(_point_line_distance(ps_i, ds_i, ps_j))
            m_d = _point_line_distance(pi_m, di_m, pj_m)
        else:
            s_d = float(_point_line_distance(ps_j, ds_j, ps_i))
            m_d = np.linalg.norm(np.cross(pi_m - pj_m, dm), axis=1)
        ok &= np.abs(m_d - s_d) <= dist_tol
    else:  # point-point
        s_d = lever
        m_d = np.linalg.norm(pj_m - pi_m, axis=1)
        ok &= np.abs(m_d - s_d) <= dist_tol
    return ok


def pose_consistency(item: SceneItem, el: ModelElements, cand: np.ndarray, T: np.ndarray, angle_tol: float,
                     dist_tol: float) -> np.ndarray:
    """Normalised misfit (N,) of ``item`` moved by ``T_world_sensor`` against elements ``cand``; ``inf``
    where it fails (direction, position across, extent along/in-plane).

    The misfit is ``max(angle / angle_tol, distance / dist_tol)`` (smaller is better)."""
    R, t = T[:3, :3], T[:3, 3]
    d_w = R @ item.direction
    p_w = R @ item.position + t
    dm = el.direction[cand]
    pm = el.position[cand]
    half_len = 0.5 * (item.length if np.isfinite(item.length) else 0.0)
    if item.kind == "PLAN":
        ang = np.arccos(np.clip(dm @ d_w, -1, 1))
        dist = np.abs(np.sum(dm * (p_w - pm), axis=1))
        w = p_w - pm
        hs = el.half_size[cand]
        u = el.u_axis[cand]
        is_rect = np.isfinite(u[:, 0])
        v = np.cross(dm, np.where(is_rect[:, None], u, 0.0))
        eu = np.abs(np.sum(w * np.where(is_rect[:, None], u, 0.0), axis=1)) - hs[:, 0]
        ev = np.abs(np.sum(w * v, axis=1)) - hs[:, 1]
        rad = np.linalg.norm(w - np.sum(w * dm, axis=1)[:, None] * dm, axis=1) - hs[:, 0]
        excess = np.where(is_rect, np.maximum(eu, ev), rad)
        inside = excess <= half_len + dist_tol
    elif item.kind in ("CYL", "CONE"):
        c = np.abs(dm @ d_w) if item.kind == "CYL" else dm @ d_w
        ang = np.arccos(np.clip(c, -1, 1))
        w = p_w - pm
        along = np.sum(w * dm, axis=1)
        dist = np.linalg.norm(w - along[:, None] * dm, axis=1)
        if item.kind == "CYL":
            excess = np.abs(along) - 0.5 * el.length[cand]
            inside = excess <= half_len + dist_tol
            rerr = np.zeros(len(cand))
        else:
            lo, hi = el.start[cand], el.start[cand] + el.length[cand]
            inside = (along >= lo - half_len - dist_tol) & (along <= hi + half_len + dist_tol)
            # radius at the fitted point vs the model's radius there
            rerr = np.abs(along * np.tan(el.half_angle[cand]) - item.radius)
            dist = np.maximum(dist, rerr)
    else:
        ang = np.zeros(len(cand))
        dist = np.linalg.norm(p_w - pm, axis=1)
        inside = np.ones(len(cand), dtype=bool)
    mis = np.maximum(ang / angle_tol, dist / dist_tol)
    return np.where((mis <= 1.0) & inside, mis, np.inf)


def make_pair(item: SceneItem, el: ModelElements, e: int) -> Pair:
    """The pose correspondence of ``item`` and element ``e``."""
    if item.kind == "PLAN":
        n_m = el.direction[e]
        return PlanePair(item.direction, item.position, n_m, float(n_m @ el.position[e]), item.sigma_angle,
                         item.sigma_pos)
    if item.kind == "CYL":
        return AxisPair(item.direction, item.position, el.direction[e], el.position[e], item.sigma_angle,
                        item.sigma_pos, signed=False)
    if item.kind == "CONE":
        ta = math.tan(float(el.half_angle[e]))
        along = item.radius / max(ta, 1e-6)
        s_along = max(item.radius_tol / 3.0, item.sigma_pos) / max(ta, 1e-6)
        return AxisPair(item.direction, item.position, el.direction[e], el.position[e], item.sigma_angle,
                        item.sigma_pos, signed=True, along_m=along, sigma_along=s_along)
    return PointPair(item.position, el.position[e], item.sigma_pos)


# ---------------------------------------------------------------------------------------------------------
# the search


@dataclass(frozen=True)
class Hypothesis:
    """A leaf of the tree.

    Attributes
    ----------
    pairs : tuple of (item index, element index or -1 for a wildcard), one per item in the tree.
    pose : the pose from all matched pairs.
    score : summed ``log(pixels)`` of the matched items.
    n_matched : int
    """

    pairs: tuple[tuple[int, int], ...]
    pose: PoseEstimate
    score: float
    n_matched: int


@dataclass(frozen=True)
class MatchResult:
    """Hypotheses (best score first), the items and elements they index, and search statistics
    (``stop_reason``: why the search stopped early - node or time budget - or "" when it completed).
    ``matchable``: the patch indices of every scene item, those without a candidate element included."""

    hypotheses: tuple[Hypothesis, ...]
    items: tuple[SceneItem, ...]
    elements: ModelElements
    n_nodes: int
    exhausted: bool
    candidates: tuple[int, ...] = field(default=())
    stop_reason: str = ""
    matchable: frozenset[int] = frozenset()


class _FlatPairs:
    """Every (item, candidate element) pair of the tree as flat arrays, so that a fixed pose is tested against
    all remaining items and all their candidates at once (DESIGN 6.3: no per-pair numpy calls)."""

    def __init__(self, items, el: ModelElements, cands):
        self.el = el
        self.n_items = len(items)
        self.groups = []
        for kind in KINDS:
            it_idx = [i for i, it in enumerate(items) if it.kind == kind and len(cands[i])]
            if not it_idx:
                continue
            ii = np.concatenate([np.full(len(cands[i]), i) for i in it_idx]).astype(np.intp)
            ee = np.concatenate([cands[i] for i in it_idx]).astype(np.intp)
            g = dict(kind=kind, item=ii, el=ee,
                     d=np.array([items[i].direction for i in ii]).reshape(-1, 3),
                     p=np.array([items[i].position for i in ii]).reshape(-1, 3),
                     half_len=np.array([0.5 * items[i].length if np.isfinite(items[i].length) else 0.0
                                        for i in ii]),
                     radius=np.array([items[i].radius for i in ii]),
                     ang_tol=np.array([items[i].angle_tol for i in ii]),
                     dist_tol=np.array([items[i].dist_tol for i in ii]),
                     dm=el.direction[ee], pm=el.position[ee], hs=el.half_size[ee], u=el.u_axis[ee],
                     length=el.length[ee], start=el.start[ee], half_angle=el.half_angle[ee])
            g["is_rect"] = np.isfinite(g["u"][:, 0])
            g["u0"] = np.where(g["is_rect"][:, None], g["u"], 0.0)
            g["v0"] = np.cross(g["dm"], g["u0"])
            self.groups.append(g)

    def best(self, T: np.ndarray, ang_scale: float, dist_scale: float, lever_sigma: float, centre: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """For every item: the best consistent element under ``T`` (-1: none) and its misfit (inf: none).

        Tolerances are ``ang_scale`` x the item's angle tolerance and ``dist_scale`` x its distance tolerance
        plus ``lever_sigma`` x the item's distance from ``centre`` (sensor frame; the seed pose's rotation
        uncertainty moves far items more)."""
        R, t = T[:3, :3], T[:3, 3]
        best_e = np.full(self.n_items, -1, dtype=np.intp)
        best_m = np.full(self.n_items, np.inf)
        for g in self.groups:
            d_w = g["d"] @ R.T
            p_w = g["p"] @ R.T + t
            dm, pm = g["dm"], g["pm"]
            lever = _row_norms(g["p"] - centre)
            atol = ang_scale * g["ang_tol"] + lever_sigma
            dtol = dist_scale * g["dist_tol"] + lever_sigma * lever
            w = p_w - pm
            hl = g["half_len"]
            kind = g["kind"]
            if kind == "PLAN":
                ang = np.arccos(np.clip(np.sum(dm * d_w, axis=1), -1, 1))
                dist = np.abs(np.sum(dm * w, axis=1))
                eu = np.abs(np.sum(w * g["u0"], axis=1)) - g["hs"][:, 0]
                ev = np.abs(np.sum(w * g["v0"], axis=1)) - g["hs"][:, 1]
                rad = _row_norms(w - np.sum(w * dm, axis=1)[:, None] * dm) - g["hs"][:, 0]
                excess = np.where(g["is_rect"], np.maximum(eu, ev), rad)
                inside = excess <= hl + dtol
            elif kind in ("CYL", "CONE"):
                c = np.sum(dm * d_w, axis=1)
                ang = np.arccos(np.clip(np.abs(c) if kind == "CYL" else c, -1, 1))
                along = np.sum(w * dm, axis=1)
                dist = _row_norms(w - along[:, None] * dm)
                if kind == "CYL":
                    inside = np.abs(along) - 0.5 * g["length"] <= hl + dtol
                else:
                    lo, hi = g["start"], g["start"] + g["length"]
                    inside = (along >= lo - hl - dtol) & (along <= hi + hl + dtol)
                    dist = np.maximum(dist, np.abs(along * np.tan(g["half_angle"]) - g["radius"]))
            else:
                ang = np.zeros(len(dm))
                dist = _row_norms(w)
                inside = np.ones(len(dm), dtype=bool)
            mis = np.maximum(ang / atol, dist / dtol)
            mis = np.where((mis <= 1.0) & inside, mis, np.inf)
            order = np.lexsort((mis, g["item"]))
            ii = g["item"][order]
            first = np.flatnonzero(np.r_[True, ii[1:] != ii[:-1]])
            sel = order[first]
            best_m[g["item"][sel]] = mis[sel]
            best_e[g["item"][sel]] = np.where(np.isfinite(mis[sel]), g["el"][sel], -1)
        return best_e, best_m


def _seed_constrains(items, el: ModelElements, assigned: list[tuple[int, int]]) -> bool:
    """Cheap test, in the model frame, of whether the pairs can constrain all 6 DOF (the pose solver has the
    last word): two clearly non-parallel directions, or one direction family plus an off-axis lever (two
    separated parallel axes, an axis and a point, two points); translation rows of full rank."""
    dirs, rows, lines, pts = [], [], [], []
    for i, e in assigned:
        if e < 0:
            continue
        k = items[i].kind
        d, p = el.direction[e], el.position[e]
        if k == "PLAN":
            dirs.append(d)
            rows.append(d)
        elif k in ("CYL", "CONE"):
            dirs.append(d)
            rows.append(d) if k == "CONE" else None
            rows.extend(perpendicular_basis(d))
            lines.append((p, d))
            if k == "CONE":
                pts.append(p)
        else:
            rows.extend(np.eye(3))
            pts.append(p)
    if len(rows) < 3:
        return False
    if np.linalg.svd(np.array(rows), compute_uv=False)[2] < 0.25:
        return False
    D = np.array(dirs).reshape(-1, 3)
    if len(D) >= 2:
        c = np.abs(D @ D.T)
        if np.min(c) < math.cos(math.radians(14.0)):
            return True
    # a single direction family (or none): the roll needs a lever
    a = D[0] if len(D) else None
    levers = [q2 - q1 for (q1, _), (q2, _) in zip(lines, lines[1:], strict=False)]
    levers += [q - l[0] for l in lines for q in pts]
    levers += [q2 - q1 for q1, q2 in zip(pts, pts[1:], strict=False)]
    for v in levers:
        if a is not None:
            v = v - (v @ a) * a
        if np.linalg.norm(v) > 0.05:
            return True
    return False


class _Search:
    """Depth-limited interpretation tree: seeds of 2-4 consistent pairs that fix the pose (items taken in
    order of fewest candidates, item tuples enumerated by their last item so every item is tried early),
    each seed's closed-form pose tested against every other item at once (:class:`_FlatPairs`)."""

    def __init__(self, items, el, cands, params: MatchParams, length_m: float):
        self.items, self.el, self.cands, self.p = items, el, cands, params
        self.length_m = length_m
        self.n_nodes = 0
        self.leaves: list[Hypothesis] = []
        self.max_wild = int(params.max_wildcard_fraction * len(items)) + params.extra_wildcards
        self.total_weight = float(sum(it.weight for it in items))
        self.best_score = 0.0
        self._poses = np.zeros((64, 4, 4))
        self._n_poses = 0
        self.dedupe_angle = math.radians(2.0)
        self.dedupe_dist = 0.02 * length_m
        # fewest candidates first, tempered by size: a small patch is the likeliest to be spurious or
        # misclassified, and a seed that starts with it wastes the budget
        self.order = sorted(range(len(items)), key=lambda i: (math.log(len(cands[i]) + 1.0)
                                                              - params.size_weight * math.log(items[i].n_pixels),
                                                              -items[i].n_pixels))
        self.flat = _FlatPairs(items, el, cands)
        self.stop_reason = ""
        self.t0 = time.perf_counter()
        self.c0 = time.process_time()
        self.partial: list[tuple[int, list[tuple[int, int]]]] = []  # (dims, pairs) when nothing fixes 6 DOF

    def out_of_budget(self) -> bool:
        if self.stop_reason:
            return True
        if self.n_nodes >= self.p.max_nodes:
            self.stop_reason = f"node budget ({self.p.max_nodes}) reached"
        elif time.process_time() - self.c0 > self.p.max_time_s:
            self.stop_reason = f"time budget ({self.p.max_time_s:g} s CPU) reached"
        elif time.perf_counter() - self.t0 > self.p.max_wall_s:
            self.stop_reason = f"time budget ({self.p.max_wall_s:g} s wall) reached"
        return bool(self.stop_reason)

    def pose(self, assigned: list[tuple[int, int]], T_init=None, iterations=None, assess=True,
             chi2_slack: float = 1.0) -> list[PoseEstimate]:
        pairs = [make_pair(self.items[i], self.el, e) for i, e in assigned if e >= 0]
        hyps = pose_hypotheses(pairs, length_m=self.length_m, max_sigma=self.p.max_free_sigma, T_init=T_init,
                               iterations=(1 if T_init is None else 3) if iterations is None else iterations,
                               max_signs=4, assess=assess)
        return [h for h in hyps if h.ok and h.cost <= chi2_slack * (self.p.pose_chi2_factor * h.n_residuals + 10.0)]

    def run(self):
        order = self.order
        n = len(order)
        max_depth = self.p.max_seed_size
        # item tuples (positions in ``order``) by their last position: (0,1), (0,2), (1,2), (0,3), ...
        for last in range(1, n):
            for first in range(last):
                self._seed([order[first], order[last]], [], max_depth, last)
                if self.out_of_budget():
                    return
            if self.best_score >= self.p.stop_fraction * self.total_weight and len(self.leaves) > 0 \
                    and last >= min(n - 1, 3):
                self.stop_reason = ""  # explained almost everything: done
                return

    def _seed(self, want: list[int], assigned: list[tuple[int, int]], max_depth: int, last: int) -> None:
        """Assign ``want[0]`` (then the rest) every consistent candidate; when the pairs fix 6 DOF, test the
        pose; otherwise extend with one more item positioned after ``last`` in the order (depth-limited)."""
        if self.out_of_budget():
            return
        if not want:
            if len(assigned) >= max_depth:
                return
            # add a third (fourth) item after the last one used
            for pos in range(last + 1, len(self.order)):
                self._seed([self.order[pos]], assigned, max_depth, pos)
                if self.out_of_budget():
                    return
            return
        i = want[0]
        item = self.items[i]
        cand = self.cands[i]
        for j, e in assigned:
            if len(cand) == 0:
                break
            cand = cand[binary_ok(self.items[j], e, item, cand, self.el, self.p.length_slack)]
        self.n_nodes += 1
        for e in cand:
            if self.out_of_budget():
                return
            new = assigned + [(i, int(e))]
            if len(want) > 1:
                self._seed(want[1:], new, max_depth, last)
                continue
            if _seed_constrains(self.items, self.el, new):
                self.n_nodes += 1
                hyps = self.pose(new, iterations=0, assess=False, chi2_slack=3.0)  # closed form; finish() assesses
                if hyps:
                    for h in hyps[:2]:
                        self._complete(new, h)
                    continue
            # pairs that fix fewer than 6 DOF are kept, at every depth, for when no seed fixes all 6: a floor and
            # a wall with nothing else consistent (the pipe patch a merge) still place the sensor but for a shift
            # along the wall, which the caller may find by agreement
            self.partial.append((sum(_DIMS[self.items[k].kind] for k, _ in new), new))
            if len(new) < max_depth:
                self._seed([], new, max_depth, last)

    def _complete(self, seed: list[tuple[int, int]], pose: PoseEstimate) -> None:
        """Every other item takes its best element consistent with the seed's pose, all at once."""
        T = pose.T_world_sensor
        if self._seen(T):
            return
        seed_items = [i for i, _ in seed]
        # rotation uncertainty of a seed pose: about the worst direction sigma of its items
        s_rot = max(self.items[i].sigma_angle for i in seed_items)
        centre = np.mean([self.items[i].position for i in seed_items], axis=0)
        best_e, _ = self.flat.best(T, 2.0, 2.0, 3.0 * s_rot, centre)
        for i, e in seed:
            best_e[i] = e
        n_w = int(np.sum(best_e < 0))
        if n_w > self.max_wild:
            self._remember(T)  # too many items unexplained: not a leaf, but do not test this pose again
            return
        out = [(i, int(best_e[i])) for i in range(len(self.items))]
        self._leaf(out, pose)

    def _remember(self, T: np.ndarray) -> None:
        if self._n_poses == len(self._poses):
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        self._poses[self._n_poses] = T
        self._n_poses += 1

    def _seen(self, T: np.ndarray) -> bool:
        """Whether a leaf with (nearly) the same pose exists (all leaves tested at once)."""
        if self._n_poses == 0:
            return False
        P = self._poses[: self._n_poses]
        cos = (np.einsum("nij,ij->n", P[:, :3, :3], T[:3, :3]) - 1.0) / 2.0
        close = (cos > math.cos(self.dedupe_angle)) & (
            _row_norms(P[:, :3, 3] - T[:3, 3]) < self.dedupe_dist)
        return bool(close.any())

    def _leaf(self, assigned, pose: PoseEstimate) -> None:
        matched = [i for i, e in assigned if e >= 0]
        score = float(sum(self.items[i].weight for i in matched))
        self.leaves.append(Hypothesis(tuple(sorted(assigned)), pose, score, len(matched)))
        self._remember(pose.T_world_sensor)
        if pose.free_dof == 0:
            self.best_score = max(self.best_score, score)

    def finish(self, max_hypotheses: int) -> list[Hypothesis]:
        """The best leaves refined with all their pairs (a second completion under the refined pose); when no
        seed fixed 6 DOF, the largest partial assignments as underconstrained hypotheses."""
        leaves = _diverse(sorted(self.leaves, key=lambda h: (-h.score, h.pose.cost)), self.order,
                          2 * max_hypotheses)
        out: list[Hypothesis] = []
        for h in leaves:
            T = h.pose.T_world_sensor
            ref = self.pose(list(h.pairs), T_init=T)
            if not ref:
                out.append(h)
                continue
            pose = ref[0]
            seed_items = [i for i, e in h.pairs if e >= 0]
            centre = np.mean([self.items[i].position for i in seed_items], axis=0)
            best_e, _ = self.flat.best(pose.T_world_sensor, 2.0, 2.0, 0.0, centre)
            pairs = [(i, int(best_e[i])) for i in range(len(self.items))]
            if pairs != list(h.pairs) and sum(e >= 0 for _, e in pairs) >= h.n_matched:
                ref2 = self.pose(pairs, T_init=pose.T_world_sensor)
                if ref2 and ref2[0].free_dof == 0:
                    pose = ref2[0]
                else:
                    pairs = list(h.pairs)
            else:
                pairs = list(h.pairs)
            matched = [i for i, e in pairs if e >= 0]
            out.append(Hypothesis(tuple(pairs), pose, float(sum(self.items[i].weight for i in matched)),
                                  len(matched)))
        if not out and self.partial:
            self.partial.sort(key=lambda x: -x[0])
            for _, pairs in self.partial[: max_hypotheses]:
                hyps = self.pose(pairs, iterations=3)
                paired = {k for k, _ in pairs}
                full = pairs + [(i, -1) for i in range(len(self.items)) if i not in paired]
                # every pose the pairs admit: a pipe's axis fixes the rotation only up to its sign, and which
                # of the two the solver lists first turns on the last bits of the fits
                for h in hyps:
                    out.append(Hypothesis(tuple(sorted(full)), h,
                                          float(sum(self.items[i].weight for i, _ in pairs)), len(pairs)))
        return out


def _diverse(ranked: list[Hypothesis], order: list[int], n: int) -> list[Hypothesis]:
    """At most ``n`` of the ``ranked`` hypotheses: the best half by score, then the best one that matches each
    item (items in search ``order``: fewest candidates first), then the rest by score.

    The score counts matched pixels, not how telling the matches are: a new cabinet whose three faces fit
    some cabinet of the model outscores the one tank that fits a single element, and with enough such
    coincidences the right interpretation falls out of a list cut by score. Verification, not the score,
    decides; it must be shown, for every item, the best interpretation that explains it.
    """
    chosen = ranked[: n // 2]
    taken = {id(h) for h in chosen}
    for i in order:
        if len(chosen) >= n:
            break
        h = next((h for h in ranked if id(h) not in taken and any(k == i and e >= 0 for k, e in h.pairs)), None)
        if h is not None:
            chosen.append(h)
            taken.add(id(h))
    chosen += [h for h in ranked if id(h) not in taken][: n - len(chosen)]
    return chosen


def _same_pose(a: np.ndarray, b: np.ndarray, angle_rad: float, dist_m: float) -> bool:
    dR = a[:3, :3].T @ b[:3, :3]
    ang = math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))
    return ang < angle_rad and float(np.linalg.norm(a[:3, 3] - b[:3, 3])) < dist_m


def match(description: SceneDescription, model: SceneModel | ModelElements, pixel_pitch_rad: float,
          params: MatchParams = MatchParams(), prior: np.ndarray | None = None) -> MatchResult:
    """Interpretation-tree search (module docstring).

    Parameters
    ----------
    description : the scene description (patches in the sensor frame).
    model : the a priori model, or its :func:`model_elements` (precomputed once per model).
    pixel_pitch_rad : the sensor's angular pixel size (for patch areas).
    params : tolerances and limits.
    prior : optional ``T_world_sensor`` (4, 4) prior restricting the candidates (with
        ``params.prior_angle_rad`` and ``params.prior_dist_m``).

    Returns
    -------
    MatchResult with its hypotheses sorted by score (then fewer free DOF, then lower pose cost).
    """
    el = model if isinstance(model, ModelElements) else model_elements(model)
    items = scene_items(description, pixel_pitch_rad, params)
    matchable = frozenset(it.patch_index for it in items)
    cands = [unary_candidates(it, el, params, prior) for it in items]
    keep = [k for k in range(len(items)) if len(cands[k])]
    items = [items[k] for k in keep]
    cands = [cands[k] for k in keep]
    if not items:
        return MatchResult((), tuple(items), el, 0, True, (), matchable=matchable)
    length_m = params.length_m or float(np.median([it.range_m for it in items]))
    s = _Search(items, el, cands, params, length_m)
    s.run()
    leaves = sorted(s.finish(params.max_hypotheses), key=lambda h: (-h.score, h.pose.free_dof, h.pose.cost))
    uniq: list[Hypothesis] = []
    for h in leaves:
        T = h.pose.T_world_sensor
        if any(_same_pose(T, u.pose.T_world_sensor, math.radians(2.0), 0.02 * length_m) for u in uniq):
            continue
        uniq.append(h)
    uniq = sorted(_diverse(uniq, s.order, params.max_hypotheses),
                  key=lambda h: (-h.score, h.pose.free_dof, h.pose.cost))
    return MatchResult(tuple(uniq), tuple(items), el, s.n_nodes, not s.stop_reason,
                       tuple(len(c) for c in cands), s.stop_reason, matchable)


def given_match(description: SceneDescription, model: SceneModel | ModelElements, pixel_pitch_rad: float,
                pairings: dict[int, tuple[str, str]], params: MatchParams = MatchParams()) -> MatchResult:
    """The match result of given correspondences (``{patch id: (feature id, part)}``) instead of a search:
    one hypothesis whose pose is computed from them in closed form. Used to isolate the pose stage from
    matching (the harness's ``pairing`` oracle); patches not in ``pairings`` are wildcards."""
    el = model if isinstance(model, ModelElements) else model_elements(model)
    items = tuple(scene_items(description, pixel_pitch_rad, params))
    index = {(str(f), str(p)): e for e, (f, p) in enumerate(zip(el.feature_id, el.part, strict=True))}
    pairs_idx = []
    for i, it in enumerate(items):
        e = index.get(pairings.get(it.patch_id, ("", "")), -1)
        if e >= 0 and el.kind[e] != it.kind:
            e = -1  # a pairing the item's kind cannot express (e.g. a patch labelled CYL on a plane)
        pairs_idx.append((i, e))
    pairs = [make_pair(items[i], el, e) for i, e in pairs_idx if e >= 0]
    hyps: tuple[Hypothesis, ...] = ()
    if pairs:
        length_m = params.length_m or float(np.median([it.range_m for it in items]))
        pose = estimate_pose(pairs, length_m=length_m, max_sigma=params.max_free_sigma)
        if pose.ok:
            score = float(sum(items[i].weight for i, e in pairs_idx if e >= 0))
            hyps = (Hypothesis(tuple(pairs_idx), pose, score, len(pairs)),)
    return MatchResult(hyps, items, el, 0, True, matchable=frozenset(it.patch_index for it in items))
