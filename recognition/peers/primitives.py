"""Primitive-detection peers: RANSAC shape detection instead of H-K segmentation + quadric classification.

* ``efficient_ransac`` - Efficient RANSAC (Schnabel, Wahl & Klein, "Efficient RANSAC for point-cloud shape
  detection", Computer Graphics Forum 26(2), 2007, doi:10.1111/j.1467-8659.2007.01016.x) for planes,
  cylinders, spheres and cones, through CGAL's Python bindings (PyPI ``cgal``: ``efficient_RANSAC``).
* ``pyransac3d`` - the lightweight alternative users reach for: sequential single-shape RANSAC (plane,
  cylinder, sphere; no cone), each round keeping the shape with the most inliers, its inliers split into
  connected pieces of the image grid.

Both work on the scan's valid points, subsampled on a regular pixel stride to at most ``max_points``, with
normals estimated from the organised point image (central differences, facing the sensor). Every pixel of
the full image then takes the shape of its nearest sample pixel when it lies within ``epsilon`` of that
shape's surface. Each shape becomes a patch whose label is its type (plane PLAN, cylinder CYL, sphere SPH,
cone CONE); the shape is refitted on the patch's points by the core's dedicated least-squares fit
(:mod:`recognition.fitting`) so the downstream stages (matching, change) read the same parameterisation
as the core's; a refit that fails makes the patch OTH with the reason. These detectors give no
probabilities: the probability vector is 1 on the label (documented; it makes their Brier score that of a
hard classifier).

Inlier distance ``epsilon`` defaults to ``3 x`` the median per-pixel sigma of the scan's own noise model (at
least 3 mm); the cluster distance to 3 sample spacings at the median range; the smallest shape to
``min_pixels`` pixels of the full image (as the evaluation counts regions).

Determinism: pyransac3d draws from Python's global ``random`` module: it is seeded (``seed``) for the call
and its state restored after. CGAL seeds its generator from the wall clock (``CGAL::Random()`` uses
``std::time``) and the Python bindings do not expose it, so ``efficient_ransac`` is **not** reproducible
run to run; its peer says so (``deterministic=False``) and the bench reports the spread.
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import scipy.ndimage as ndi

from recognition import fitting
from recognition.classification import CLASSES, PatchClassification
from recognition.describe import SceneDescription, ScenePatch, core_sigma
from recognition.fitting import fit_plane_lsq, fit_quadric_lsq
from recognition.segmentation import Patch, Segmentation, SurfaceType
from recognition.tuning import AUTO, tuned
from sensors.range_image import Scan

__all__ = ["PrimitiveParams", "detect_primitives", "image_normals", "available_peers", "missing_peers"]

SHAPES = ("plane", "cylinder", "sphere", "cone")
_LABEL = {"plane": "PLAN", "cylinder": "CYL", "sphere": "SPH", "cone": "CONE", "torus": "OTH"}
_SURFACE = {"PLAN": SurfaceType.PLANAR, "CYL": SurfaceType.CYLINDRICAL, "CONE": SurfaceType.CYLINDRICAL,
            "SPH": SurfaceType.ELLIPTIC, "OTH": SurfaceType.NONE}


@dataclass(frozen=True)
class PrimitiveParams:
    """Parameters of :func:`detect_primitives` (lengths in metres).

    Attributes
    ----------
    detector : ``"cgal"`` (Efficient RANSAC) or ``"pyransac3d"``.
    shapes : shape types to detect (pyransac3d ignores ``cone``).
    max_points : most sample points given to the detector.
    epsilon : inlier distance; "auto": ``3 x`` the median sigma (>= 3 mm).
    cluster_epsilon : CGAL's connectivity distance; "auto": 3 sample spacings at the median range.
    normal_threshold : CGAL's smallest |cos| between a point's normal and the shape's.
    probability : CGAL's probability of missing the largest candidate shape.
    min_pixels : smallest shape in full-image pixels.
    iterations : pyransac3d's RANSAC iterations per shape type and round.
    max_shapes : pyransac3d's most extraction rounds.
    seed : pyransac3d's seed (CGAL cannot be seeded).

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    detector: str = tuned("cgal", unit="-", chosen="CGAL's Efficient RANSAC (the pyransac3d peer sets pyransac3d)")
    shapes: tuple[str, ...] = tuned(SHAPES, unit="-", chosen="every primitive the core labels")
    max_points: int = tuned(40_000, unit="points", chosen="not tuned: a speed bound, set in a837a85 (the "
                            "pyransac3d peer uses 8000)")
    epsilon: float | Literal["auto"] = tuned(
        "auto", unit="m", chosen="not tuned: 3x the median sigma, >= 3 mm (formerly spelled None; a837a85)")
    cluster_epsilon: float | Literal["auto"] = tuned(
        "auto", unit="m", chosen="not tuned: 3 sample spacings at the median range (formerly spelled None; "
        "a837a85)")
    normal_threshold: float = tuned(0.9, unit="|cos|", chosen="not tuned: set in a837a85")
    probability: float = tuned(0.01, unit="probability", chosen="not tuned: set in a837a85")
    min_pixels: int = tuned(200, unit="px", chosen="not tuned: the 200-pixel floor of the scored regions (a837a85)")
    iterations: int = tuned(300, unit="count", chosen="not tuned: set in a837a85 (the pyransac3d peer uses 200)")
    max_shapes: int = tuned(40, unit="count", chosen="not tuned: set in a837a85 (the pyransac3d peer uses 25)")
    seed: int = tuned(0, unit="-", chosen="a fixed seed (reproducible)")

    def __post_init__(self):
        if self.detector not in ("cgal", "pyransac3d"):
            raise ValueError(f"detector must be 'cgal' or 'pyransac3d', got {self.detector!r}")
        bad = set(self.shapes) - set(SHAPES)
        if bad or not self.shapes:
            raise ValueError(f"shapes must be a non-empty subset of {SHAPES}, got {self.shapes}")
        for name in ("epsilon", "cluster_epsilon"):
            v = getattr(self, name)
            if v != AUTO and not (isinstance(v, int | float) and not isinstance(v, bool) and v > 0):
                raise ValueError(f"{name} must be > 0 or 'auto', got {v!r}")
        if self.max_points < 100 or self.min_pixels < 1 or self.iterations < 1 or self.max_shapes < 1:
            raise ValueError("max_points >= 100, min_pixels, iterations and max_shapes >= 1 required")
        if not 0 < self.probability < 1 or not 0 <= self.normal_threshold < 1:
            raise ValueError("probability must be in (0, 1) and normal_threshold in [0, 1)")

    @classmethod
    def from_dict(cls, params: dict[str, Any] | None, **defaults) -> PrimitiveParams:
        """From a suite's method parameters; unknown keys are a ``ValueError`` naming them."""
        merged = {**defaults, **(params or {})}
        unknown = set(merged) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown primitive-detection parameter(s): {', '.join(sorted(unknown))}")
        if "shapes" in merged:
            merged["shapes"] = tuple(merged["shapes"])
        return cls(**merged)


def image_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals (H, W, 3) of an organised point image by central differences, facing the sensor
    (``n . p < 0``); NaN where a neighbour is missing (image borders included).

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, NaN where no return.
    """
    P = np.asarray(points, dtype=np.float64)
    if P.ndim != 3 or P.shape[2] != 3:
        raise ValueError(f"expected points of shape (H, W, 3), got {P.shape}")
    Pu = np.full_like(P, np.nan)
    Pv = np.full_like(P, np.nan)
    Pu[:, 1:-1] = P[:, 2:] - P[:, :-2]
    Pv[1:-1, :] = P[2:, :] - P[:-2, :]
    n = np.cross(Pu, Pv)
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / norm
    flip = np.sum(n * P, axis=-1) > 0
    n[flip] *= -1
    return n


# ------------------------------------------------------------------------------------------------ detectors


def _cgal_detect(pts: np.ndarray, nrm: np.ndarray, eps: float, cluster_eps: float, min_points: int,
                 params: PrimitiveParams) -> tuple[np.ndarray, list[str]]:
    """Efficient RANSAC: shape index per point (-1 none) and the shape types."""
    from CGAL.CGAL_Kernel import Point_3, Vector_3
    from CGAL.CGAL_Point_set_3 import Point_set_3
    from CGAL.CGAL_Shape_detection import efficient_RANSAC

    ps = Point_set_3()
    ps.add_normal_map()
    original = ps.add_int_map("original")  # Efficient RANSAC reorders the point set in place
    for k, (p, q) in enumerate(zip(pts.tolist(), nrm.tolist(), strict=True)):
        original.set(ps.insert(Point_3(*p), Vector_3(*q)), k)
    shape_map = ps.add_int_map("shape")
    info = efficient_RANSAC(ps, shape_map, min_points=int(min_points), epsilon=float(eps),
                            cluster_epsilon=float(cluster_eps), normal_threshold=float(params.normal_threshold),
                            probability=float(params.probability), planes="plane" in params.shapes,
                            cones="cone" in params.shapes, cylinders="cylinder" in params.shapes,
                            spheres="sphere" in params.shapes, tori=False)
    pairs = np.array([(original.get(i), shape_map.get(i)) for i in ps.indices()], dtype=np.int64).reshape(-1, 2)
    labels = np.full(len(pts), -1, dtype=np.int64)
    labels[pairs[:, 0]] = pairs[:, 1]
    types = [s.split()[1] if s.startswith("Type:") else "other" for s in info]
    return labels, types


def _pyransac_detect(pts: np.ndarray, eps: float, min_points: int, grid: tuple[np.ndarray, np.ndarray, tuple],
                     params: PrimitiveParams) -> tuple[np.ndarray, list[str]]:
    """Sequential pyransac3d: per round the shape type with the most inliers, split into grid-connected
    pieces of at least ``min_points``; stops when the best shape has fewer inliers than that."""
    import pyransac3d as pyrsc

    rows, cols, shape = grid
    labels = np.full(len(pts), -1, dtype=np.int64)
    types: list[str] = []
    makers = {"plane": pyrsc.Plane, "cylinder": pyrsc.Cylinder, "sphere": pyrsc.Sphere}
    kinds = [k for k in ("plane", "cylinder", "sphere") if k in params.shapes]
    state = random.getstate()
    random.seed(params.seed)
    try:
        for _ in range(params.max_shapes):
            free = np.flatnonzero(labels == -1)
            if len(free) < max(min_points, 10):
                break
            best_kind, best_in = None, np.zeros(0, dtype=np.int64)
            for kind in kinds:
                try:
                    with np.errstate(all="ignore"):  # its sphere fit divides by zero on planar samples
                        res = makers[kind]().fit(pts[free], thresh=eps, maxIteration=params.iterations)
                except (ValueError, np.linalg.LinAlgError, ZeroDivisionError, FloatingPointError):
                    continue
                inl = np.asarray(res[-1], dtype=np.int64)
                if len(inl) > len(best_in):
                    best_kind, best_in = kind, inl
            if best_kind is None or len(best_in) < min_points:
                break
            chosen = free[best_in]
            img = np.zeros(shape, dtype=bool)  # the sample grid
            img[rows[chosen], cols[chosen]] = True
            comp, n = ndi.label(img, structure=np.ones((3, 3), bool))
            comp_of = comp[rows[chosen], cols[chosen]]
            sizes = np.bincount(comp_of, minlength=n + 1)
            kept = 0
            for c in np.flatnonzero(sizes >= min_points):
                labels[chosen[comp_of == c]] = len(types)
                types.append(best_kind)
                kept += 1
            if kept == 0:  # only scattered inliers: claim them as nothing, so the next round moves on
                labels[chosen] = -2
        labels[labels == -2] = -1
    finally:
        random.setstate(state)
    return labels, types


# -------------------------------------------------------------------------------------------- shape -> patch


def _residual(fit, x: np.ndarray) -> np.ndarray:
    """Unsigned distance (N,) of points to a fitted primitive's surface (approximate for cones)."""
    if isinstance(fit, fitting.PlaneFit):
        return np.abs(x @ fit.normal - fit.offset)
    if isinstance(fit, fitting.SphereFit):
        return np.abs(np.linalg.norm(x - fit.centre, axis=1) - fit.radius)
    w = x - fit.point
    h = w @ fit.axis
    radial = np.linalg.norm(w - h[:, None] * fit.axis, axis=1)
    if isinstance(fit, fitting.CylinderFit):
        return np.abs(radial - fit.radius)
    ta = math.tan(fit.half_angle)
    return np.abs(radial - (fit.radius_at_point + ta * h)) * math.cos(fit.half_angle)


def _length_sigma(pts: np.ndarray, axis: np.ndarray, length: float) -> float:
    w = pts - pts.mean(axis=0)
    across = w - np.outer(w @ axis, axis)
    width = 2 * float(np.sqrt(np.mean(np.sum(across**2, axis=1)))) + 1e-9
    return float(np.sqrt(max(length, 1e-9) * width / max(len(pts), 1)))


def _invariants(fit, pts: np.ndarray) -> dict[str, tuple[float, float]]:
    if isinstance(fit, fitting.CylinderFit):
        return {"radius_m": (fit.radius, fit.radius_sigma),
                "length_m": (fit.length, _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, fitting.SphereFit):
        return {"radius_m": (fit.radius, fit.radius_sigma)}
    if isinstance(fit, fitting.ConeFit):
        return {"half_angle_rad": (fit.half_angle, fit.half_angle_sigma),
                "length_m": (fit.length, _length_sigma(pts, fit.axis, fit.length))}
    return {}


def _classification(label: str, fit, pts: np.ndarray, detector: str) -> PatchClassification:
    if label != "OTH" and (fit is None or not fit.ok):
        reason = f"{detector} {label}, refit failed: {getattr(fit, 'reason', 'no fit')}"
        label, fit = "OTH", None
    else:
        reason = ""
    probs = dict.fromkeys(CLASSES, 0.0)
    probs[label] = 1.0
    plaus = {k: float(label == k) for k in ("CYL", "SPH", "CONE")}
    return PatchClassification(label, probs, plaus, fit if label != "OTH" else None,
                               _invariants(fit, pts) if label != "OTH" else {}, reason,
                               {"detector": detector})


def detect_primitives(scan: Scan, params: PrimitiveParams = PrimitiveParams()) -> SceneDescription:
    """Detect planes, cylinders, spheres (and cones) in ``scan`` by RANSAC and describe them as patches.

    Returns
    -------
    SceneDescription
        One patch per detected shape (ids ``0..n-1`` by decreasing size), ``labels`` the patch id per
        pixel (-1 none), a :class:`recognition.segmentation.Segmentation` with the simple image normals
        (curvatures NaN, no edges), ``timing_s`` with ``segmentation`` (normals, detection, pixel
        assignment) and ``classification`` (the refits).
    """
    t_start = time.perf_counter()
    shape = scan.range.shape
    normals = image_normals(scan.points)
    sigma = core_sigma(scan, normals)
    ok = scan.valid & np.isfinite(normals[..., 0])
    n_ok = int(ok.sum())
    labels = np.full(shape, -1, dtype=np.int32)
    stride = max(1, math.ceil(math.sqrt(n_ok / params.max_points))) if n_ok else 1
    sub = np.zeros(shape, dtype=bool)
    sub[::stride, ::stride] = True
    rows, cols = np.nonzero(ok & sub)
    patches: list[ScenePatch] = []
    seg_patches: list[Patch] = []
    timing = {"segmentation": 0.0, "classification": 0.0}
    if len(rows) >= 10:
        pts = scan.points[rows, cols]
        nrm = normals[rows, cols]
        med_sigma = float(np.nanmedian(sigma[ok]))
        eps = max(3 * med_sigma, 3e-3) if params.epsilon == AUTO else params.epsilon
        med_range = float(np.median(scan.range[ok]))
        cluster_eps = (3 * stride * scan.sensor.pixel_pitch_rad * med_range if params.cluster_epsilon == AUTO
                       else params.cluster_epsilon)
        min_points = max(10, params.min_pixels // stride**2)
        if params.detector == "cgal":
            sample_labels, types = _cgal_detect(pts, nrm, eps, cluster_eps, min_points, params)
        else:
            grid_shape = ((shape[0] + stride - 1) // stride, (shape[1] + stride - 1) // stride)
            sample_labels, types = _pyransac_detect(pts, eps, min_points, (rows // stride, cols // stride,
                                                                           grid_shape), params)
        patches, seg_patches, labels, t_cls = _to_patches(scan, sigma, normals, ok, rows, cols, stride,
                                                          sample_labels, types, eps, params)
        timing["classification"] = t_cls
    timing["segmentation"] = time.perf_counter() - t_start - timing["classification"]
    hk = np.zeros(shape, dtype=np.int8)
    for p in patches:
        hk.flat[p.pixels] = int(p.surface_type)
    nan = np.full(shape, np.nan)
    seg = Segmentation(labels=labels, hk_class=hk, H=nan, K=nan.copy(), sigma_H=nan.copy(), sigma_K=nan.copy(),
                       normals=normals, edges=np.zeros(shape, np.uint8), patches=tuple(seg_patches))
    return SceneDescription(tuple(patches), labels, seg, sigma, timing)


def _to_patches(scan, sigma, normals, ok, rows, cols, stride, sample_labels, types, eps, params):
    """Full-resolution patches from the sample labels: nearest sample pixel's shape, within ``eps`` of it."""
    shape = scan.range.shape
    grid = np.full(((shape[0] + stride - 1) // stride, (shape[1] + stride - 1) // stride), -1, dtype=np.int64)
    grid[rows // stride, cols // stride] = sample_labels
    r_all, c_all = np.nonzero(ok)
    gi = np.clip(np.rint(r_all / stride).astype(int), 0, grid.shape[0] - 1)
    gj = np.clip(np.rint(c_all / stride).astype(int), 0, grid.shape[1] - 1)
    owner = grid[gi, gj]
    flat = np.ravel_multi_index((r_all, c_all), shape)
    P = scan.points.reshape(-1, 3)
    S = sigma.reshape(-1)
    N = normals.reshape(-1, 3)
    detector = "Efficient RANSAC" if params.detector == "cgal" else "pyransac3d"
    candidates = []
    t_cls = 0.0
    for k, kind in enumerate(types):
        pix = flat[owner == k]
        samp = sample_labels == k
        if samp.sum() < 3 or len(pix) < 3:
            continue
        label = _LABEL.get(kind, "OTH")
        t0 = time.perf_counter()
        spts = scan.points[rows[samp], cols[samp]]
        sfit = fitting.fit_primitive(label, spts, np.maximum(sigma[rows[samp], cols[samp]], 1e-6),
                                  normals[rows[samp], cols[samp]])
        if sfit is not None and sfit.ok:
            pix = pix[_residual(sfit, P[pix]) <= max(eps, 3 * float(np.nanmedian(S[pix])))]
        t_cls += time.perf_counter() - t0
        if len(pix) < params.min_pixels:
            continue
        candidates.append((len(pix), k, label, pix))
    candidates.sort(key=lambda c: (-c[0], c[1]))
    labels = np.full(shape, -1, dtype=np.int32)
    patches, seg_patches = [], []
    for new_id, (_, _, label, pix) in enumerate(candidates):
        labels.flat[pix] = new_id
        pts, sig = P[pix], np.maximum(S[pix], 1e-6)
        t0 = time.perf_counter()
        fit = fitting.fit_primitive(label, pts, sig, N[pix])
        cls = _classification(label, fit, pts, detector)
        stype = _SURFACE[cls.label]
        surf = fit_plane_lsq(pts, sig) if cls.label == "PLAN" else fit_quadric_lsq(pts, sig)
        t_cls += time.perf_counter() - t0
        rc = np.stack(np.unravel_index(pix, shape), axis=1)
        small = len(pix) < 50
        patches.append(ScenePatch(new_id, pix, pts, S[pix], stype, cls, small, False))
        seg_patches.append(Patch(new_id, rc, len(pix), stype, surf, small, False))
    return patches, seg_patches, labels, t_cls


# ------------------------------------------------------------------------------------------------- registry


def _importable(module: str) -> str:
    """"" when ``module`` imports, else the error."""
    try:
        __import__(module)
    except Exception as exc:  # noqa: BLE001 - any failure to import means the peer is unavailable
        return f"{type(exc).__name__}: {exc}"
    return ""


def _runner(detector: str):
    defaults = {"detector": detector}
    if detector == "pyransac3d":  # its cylinder fit costs ~1 ms per iteration per 10k points
        defaults.update(max_points=8000, iterations=200, max_shapes=25)

    def run(scan: Scan, params: dict[str, Any] | None) -> SceneDescription:
        """Peer ``description`` stage."""
        return detect_primitives(scan, PrimitiveParams.from_dict(params, **defaults))

    run.__name__ = f"run_{detector}"
    return run


def available_peers() -> list:
    """The primitive-detection peers whose package imports."""
    from recognition.peers import Peer

    out = []
    if not _importable("CGAL.CGAL_Shape_detection"):
        out.append(Peer("efficient_ransac", "description", _runner("cgal"),
                        "Efficient RANSAC (Schnabel et al. 2007, CGAL) planes/cylinders/spheres/cones; "
                        "not seedable (CGAL seeds from the clock)", {"epsilon": AUTO, "probability": 0.01},
                        deterministic=False))
    if not _importable("pyransac3d"):
        out.append(Peer("pyransac3d", "description", _runner("pyransac3d"),
                        "pyransac3d sequential RANSAC planes/cylinders/spheres, split into connected pieces",
                        {"epsilon": AUTO, "max_points": 8000, "iterations": 200, "max_shapes": 25}))
    return out


def missing_peers() -> dict[str, str]:
    """Primitive-detection peers whose package does not import, with the reason."""
    out = {}
    err = _importable("CGAL.CGAL_Shape_detection")
    if err:
        out["efficient_ransac"] = f"package 'cgal' (CGAL Python bindings) does not import: {err}"
    err = _importable("pyransac3d")
    if err:
        out["pyransac3d"] = f"package 'pyransac3d' does not import: {err}"
    return out
