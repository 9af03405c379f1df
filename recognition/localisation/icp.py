"""ICP refinement of a pose against the model surfaces predicted visible from it (Open3D).

The target is not a sample of the whole CAD model: hidden back faces pull ICP off (DESIGN 6.3: a 2 cm slab
gave exactly 20 mm errors). It is the model's predicted range image at the hypothesised pose
(:class:`recognition.localisation.Prediction`, shared with verification), as world points with analytic normals
of the features they lie on. The source is the scan's points (sensor frame) on a regular pixel stride.
Open3D's point-to-plane ICP with a Tukey robust kernel runs from the hypothesised pose in a few passes of
shrinking correspondence distance (scaled with the median range, floored by the target's point spacing),
on a few thousand source points. Open3D runs single-threaded here
(``OMP``-free reductions are not guaranteed otherwise), so results are deterministic.

The covariance of the result is the point-to-plane information at the final pose,
``(J' J)^-1 s²`` with ``J`` rows ``[(p x n)', n']`` over the inlier correspondences (left perturbation in
the world frame, rotation vector in rad then translation in m; DESIGN 10.11) and ``s`` the robust residual
scale.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from recognition.tuning import tuned
from scenes.features import Cylinder, Plane
from scenes.model import SceneModel
from sensors.range_image import Scan

from .prediction import Prediction

__all__ = ["IcpParams", "IcpResult", "model_normals", "icp_refine", "icp_fixed_directions"]


@dataclass(frozen=True)
class IcpParams:
    """Parameters of :func:`icp_refine`.

    Attributes
    ----------
    source_stride : pixel stride of the scan points used as the source.
    max_source_points : the source is thinned on a regular stride to at most this many points.
    max_corr_rel : first-pass maximum correspondence distance, as a fraction of the median range ...
    max_corr_min_m : ... but at least this (metres).
    narrow_factor : each further pass divides the correspondence distance by this ...
    n_passes : ... over this many passes ...
    spacing_factor : ... but never below this many times the target's point spacing at the median range
        (the target is a prediction on a pixel stride: nearest neighbours are that far apart).
    tukey_rel : Tukey kernel parameter as a fraction of the pass's correspondence distance.
    max_iterations : per pass.
    min_fitness : below this inlier fraction the result is not ok.

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    source_stride: int = tuned(3, unit="px", chosen="not tuned: set in c9baa1a")
    max_source_points: int = tuned(3000, unit="points", chosen="not tuned: a speed bound, set in af4da75")
    max_corr_rel: float = tuned(0.03, unit="fraction of range", chosen="not tuned: set in af4da75")
    max_corr_min_m: float = tuned(0.005, unit="m", chosen="not tuned: set in c9baa1a")
    narrow_factor: float = tuned(3.0, unit="ratio", chosen="not tuned: set in af4da75")
    n_passes: int = tuned(3, unit="count", chosen="not tuned: set in af4da75")
    spacing_factor: float = tuned(2.5, unit="spacings", chosen="not tuned: set in af4da75")
    tukey_rel: float = tuned(0.5, unit="fraction", chosen="not tuned: set in c9baa1a")
    max_iterations: int = tuned(15, unit="count", chosen="not tuned: set in af4da75")
    min_fitness: float = tuned(0.2, unit="fraction", chosen="not tuned: set in c9baa1a")

    def __post_init__(self):
        if self.source_stride < 1 or self.max_source_points < 10 or self.max_iterations < 1 or self.n_passes < 1:
            raise ValueError("source_stride >= 1, max_source_points >= 10, max_iterations >= 1 and n_passes >= 1 "
                             "are required")
        for name in ("max_corr_rel", "max_corr_min_m", "narrow_factor", "tukey_rel"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class IcpResult:
    """Result of :func:`icp_refine`.

    Attributes
    ----------
    ok : bool; reason : str ("" when ok).
    T_world_sensor : ndarray of shape (4, 4) (the initial pose when not ok).
    cov_T_world_sensor : ndarray of shape (6, 6) or None.
    fitness : inlier fraction of the source; rmse_m : inlier RMS point-to-plane residual (metres).
    n_correspondences : int; free_dof : directions the correspondences leave unconstrained.
    free_dof_without_one : the most directions left unconstrained when the correspondences of one movable model
        object (any kind but :data:`STABLE_KINDS`) are left out; ``resting_on`` that object's id ("" when none
        leaves a direction free).
    loose_without_one : the same with directions counted when the rest fixes them no better than the
        ``tolerance`` of :func:`icp_refine` (``free_dof_without_one`` without one); ``loose_on`` that object.
    """

    ok: bool
    reason: str
    T_world_sensor: np.ndarray
    cov_T_world_sensor: np.ndarray | None
    fitness: float
    rmse_m: float
    n_correspondences: int
    free_dof: int
    free_dof_without_one: int = 0
    resting_on: str = ""
    loose_without_one: int = 0
    loose_on: str = ""


def model_normals(model: SceneModel, feature_ids: np.ndarray, parts: np.ndarray, points: np.ndarray
                  ) -> np.ndarray:
    """Unit outward normals (N, 3) of the model features at world points (N, 3) on them.

    Plane faces and cylinder caps are exact; other surfaces use the central-difference gradient of the
    feature's signed distance.
    """
    out = np.full(points.shape, np.nan)
    eps = 1e-5
    for fid in np.unique(feature_ids):
        sel = feature_ids == fid
        f = model.feature(str(fid))
        if isinstance(f, Plane):
            out[sel] = f.normal
            continue
        p = points[sel]
        g = np.zeros_like(p)
        for k in range(3):
            dv = np.zeros(3)
            dv[k] = eps
            g[:, k] = f.signed_distance(p + dv) - f.signed_distance(p - dv)
        n = np.linalg.norm(g, axis=1, keepdims=True)
        g = g / np.where(n > 0, n, 1.0)
        if isinstance(f, Cylinder):
            pt = parts[sel]
            g[pt == "cap_start"] = -f.axis
            g[pt == "cap_end"] = f.axis
        out[sel] = g
    return out


#: object kinds a pose may rest on alone: the building's shell (a partially correct model's equipment may have
#: moved, its walls and floor are where the model has them)
STABLE_KINDS = ("floor", "wall")


def _info(src_w: np.ndarray, tgt: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = np.sum((src_w - tgt) * nrm, axis=1)
    J = np.hstack([np.cross(src_w, nrm), nrm])
    return r, J


def icp_refine(scan: Scan, prediction: Prediction, model: SceneModel, T_init: np.ndarray | None = None,
               params: IcpParams = IcpParams(), source_mask: np.ndarray | None = None,
               tolerance: tuple[float, float] | None = None) -> IcpResult:
    """Refine ``T_world_sensor`` (default: the prediction's pose) against the predicted-visible model.

    Parameters
    ----------
    scan : the scan (points in the sensor frame).
    prediction : the model's predicted range image at (or near) the pose; its points are the target.
    model : the a priori model (for the target normals).
    T_init : ndarray of shape (4, 4), the starting pose.
    params : :class:`IcpParams`.
    source_mask : optional bool (H, W): the scan pixels that may be source points (default: all valid).
    tolerance : ``(degrees, fraction of the median range)``, optional: a direction counts as loose without one
        movable object (``loose_without_one``) when the rest of the correspondences leave it a standard
        deviation beyond this, not only beyond the 0.1 (rad, or median ranges) that makes a direction free:
        a pose whose other surfaces fix it to 5 deg is not fixed to the 1 deg it claims, and the object (a moved
        pipe run) carries it the rest of the way.

    Returns
    -------
    IcpResult (``ok=False`` with the reason when there is too little to register or the fit is poor).
    """
    import open3d as o3d

    T0 = np.array(prediction.T_world_sensor if T_init is None else T_init, dtype=np.float64)
    fail = IcpResult(False, "", T0, None, 0.0, math.nan, 0, 6)
    target = _target(prediction, model)
    if len(target[0]) < 30:
        return _replace_reason(fail, f"the model predicts too few visible points ({len(target[0])})")
    tgt, nrm, objects = target
    src = _source(scan, params, source_mask)
    if len(src) < 30:
        return _replace_reason(fail, f"too few scan points ({len(src)})")
    med_range = float(np.median(np.linalg.norm(src, axis=1)))
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src))
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt))
    target.normals = o3d.utility.Vector3dVector(nrm)
    d = max(params.max_corr_rel * med_range, params.max_corr_min_m)
    pitch = getattr(prediction.sensor, "pixel_pitch_rad", None)
    floor = params.spacing_factor * med_range * float(pitch) if pitch else 0.0
    raw = [max(d / params.narrow_factor**k, params.max_corr_min_m) for k in range(params.n_passes)]
    threads = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)  # a parallel reduction sums in thread order: one thread keeps ICP deterministic
    try:
        T, res = _icp_passes(o3d, source, target, raw, floor, T0, params)
    finally:
        o3d.utility.set_max_threads(threads)
    corr = np.asarray(res.correspondence_set)
    if len(corr) < 30 or res.fitness < params.min_fitness:
        return IcpResult(False, f"ICP fitness {res.fitness:.2f} below {params.min_fitness} "
                         f"({len(corr)} correspondences)", T0, None, float(res.fitness), float(res.inlier_rmse),
                         len(corr), 6)
    src_w = src[corr[:, 0]] @ T[:3, :3].T + T[:3, 3]
    r, J = _info(src_w, tgt[corr[:, 1]], nrm[corr[:, 1]])
    scale = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    scale = max(scale, 1e-6)
    inl = np.abs(r) <= 3 * scale
    Ji = J[inl] / scale
    info = Ji.T @ Ji
    from .pose import free_dof_of

    free, _ = free_dof_of(Ji, med_range, 0.1)
    free_without, resting_on, loose_without, loose_on = 0, "", 0, ""
    objs = objects[corr[:, 1]][inl]
    if tolerance is not None:  # translations scaled so that both parts of the tolerance are one sigma
        loose_length, loose_sigma = med_range * math.radians(tolerance[0]) / tolerance[1], math.radians(tolerance[0])
    for o in sorted(set(objs.tolist()) - {""}):  # each movable object left out in turn
        rest = Ji[objs != o]
        k, _ = free_dof_of(rest, med_range, 0.1)
        loose = k if tolerance is None else free_dof_of(rest, loose_length, loose_sigma)[0]
        if k > free_without:
            free_without, resting_on = k, o
        if loose > loose_without:
            loose_without, loose_on = loose, o
    cov = np.linalg.pinv(info, rcond=1e-12, hermitian=True)
    return IcpResult(True, "", T, cov, float(res.fitness), float(np.sqrt(np.mean(r[inl] ** 2))), len(corr), free,
                     free_without, resting_on, loose_without, loose_on)


def _target(prediction: Prediction, model: SceneModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ICP's target: the predicted points (N, 3) in the world frame, their analytic normals (N, 3), and the
    movable object (N,) each lies on ("" for the stable kinds)."""
    pts_s = prediction.points_sensor().reshape(-1, 3)
    sid = prediction.surface_id.ravel()
    keep = np.flatnonzero((sid >= 0) & np.isfinite(pts_s[:, 0]))
    Tp = prediction.T_world_sensor
    tgt = pts_s[keep] @ Tp[:3, :3].T + Tp[:3, 3]
    fids = np.array([s.feature_id for s in prediction.surfaces], dtype=object)[sid[keep]]
    parts = np.array([s.part for s in prediction.surfaces], dtype=object)[sid[keep]]
    nrm = model_normals(model, fids, parts, tgt) if len(keep) else np.zeros((0, 3))
    good = np.all(np.isfinite(nrm), axis=1)
    movable = {f: model.object_of(f) for f in set(fids.tolist())}
    movable = {f: o for f, o in movable.items() if model.object(o).kind not in STABLE_KINDS}
    objects = np.array([movable.get(f, "") for f in fids[good].tolist()], dtype=object)
    return tgt[good], nrm[good], objects


def _source(scan: Scan, params: IcpParams, source_mask: np.ndarray | None) -> np.ndarray:
    """ICP's source: the scan's points (N, 3, sensor frame) on ``params.source_stride`` within ``source_mask``,
    thinned on a regular stride to at most ``params.max_source_points``."""
    s = params.source_stride
    src = scan.points[::s, ::s].reshape(-1, 3)
    usable = np.all(np.isfinite(src), axis=1)
    if source_mask is not None:
        usable &= np.asarray(source_mask, dtype=bool)[::s, ::s].ravel()
    src = src[usable]
    if len(src) > params.max_source_points:
        src = src[np.linspace(0, len(src) - 1, params.max_source_points).round().astype(np.intp)]
    return src


def icp_fixed_directions(scan: Scan, prediction: Prediction, model: SceneModel, T_init: np.ndarray,
                         source_mask: np.ndarray, reach_m: float, params: IcpParams = IcpParams(),
                         iterations: int = 30, min_eigen_ratio: float = 1e-4) -> IcpResult:
    """Register the scan points of ``source_mask`` to the predicted-visible model, moving ``T_init`` only in the
    directions those points fix.

    A few patches (a wall alone) leave directions of the pose free; an unconstrained solve lets the pose drift
    along them until nothing corresponds. Here each Gauss-Newton step of the point-to-plane residuals (Tukey
    weights at half the correspondence distance) is solved in the span of the information's eigenvectors whose
    eigenvalues exceed ``min_eigen_ratio`` of the largest (rotation in rad, translation scaled by the median
    range): the free directions keep ``T_init``'s values. Correspondences reach ``reach_m`` at first, a third of
    that after a third of the iterations, a ninth after two thirds (floored by ``params.max_corr_min_m``).

    Returns an :class:`IcpResult` (no covariance; ``free_dof`` the directions left at ``T_init``), not ok when
    fewer than ``params.min_fitness`` of the source points correspond at the end.
    """
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    T = np.array(T_init, dtype=np.float64)
    fail = IcpResult(False, "", T, None, 0.0, math.nan, 0, 6)
    tgt, nrm, _ = _target(prediction, model)
    src = _source(scan, params, source_mask)
    if len(tgt) < 30 or len(src) < 30:
        return _replace_reason(fail, f"too few points ({len(src)} of the scan, {len(tgt)} of the model)")
    med_range = float(np.median(np.linalg.norm(src, axis=1)))
    S = np.diag([1.0, 1.0, 1.0, med_range, med_range, med_range])
    tree = cKDTree(tgt)
    free, n_corr = 6, 0
    for it in range(iterations):
        reach = max(reach_m / 3 ** (3 * it // iterations), params.max_corr_min_m)
        src_w = src @ T[:3, :3].T + T[:3, 3]
        dist, idx = tree.query(src_w, distance_upper_bound=reach)
        hit = np.isfinite(dist)
        n_corr = int(hit.sum())
        if n_corr < 30:
            return _replace_reason(fail, f"{n_corr} correspondences within {reach:.3f} m")
        r, J = _info(src_w[hit], tgt[idx[hit]], nrm[idx[hit]])
        c = reach / 2
        w = np.where(np.abs(r) < c, (1 - (r / c) ** 2) ** 2, 0.0)
        Js = J @ S
        info = Js.T @ (w[:, None] * Js)
        vals, vecs = np.linalg.eigh(info)
        fixed = vals > min_eigen_ratio * max(float(vals[-1]), 1e-300)
        free = int((~fixed).sum())
        g = vecs[:, fixed].T @ (Js.T @ (w * r))
        step = S @ (vecs[:, fixed] @ (-g / vals[fixed]))
        R_d = Rotation.from_rotvec(step[:3]).as_matrix()
        T = np.vstack([np.hstack([R_d @ T[:3, :3], (R_d @ T[:3, 3] + step[3:])[:, None]]), [0, 0, 0, 1.0]])
    fitness = n_corr / len(src)
    if fitness < params.min_fitness:
        return _replace_reason(IcpResult(False, "", T_init, None, fitness, math.nan, n_corr, free),
                               f"fitness {fitness:.2f} below {params.min_fitness}")
    return IcpResult(True, "", T, None, fitness, math.nan, n_corr, free)


def _icp_passes(o3d, source, target, raw: list[float], floor: float, T: np.ndarray, params: IcpParams):
    """Point-to-plane ICP passes with narrowing correspondence distances; returns (T, last result)."""
    res = None
    for dist_raw in raw:
        # the correspondence search is floored by the target spacing, the robust kernel (on the
        # point-to-plane residual, exact on analytic normals) is not: changed parts must not pull
        dist = max(dist_raw, floor)
        est = o3d.pipelines.registration.TransformationEstimationPointToPlane(
            o3d.pipelines.registration.TukeyLoss(k=params.tukey_rel * dist_raw))
        res = o3d.pipelines.registration.registration_icp(
            source, target, dist, T, est,
            o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7,
                                                              max_iteration=params.max_iterations))
        T = np.asarray(res.transformation).copy()
    return T, res


def _replace_reason(r: IcpResult, reason: str) -> IcpResult:
    return IcpResult(False, reason, r.T_world_sensor, None, r.fitness, r.rmse_m, r.n_correspondences, r.free_dof)
