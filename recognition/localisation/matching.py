"""Interpretation-tree matching of scene patches to a priori model features (the paper's section 4).

Scene side: every patch labelled PLAN, CYL, CONE or SPH with a successful dedicated fit becomes a
:class:`SceneItem` (sensor frame) with its uncertainties inflated to tolerances (DESIGN 6.3: fit covariances
are overconfident, so ``k`` times the propagated sigma with a floor that grows as patches shrink). Model
side: :func:`model_elements` turns the a priori :class:`scenes.model.SceneModel` into arrays of elements
(world frame): plane faces and cylinder caps (PLAN), cylinder sides (CYL), cones (CONE), spheres (SPH).

The search over these items and elements is :mod:`.interpretation_tree`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from recognition.describe import SceneDescription
from recognition.fitting import ConeFit, CylinderFit, PlaneFit, SphereFit
from recognition.tuning import AUTO, tuned
from scenes.features import Cone, Cylinder, Plane, Sphere
from scenes.model import SceneModel

from .pose import AxisPair, Pair, PlanePair, PointPair

__all__ = [
    "MatchParams",
    "ModelElements",
    "SceneItem",
    "model_elements",
    "scene_items",
    "make_pair",
    "unary_candidates",
    "binary_ok",
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
    width_directions : the least width is sought over this many in-plane directions (36: 5 deg apart) ...
    width_points : ... on at most this many of the patch's points (a regular subsample).
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
    bound_ratio : not used: kept so that configurations setting it still load (the depth-limited search has
        no branch-and-bound step).
    pose_chi2_factor : a pose fit is accepted when its whitened cost <= factor x residual count (+ 10).
    length_m : characteristic length (m) for the free-DOF test and ``same_pose_rel``; "auto": the median range
        of the items.
    max_free_sigma : a direction with a larger sigma (rad, or ``length_m`` units) counts as free.
    prior_angle_rad, prior_dist_m : tolerances of the unary test against a pose prior (None: no prior test).
    same_pose_angle_deg, same_pose_rel : two poses within this angle (degrees) and this fraction of
        ``length_m`` of each other are the same pose: the search keeps one hypothesis of them, and
        :func:`recognition.localisation.localise` does not count it as a distinct alternative (the scale there:
        the median range of the description's patches).

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    min_pixels: int = tuned(150, unit="px", chosen="not tuned: set with the tree in c9baa1a")
    max_items: int = tuned(30, unit="count", chosen="not tuned: a bound, set in c9baa1a")
    k_sigma: float = tuned(3.0, unit="sigma", chosen="not tuned here: within the 1.5-3x the first prototype "
                           "measured before this code (c9baa1a)")
    angle_floor_rad: float = tuned(math.radians(1.0), unit="rad", chosen="not tuned: set in c9baa1a (plane "
                                   "normals were 3 deg off against a reported 0.5 deg in the prototype)")
    angle_floor_px_rad: float = tuned(math.radians(1.5), unit="rad", chosen="not tuned: set in c9baa1a")
    dist_floor_m: float = tuned(0.002, unit="m", chosen="not tuned: set in c9baa1a")
    dist_floor_rel: float = tuned(0.004, unit="fraction of range", chosen="not tuned: set in c9baa1a")
    radius_rel_tol: float = tuned(0.08, unit="fraction", chosen="not tuned: set in c9baa1a")
    half_angle_tol_rad: float = tuned(math.radians(3.0), unit="rad", chosen="not tuned: set in c9baa1a")
    length_slack: float = tuned(1.15, unit="ratio", chosen="not tuned: set in c9baa1a")
    width_test: bool = tuned(True, unit="-", chosen="calibration (phase 1): constrained pose success 15/19 -> "
                             "16/19, the same 4 ok-but-wrong (9101156)")
    width_trim: float = tuned(0.01, unit="fraction", chosen="not tuned: set with the width test in 9101156")
    max_wildcard_fraction: float = tuned(0.4, unit="fraction", chosen="not tuned here: the first prototype's "
                                         "limit (40 % of the patches + 2; c9baa1a)")
    extra_wildcards: int = tuned(2, unit="count", chosen="not tuned here: the first prototype's limit (c9baa1a)")
    max_nodes: int = tuned(1500, unit="count", chosen="not tuned: a budget, set in af4da75 (the first prototype "
                           "needed about 1,000)")
    max_hypotheses: int = tuned(12, unit="count", chosen="not tuned: set in c9baa1a (localise asks for 20)")
    bound_ratio: float = tuned(0.7, unit="-", chosen="not used (kept so that configurations setting it load)")
    max_time_s: float = tuned(3.0, unit="s (CPU)", chosen="a safety net, 1 -> 3 s after a search stopped on time "
                              "under the benchmark's load (03ed3d2); the node budget binds first")
    max_wall_s: float = tuned(6.0, unit="s", chosen="a safety net, 2 -> 6 s with max_time_s (03ed3d2)")
    size_weight: float = tuned(
        0.25, unit="-", chosen="the first phase's default (now classic): 0.5 -> 0.25 keeps mock-up and factory "
        "constrained trials at 100 %, Kinect-like unchanged (5745704)")
    max_seed_size: int = tuned(3, unit="pairs", chosen="not tuned: set in af4da75")
    stop_fraction: float = tuned(0.9, unit="fraction", chosen="not tuned: set in af4da75")
    pose_chi2_factor: float = tuned(9.0, unit="ratio", chosen="not tuned: set in c9baa1a")
    length_m: float | Literal["auto"] = tuned("auto", unit="m", chosen="the items' median range (formerly spelled "
                                              "0; c9baa1a)")
    max_free_sigma: float = tuned(0.1, unit="rad or length_m", chosen="not tuned: set in c9baa1a")
    prior_angle_rad: float | None = tuned(None, unit="rad", chosen="off: localise sets it from "
                                          "LocaliseParams.prior_angle_deg when the scan has a prior")
    prior_dist_m: float | None = tuned(None, unit="m", chosen="off: localise sets it from "
                                       "LocaliseParams.prior_dist_m when the scan has a prior")
    same_pose_angle_deg: float = tuned(2.0, unit="deg", chosen="not tuned: set in af4da75")
    same_pose_rel: float = tuned(0.02, unit="fraction of length_m", chosen="not tuned: set in af4da75")
    width_directions: int = tuned(36, unit="count", chosen="not tuned: 5 deg apart, set with the width test in "
                                  "9101156")
    width_points: int = tuned(2000, unit="points", chosen="not tuned: a speed bound, set with the width test in "
                              "9101156")

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
        if self.extra_wildcards < 0:
            raise ValueError(f"extra_wildcards must be >= 0, got {self.extra_wildcards}")
        if self.length_m != AUTO and not self.length_m > 0:
            raise ValueError(f"length_m must be > 0 or 'auto', got {self.length_m!r}")
        for name in ("same_pose_angle_deg", "same_pose_rel"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.width_directions < 1 or self.width_points < 3:
            raise ValueError(f"width_directions must be >= 1 and width_points >= 3, got {self.width_directions}, "
                             f"{self.width_points}")
        if not 0 <= self.width_trim < 0.5:
            raise ValueError(f"width_trim must be in [0, 0.5), got {self.width_trim}")


# --------------------------------------------------------------------------------------- model side


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


# --------------------------------------------------------------------------------------- scene side


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
                         k * s_off + floor_d, rng_m, _min_width(inplane @ evec[:, 1:], params))
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


# -------------------------------------------------------------------------------- unary constraints


def _width_step_error(params: MatchParams) -> float:
    """The least of the widths over ``width_directions`` directions exceeds the true least width by at most
    this share of the patch's extent."""
    return math.sin(math.pi / (2 * params.width_directions))


def _min_width(uv: np.ndarray, params: MatchParams) -> float:
    """Least width (metres) of in-plane points ``uv`` (N, 2) over ``width_directions`` directions (on at most
    ``width_points`` of them), each span taken between the ``width_trim`` and ``1 - width_trim`` quantiles (stray
    pixels off the face do not widen it); NaN for fewer than 3 points. A patch inside a rectangle is never
    wider than its short side."""
    trim, max_points = params.width_trim, params.width_points
    if len(uv) < 3:
        return float("nan")
    if len(uv) > max_points:
        uv = uv[np.linspace(0, len(uv) - 1, max_points).astype(np.int64)]
    a = np.linspace(0.0, np.pi, params.width_directions, endpoint=False)
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
                                 + _width_step_error(params) * item.length)
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


# ------------------------------------------------------------------------------- binary constraints


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
