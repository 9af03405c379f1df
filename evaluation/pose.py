"""Pose metrics (definitions of bop_toolkit's ``pose_error.py``; Hodan et al., "BOP: Benchmark for 6D
Object Pose Estimation", ECCV 2018, doi:10.1007/978-3-030-01249-6_2) and the pose section of a trial.

All functions are pure. Poses are ``T_world_sensor`` (``p_world = R p_sensor + t``); rotation errors are in
degrees, translation errors and ADD in millimetres. Success (DESIGN 10.6): rotation <= 1 deg and translation
<= 1 % of the median true range of the trial. Whether a trial "sees enough structure to constrain 6 DOF" is
decided here from the truth (:func:`constrains_pose`, :func:`twin_ambiguous`), never by the core.
"""

from __future__ import annotations

import math
from collections.abc import Collection

import numpy as np

from evaluation.metrics import MIN_SCORED_PIXELS
from recognition.localisation import AxisPair, PlanePair, PointPair, free_dof_of, residuals
from recognition.localisation.twins import twin_poses
from scenes.features import Cone, Cylinder, Plane, Sphere, Torus
from scenes.geometry import invert_transform
from scenes.model import SceneModel
from scenes.perturb import ChangeTruth
from sensors.range_image import ScanTruth

__all__ = ["rotation_error_deg", "translation_error_mm", "add_mm", "pose_section", "constrains_pose",
           "changed_features", "twin_ambiguous", "constrained_view",
           "SUCCESS_ROTATION_DEG", "SUCCESS_TRANSLATION_FRACTION"]

SUCCESS_ROTATION_DEG = 1.0
SUCCESS_TRANSLATION_FRACTION = 0.01


def _check_R(R, name: str) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"expected {name} of shape (3, 3), got {R.shape}")
    return R


def _check_t(t, name: str) -> np.ndarray:
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"expected {name} of shape (3,), got {t.shape}")
    return t


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Angle of ``R_est R_gt'``: ``arccos((tr(R_est R_gt') - 1) / 2)`` in degrees (bop_toolkit ``re``).

    >>> rotation_error_deg(np.eye(3), np.eye(3))
    0.0
    """
    R_est, R_gt = _check_R(R_est, "R_est"), _check_R(R_gt, "R_gt")
    c = (np.trace(R_est @ R_gt.T) - 1.0) / 2.0
    return math.degrees(math.acos(min(1.0, max(-1.0, float(c)))))


def translation_error_mm(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Euclidean distance of the translations (metres in) in millimetres (bop_toolkit ``te``)."""
    return 1000.0 * float(np.linalg.norm(_check_t(t_est, "t_est") - _check_t(t_gt, "t_gt")))


def add_mm(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
           model_points: np.ndarray) -> float:
    """ADD: mean distance (mm) of ``model_points`` (N, 3) mapped by the two poses (bop_toolkit ``add``).

    The points are in the frame the poses map from (here: sensor-frame points, e.g. the scan's, or any
    fixed sample); NaN when there are no points.
    """
    R_est, R_gt = _check_R(R_est, "R_est"), _check_R(R_gt, "R_gt")
    t_est, t_gt = _check_t(t_est, "t_est"), _check_t(t_gt, "t_gt")
    pts = np.asarray(model_points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"expected model_points of shape (N, 3), got {pts.shape}")
    if len(pts) == 0:
        return math.nan
    d = pts @ (R_est - R_gt).T + (t_est - t_gt)
    return 1000.0 * float(np.mean(np.linalg.norm(d, axis=1)))


def _errors(T, G, median_true_range_m, model_points):
    if T is None:
        return {"rotation_error_deg": None, "translation_error_mm": None, "add_mm": None, "success": False}
    T = np.asarray(T, dtype=np.float64)
    re = rotation_error_deg(T[:3, :3], G[:3, :3])
    te = translation_error_mm(T[:3, 3], G[:3, 3])
    add = add_mm(T[:3, :3], T[:3, 3], G[:3, :3], G[:3, 3], model_points) if model_points is not None else None
    ok = re <= SUCCESS_ROTATION_DEG and te <= 1000.0 * SUCCESS_TRANSLATION_FRACTION * median_true_range_m
    return {"rotation_error_deg": re, "translation_error_mm": te, "add_mm": add, "success": bool(ok)}


def pose_section(result, truth_T_world_sensor: np.ndarray, median_true_range_m: float, constrained: bool,
                 model_points: np.ndarray | None) -> dict:
    """The ``pose`` section of a trial record.

    Parameters
    ----------
    result : :class:`recognition.localise.PoseResult`.
    truth_T_world_sensor : ndarray of shape (4, 4), the true pose.
    median_true_range_m : median of the trial's true ranges (metres): sets the translation threshold.
    constrained : :func:`constrains_pose` of the trial (from the truth).
    model_points : ndarray of shape (N, 3) or None, points for ADD (sensor frame).

    Returns
    -------
    dict with ``rotation_error_deg``, ``translation_error_mm``, ``add_mm`` (None when the core returned no
    pose), ``success`` (False then), ``constrained``, ``ok``, ``conditional_on`` (the one object a pose that
    passed every other check rests on, "" otherwise), ``confidence``, ``free_dof``, ``initial``
    (the same errors before ICP), ``n_hypotheses``, ``n_nodes``, ``reason``, ``alternatives`` (the other
    distinct poses the core weighed: agreement, separation from the winner, errors), ``agreement`` (the data's
    agreement with the model at the pose, when the result has one: ``confidence`` is then the probability
    the core gives its verdict).
    """
    G = np.asarray(truth_T_world_sensor, dtype=np.float64)
    if G.shape != (4, 4):
        raise ValueError(f"expected truth_T_world_sensor of shape (4, 4), got {G.shape}")
    final = _errors(result.T_world_sensor, G, median_true_range_m, model_points)
    init = _errors(result.T_world_sensor_initial, G, median_true_range_m, model_points)
    out = dict(final)
    out.update({
        "constrained": bool(constrained),
        "ok": bool(result.ok),
        "conditional_on": getattr(result, "conditional_on", ""),
        "reason": result.reason,
        "confidence": float(result.confidence),
        "free_dof": int(result.free_dof),
        "n_hypotheses": int(result.n_hypotheses),
        "n_nodes": int(result.n_nodes),
        "initial": {k: init[k] for k in ("rotation_error_deg", "translation_error_mm", "success")},
        "alternatives": [_alternative(a, G, median_true_range_m) for a in result.alternatives],
    })
    if result.agreement is not None:
        out["agreement"] = float(result.agreement)
    return out


def _alternative(alt, G: np.ndarray, median_true_range_m: float) -> dict:
    """An alternative pose of the core (:class:`recognition.localisation.PoseAlternative`) as the record keeps
    it: its agreement and separation from the winner, and its own errors against the truth."""
    e = _errors(alt.T_world_sensor, G, median_true_range_m, None)
    sep = float(alt.separation)
    return {"agreement": float(alt.agreement), "separation": sep if math.isfinite(sep) else None,
            "rotation_error_deg": e["rotation_error_deg"], "translation_error_mm": e["translation_error_mm"],
            "success": e["success"]}


def twin_ambiguous(truth: ScanTruth, model: SceneModel, predict, exclude: Collection[str] = (), *,
                   min_pixels: int = MIN_SCORED_PIXELS, min_angle_deg: float = 2.0, min_shift_fraction: float = 0.02,
                   k_sigma: float = 3.0, rel: float = 0.002, screen_stride: int = 4) -> bool:
    """Whether a materially different pose explains the truth image as well as the true pose, by the a priori
    model's symmetric or repeated structure (a box corner and a table seen away from the table's edges: turned
    by 180 deg about the box's vertical, the model shows the same image).

    :func:`constrains_pose` decides whether the visible surfaces fix the pose locally; a view that a twin pose
    explains as well is not decided by any data, however fine. The candidates are the twin poses of the visible
    features (:func:`recognition.localisation.twins.twin_poses`: each feature of ``>= min_pixels`` measured
    pixels, not in ``exclude``, carried onto every feature of the same shape, itself included) that differ from
    the truth by at least ``min_angle_deg`` or ``min_shift_fraction`` of the median true range. A twin explains
    the image as well when the measured pixels that the model seen from it does not explain (farther than
    ``k_sigma`` sigma plus ``rel`` of the range) outnumber those it leaves unexplained from the true pose by fewer
    than ``min_pixels`` (one scorable region). Screened on every ``screen_stride``-th pixel, confirmed at full
    resolution.

    Parameters
    ----------
    truth : the trial's :class:`sensors.range_image.ScanTruth`.
    model : the a priori model (what a method matches the data against).
    predict : ``predict(T_world_sensor, stride) -> Prediction`` of ``model`` in the trial's sensor
        (:meth:`recognition.localisation.ModelPredictor.predict` with the sensor bound).
    exclude : features that cannot locate the sensor (:func:`changed_features`).
    """
    T = np.asarray(truth.T_world_sensor, dtype=np.float64)
    tr = np.asarray(truth.true_range, dtype=np.float64)
    if not np.isfinite(tr).any():
        return False
    scale = float(np.nanmedian(tr))
    measured = np.isfinite(tr) & truth.measured
    counts = truth.surface_pixel_counts(truth.measured)
    seen = {truth.surfaces[sid].feature_id for sid, n in counts.items() if n >= min_pixels} - set(exclude)
    twins: dict[tuple, np.ndarray] = {}
    for Tp in twin_poses(T, seen, model):
        far = np.linalg.norm(Tp[:3, 3] - T[:3, 3]) >= min_shift_fraction * scale
        if far or rotation_error_deg(Tp[:3, :3], T[:3, :3]) >= min_angle_deg:
            twins.setdefault(tuple(np.round(Tp[:3].ravel(), 6)), Tp)
    if not twins:
        return False
    tol = k_sigma * np.nan_to_num(np.asarray(truth.sigma, dtype=np.float64), nan=0.0) + rel * np.nan_to_num(tr)

    def unexplained(pose: np.ndarray, stride: int) -> int:
        pred = predict(pose, stride)
        o, (h, w) = pred.offset, pred.range.shape
        sub = (slice(o, None, stride), slice(o, None, stride))
        with np.errstate(invalid="ignore"):
            ok = np.abs(pred.range - tr[sub][:h, :w]) <= tol[sub][:h, :w]
        return int((measured[sub][:h, :w] & ~ok).sum())

    at_truth = {1: None, screen_stride: unexplained(T, screen_stride)}
    for Tp in twins.values():
        if (unexplained(Tp, screen_stride) - at_truth[screen_stride]) * screen_stride**2 >= 4 * min_pixels:
            continue  # far apart on the screening grid: not a candidate
        if at_truth[1] is None:
            at_truth[1] = unexplained(T, 1)
        if unexplained(Tp, 1) - at_truth[1] < min_pixels:
            return True
    return False


def constrained_view(truth: ScanTruth, actual: SceneModel, apriori: SceneModel, predict,
                     exclude: Collection[str] = ()) -> tuple[bool, bool]:
    """``(constrained, twin_ambiguous)`` of a trial: whether it counts as constraining 6 DOF - its visible
    surfaces not in ``exclude`` fix the pose locally (:func:`constrains_pose` on the ``actual`` scene) and no twin
    pose explains its image as well (:func:`twin_ambiguous` against the ``apriori`` model, ``predict`` as there)
    - and whether a twin pose is what left it out."""
    local = bool(constrains_pose(truth, actual, exclude=exclude))
    twin = local and twin_ambiguous(truth, apriori, predict, exclude)
    return local and not twin, twin


def changed_features(changes: ChangeTruth) -> set[str]:
    """Features of the actual scene that cannot locate the sensor against the a priori model (the ``exclude``
    of :func:`constrains_pose`): those the perturbation moved or altered, and the new ones.

    An altered feature keeps its place but not its shape (a pipe of another radius, a smaller sphere): the
    matching keys on shape invariants (DESIGN 6.3), so before the pose is known it is an unknown object; its
    place can be read only once the unchanged part of the model has given the pose.
    """
    return {fid for fid, c in changes.features.items() if c.label in ("moved", "altered")} | \
        set(changes.new_features)


def constrains_pose(truth: ScanTruth, model: SceneModel, min_pixels: int = MIN_SCORED_PIXELS, *,
                    sigma_angle: float = 0.01, sigma_pos_m: float = 0.01, max_sigma: float = 0.1,
                    exclude: Collection[str] = ()) -> bool:
    """Whether the truth surfaces visible with >= ``min_pixels`` measured pixels (``truth.measured``) constrain all
    6 DOF of the pose.

    ``exclude`` names features that cannot locate the sensor against the a priori model: those the
    perturbation moved, altered or added (:func:`changed_features`; a wall and a table seen with a moved pipe
    leave the pose free along the wall, whatever the pipe shows).

    Every such surface contributes its exact constraint (plane face or cap: normal and offset; cylinder and
    cone side: axis line, the cone also its position along the axis; sphere: centre; torus: axis line and
    centre) with sigmas ``sigma_angle`` (rad) and ``sigma_pos_m``, in the sensor frame; the pose is
    constrained when no direction is left with a sigma above ``max_sigma`` (rad, or the median surface
    distance as length unit) - see :func:`recognition.pose.free_dof_of`.

    Parameters
    ----------
    truth : the trial's :class:`sensors.range_image.ScanTruth`.
    model : the scene whose features the truth surfaces name (the actual, perturbed scene).
    """
    counts = truth.surface_pixel_counts(truth.measured)
    T_sw = invert_transform(np.asarray(truth.T_world_sensor, dtype=np.float64))
    by_id = {f.id: f for f in model.features}
    pairs = []
    dists = []
    for sid, n in counts.items():
        if n < min_pixels:
            continue
        surf = truth.surfaces[sid]
        f = by_id.get(surf.feature_id)
        if f is None or surf.feature_id in exclude:
            continue
        f = f.transformed(T_sw)
        if isinstance(f, Plane):
            pairs.append(PlanePair(f.normal, f.centre, f.normal, float(f.normal @ f.centre), sigma_angle,
                                   sigma_pos_m))
            dists.append(np.linalg.norm(f.centre))
        elif isinstance(f, Cylinder):
            if surf.part.startswith("cap"):
                a = f.axis if surf.part == "cap_end" else -f.axis
                c = f.centre + (0.5 if surf.part == "cap_end" else -0.5) * f.length * f.axis
                pairs.append(PlanePair(a, c, a, float(a @ c), sigma_angle, sigma_pos_m))
                dists.append(np.linalg.norm(c))
            else:
                pairs.append(AxisPair(f.axis, f.centre, f.axis, f.centre, sigma_angle, sigma_pos_m))
                dists.append(np.linalg.norm(f.centre))
        elif isinstance(f, Cone):
            mid = f.apex + 0.5 * (f.start + f.end) * f.axis
            pairs.append(AxisPair(f.axis, mid, f.axis, f.apex, sigma_angle, sigma_pos_m, signed=True,
                                  along_m=0.5 * (f.start + f.end), sigma_along=sigma_pos_m / max(
                                      math.tan(f.half_angle), 1e-3)))
            dists.append(np.linalg.norm(mid))
        elif isinstance(f, Sphere):
            pairs.append(PointPair(f.centre, f.centre, sigma_pos_m))
            dists.append(np.linalg.norm(f.centre))
        elif isinstance(f, Torus):
            pairs.append(AxisPair(f.axis, f.centre, f.axis, f.centre, sigma_angle, sigma_pos_m))
            pairs.append(PointPair(f.centre, f.centre, sigma_pos_m))
            dists.append(np.linalg.norm(f.centre))
    if not pairs:
        return False
    _, J = residuals(pairs, (1,) * len(pairs), np.eye(4))
    free, _ = free_dof_of(J, float(np.median(dists)), max_sigma)
    return free == 0
