"""Extents of present features: a face or a cylinder body that reaches beyond the model's edge, or ends before it.

A resized box (a cabinet of another height, a wall of another length) keeps most of its faces in their planes:
what changed is where they end. A tank of another height keeps its body on its axis, longer or shorter. The
evidence is along the feature's *extent axes* (a rectangle's two in-plane axes, a cylinder's axis), edge by
edge, in the feature's own coordinates:

* **grown**: points of the feature's patches that the model does not explain (in front of or behind the
  predicted surface) yet lie on the feature's unbounded surface within the allowance, beyond one of its edges
  (and within the other axis's extent): the surface goes on where the model says it ends;
* **shrunk**: the feature's explained pixels stop short of an edge, and the model's pixels of the feature beyond
  that observed edge show the background (revealed), not an occluder: the surface ends where the model says
  it goes on. Where nothing lies behind (a bay's wall shortened: its rays past the new end leave the bay), the
  background is *no return where a return was expected*: no data on a ray that meets the model's surface within
  the sensor's range limits, away from grazing incidence (:func:`return_expected`).

Positions along an axis are those of each pixel's ray on the model's unbounded surface (noise-free up to the
pose), so an edge is located to a pixel footprint whatever the range noise. An edge moved when enough pixels
lie beyond it by more than a margin: ``k_sigma`` pose sigmas at the pixel's range plus ``extent_margin_px``
pixel footprints (the footprint on the surface: range times the ray spacing), lengthened along the edge's axis
as the surface's obliquity stretches it in that direction (by ``1 / cos`` of the incidence along the ray's
projection on the surface, not at all across it: :func:`_stretch`). On the calibration suite's scanner and
mock-up groups and 42 more calibration-style scenes (232 trials), the worst direction's ``1 / cos`` on every
axis kept a grazing cabinet side from growing along its lit axis: altered cabinets' F1 0.795 -> 0.824.
A rigid slide within the plane grows one edge of an axis and shrinks the opposite one: that is a move, not a
change of extent, and gives no verdict here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from recognition.localisation.pose import skew
from scenes.features import Cylinder, Feature, Plane

GROWN, SHRUNK = "grown", "shrunk"


@dataclass(frozen=True)
class EdgeChange:
    """One edge of a feature that moved: extent ``axis`` (0: a plane's u or a cylinder's axis, 1: a plane's v),
    ``side`` (+1 or -1 along it), ``kind`` (``grown`` or ``shrunk``), ``amount_m`` (median distance beyond the
    model's edge of the grown pixels, or the gap between the observed and the model's edge) and ``n_pixels``
    (the pixels beyond the edge that say so)."""

    axis: int
    side: int
    kind: str
    amount_m: float
    n_pixels: int


def has_extent(f: Feature) -> bool:
    return isinstance(f, Plane | Cylinder)


def _axes(f: Feature) -> list[tuple[np.ndarray, float]]:
    """The extent axes of ``f`` (unit direction, half extent) about its centre."""
    if isinstance(f, Plane):
        return [(f.u_axis, f.half_size[0]), (f.v_axis, f.half_size[1])]
    if isinstance(f, Cylinder):
        return [(f.axis, f.length / 2)]
    raise TypeError(type(f).__name__)


def unbounded_distance(f: Feature, pts: np.ndarray) -> np.ndarray:
    """Distance (N,) of world points to the feature's unbounded surface (a plane, a cylinder of infinite length)."""
    if isinstance(f, Plane | Cylinder):
        return np.abs(f.signed_distance(pts))
    raise TypeError(type(f).__name__)


def ray_hits(f: Feature, origin: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """Points (N, 3) where world rays (N, 3, unit) from ``origin`` (3,) first meet the feature's unbounded
    surface (NaN where they do not, or behind the origin)."""
    out = np.full(rays.shape, np.nan)
    if isinstance(f, Plane):
        den = rays @ f.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((f.centre - origin) @ f.normal) / den
        ok = np.isfinite(t) & (t > 0)
    elif isinstance(f, Cylinder):
        w = origin - f.centre
        dp = rays - np.outer(rays @ f.axis, f.axis)
        wp = w - (w @ f.axis) * f.axis
        a = np.einsum("ij,ij->i", dp, dp)
        b = 2 * dp @ wp
        c = float(wp @ wp) - f.radius**2
        disc = b * b - 4 * a * c
        with np.errstate(divide="ignore", invalid="ignore"):
            sq = np.sqrt(np.maximum(disc, 0.0))
            t1, t2 = (-b - sq) / (2 * a), (-b + sq) / (2 * a)
        t = np.where(t1 > 0, t1, t2)
        ok = (disc >= 0) & np.isfinite(t) & (t > 0)
    else:
        raise TypeError(type(f).__name__)
    out[ok] = origin + t[ok, None] * rays[ok]
    return out


def return_expected(f: Feature, origin: np.ndarray, rays: np.ndarray, cos_grazing: float) -> np.ndarray:
    """Whether world rays (N, 3, unit) from ``origin`` meet the feature's unbounded surface at an incidence whose
    cosine is at least ``cos_grazing`` (bool (N,)): a sensor returns from such a surface unless something is
    wrong with it (a dropout at grazing incidence is expected; one at near-normal incidence is not)."""
    hits = ray_hits(f, origin, rays)
    ok = np.all(np.isfinite(hits), axis=1)
    cos = np.abs(np.einsum("ij,ij->i", rays, _surface_normals(f, hits, ok)))
    return ok & (cos >= cos_grazing)


def _surface_normals(f: Feature, hits: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) of the feature's unbounded surface at ``hits`` (N, 3): a plane's normal, or a
    cylinder's radial direction at the hit; rows not ``ok`` (no hit) get the radial direction of the origin's."""
    if isinstance(f, Plane):
        return np.broadcast_to(f.normal, hits.shape)
    w = np.where(ok[:, None], hits, 0.0) - f.centre
    radial = w - np.outer(w @ f.axis, f.axis)
    return radial / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)


def extent_changes(f: Feature, origin: np.ndarray, rays_w: np.ndarray, data_w: np.ndarray, margin: np.ndarray,
                   allowance: np.ndarray, found: np.ndarray, revealed: np.ndarray, beyond_predicted: np.ndarray,
                   candidates: np.ndarray, min_pixels: int, revealed_share: float,
                   tolerance: float) -> list[EdgeChange]:
    """The edges of feature ``f`` that moved (:class:`EdgeChange`), from flat pixel indices.

    Parameters
    ----------
    origin : (3,) the sensor's position in the world frame; ``rays_w`` (P, 3) every pixel's world ray.
    data_w : (P, 3) the measured points in the world frame; ``allowance`` (P,) metres per pixel.
    margin : (P,) metres per pixel, across the ray; along each extent axis it is lengthened by the footprint's
        stretch on the feature's surface in that direction (:func:`_stretch`: by ``1 / cos`` of the incidence
        along the ray's projection on the surface, not across it).
    found : the feature's predicted pixels that its surface explains; ``revealed``: those that show the
        background; ``beyond_predicted``: all of its predicted pixels (any class).
    candidates : pixels of the feature's patches that the model does not explain (grown surface, maybe).
    min_pixels : fewest pixels beyond an edge that move it.
    revealed_share : share of the predicted pixels beyond an observed edge that must show the background.
    tolerance : least change of an edge, as a fraction of the feature's dimension along that axis (a pose a few
        millimetres off shifts every edge a little; a resized part changes by a share of its size).
    """
    axes = _axes(f)
    hit_found = ray_hits(f, origin, rays_w[found])
    hit_pred = ray_hits(f, origin, rays_w[beyond_predicted])
    on = candidates[unbounded_distance(f, data_w[candidates]) <= allowance[candidates]]
    hit_cand = ray_hits(f, origin, rays_w[on])
    keep = np.all(np.isfinite(hit_cand), axis=1)
    on, hit_cand = on[keep], hit_cand[keep]
    is_rev = np.isin(beyond_predicted, revealed)
    changes: list[EdgeChange] = []
    directions = [a for a, _ in axes]
    stretch_on = _stretch(f, rays_w[on], hit_cand, directions)  # the footprint along each axis
    stretch_pred = _stretch(f, rays_w[beyond_predicted], hit_pred, directions)
    for i, (a, h) in enumerate(axes):
        margin_on = margin[on] * stretch_on[i]
        margin_pred = margin[beyond_predicted] * stretch_pred[i]
        x_found = (hit_found - f.centre) @ a
        x_pred = (hit_pred - f.centre) @ a
        x_cand = (hit_cand - f.centre) @ a
        if len(axes) > 1:  # within the other axis's extent (beyond this edge, not past a corner)
            b, hb = axes[1 - i]
            in_band = np.abs((hit_cand - f.centre) @ b) <= hb + margin[on] * stretch_on[1 - i]
        else:
            in_band = np.ones(len(on), dtype=bool)
        per_axis: list[EdgeChange] = []
        for side in (1, -1):
            least = tolerance * 2 * h
            excess = side * x_cand - h
            grown = in_band & (excess > margin_on)
            if int(np.count_nonzero(grown)) >= min_pixels:
                amount = float(np.median(excess[grown]))
                if amount > least:
                    per_axis.append(EdgeChange(i, side, GROWN, amount, int(grown.sum())))
                continue
            xf = side * x_found[np.isfinite(x_found)]
            if len(xf) < min_pixels:
                continue
            edge = float(np.quantile(xf, 0.995))  # the observed edge (a stray explained pixel does not move it)
            gap = h - edge
            past = np.isfinite(x_pred) & (side * x_pred > edge + margin_pred)
            n_past, n_rev = int(past.sum()), int(np.count_nonzero(past & is_rev))
            if n_past and gap > max(float(np.median(margin_pred[past])), least) and n_rev >= min_pixels \
                    and n_rev >= revealed_share * n_past:
                per_axis.append(EdgeChange(i, side, SHRUNK, gap, n_rev))
        kinds = {e.kind for e in per_axis}
        if len(per_axis) == 2 and kinds == {GROWN, SHRUNK}:
            continue  # one edge on, the opposite one back: a slide within the surface, not another extent
        changes.extend(per_axis)
    return changes


def _stretch(f: Feature, rays: np.ndarray, hits: np.ndarray, directions: list[np.ndarray],
             min_cos: float = 0.2) -> np.ndarray:
    """How much a footprint across a ray (N, 3, unit) lengthens along each in-surface unit direction of
    ``directions`` where the ray meets the feature's surface (hits (N, 3)); (len(directions), N):
    ``sqrt(1 + (a.e)² tan² i)``, ``i`` the incidence and ``e`` the unit direction of the ray projected on the
    surface (the footprint is stretched by ``1 / cos i`` along ``e`` and not across it); ``cos i`` at least
    ``min_cos``. Rays without a hit give 1 / min_cos."""
    ok = np.all(np.isfinite(hits), axis=1)
    n = _surface_normals(f, hits, ok)
    d = np.einsum("ij,ij->i", rays, n)
    t = rays - d[:, None] * n  # the ray projected on the surface
    e = t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    cos = np.maximum(np.abs(d), min_cos)
    tan2 = 1.0 / (cos * cos) - 1.0
    out = []
    for a in directions:
        ae = e @ a
        out.append(np.where(ok, np.sqrt(1.0 + ae * ae * tan2), 1.0 / min_cos))
    return np.array(out)


def outgrows(f: Plane, pts: np.ndarray, normal: np.ndarray, margin_m: float, tolerance: float) -> bool:
    """Whether a patch (world points (N, 3) on a plane of unit ``normal``) found away from face ``f`` is larger
    than ``f``: not ``f`` moved rigidly, which keeps its size, but ``f`` resized with its object.

    A patch seen of a face is at most the face, along any direction within it; it is larger when, in both of two
    frames, one of its two extents exceeds the face's dimension by ``tolerance`` of it plus ``margin_m``: the
    face's own axes turned with its normal (exact for a face that turned about a horizontal axis or not at all)
    and the patch's least-area enclosing rectangle against the face's sides (exact for a face turned within its
    plane, whose own axes would see the diagonal).
    """
    n = normal / np.linalg.norm(normal)
    n = n if float(n @ f.normal) >= 0 else -n
    R = _rotation_between(f.normal, n)
    sides = 2 * np.asarray(f.half_size, dtype=np.float64)
    uv = (pts - pts.mean(axis=0)) @ np.stack([R @ f.u_axis, R @ f.v_axis], axis=1)
    lo, hi = np.quantile(uv, [0.005, 0.995], axis=0)
    bound = sides * (1 + tolerance) + margin_m
    if not np.any(hi - lo > bound):
        return False
    rect = _least_area_rectangle(uv)
    return bool(np.any(np.sort(rect) > np.sort(sides) * (1 + tolerance) + margin_m))


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The least rotation (3, 3) taking unit vector ``a`` to unit vector ``b`` (Rodrigues)."""
    c = float(a @ b)
    if c < -1 + 1e-12:
        raise ValueError("opposite vectors: no least rotation")
    K = skew(np.cross(a, b))
    return np.eye(3) + K + K @ K / (1 + c)


def _least_area_rectangle(xy: np.ndarray) -> np.ndarray:
    """Side lengths (2,) of the least-area rectangle enclosing 2-D points (N, 2), from their convex hull's edge
    directions (one side of the least-area rectangle lies along a hull edge), over the central 99 % of the
    points along each direction (a stray point does not widen it)."""
    try:
        hull = xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):  # collinear or too few points: the extents along the principal axis
        return np.ptp(xy, axis=0)
    edges = np.diff(np.vstack([hull, hull[:1]]), axis=0)
    d = edges / np.maximum(np.linalg.norm(edges, axis=1, keepdims=True), 1e-12)
    along = xy @ d.T  # (N, E)
    across = xy @ np.stack([-d[:, 1], d[:, 0]], axis=1).T
    qa, qc = np.quantile(along, [0.005, 0.995], axis=0), np.quantile(across, [0.005, 0.995], axis=0)
    wa, wc = qa[1] - qa[0], qc[1] - qc[0]
    k = int(np.argmin(wa * wc))
    return np.array([wa[k], wc[k]])


def footprint(rays: np.ndarray) -> np.ndarray:
    """Angular spacing (H, W) in radians between each pixel's ray and its neighbours' (the larger of the
    horizontal and vertical spacing), from unit rays (H, W, 3)."""
    def angle(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(np.sum(p * q, axis=-1), -1.0, 1.0))

    h, w = rays.shape[:2]
    du = angle(rays[:, 1:], rays[:, :-1]) if w > 1 else np.zeros((h, 0))
    dv = angle(rays[1:], rays[:-1]) if h > 1 else np.zeros((0, w))
    su = np.pad(du, ((0, 0), (0, 1)), mode="edge") if w > 1 else np.full((h, w), math.nan)
    sv = np.pad(dv, ((0, 1), (0, 0)), mode="edge") if h > 1 else np.full((h, w), math.nan)
    return np.fmax(su, sv)
