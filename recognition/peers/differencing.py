"""Change-detection peers: what a user does without the paper's tight/loose matching of fitted primitives.

Both take the registered scan and the a priori model, find the data the model does not explain, cluster it
into connected pieces of the image, and turn the evidence into the core's labels
(:data:`scenes.vocabulary.CHANGE_MAP_LABELS`):

* ``diff_change`` - **per-pixel differencing** of the measured range against the model's predicted range
  image at the estimated pose: a pixel is explained when ``|range - predicted| <= tau``, *behind* (the model
  surface is not there: revealed background) when larger, *in front* when smaller (something new or moved
  there, or an occluder); data where the model predicts nothing is unexplained.
* ``c2m_change`` - **cloud-to-model distance** (C2M, as in CloudCompare): each scan point's distance to the
  nearest point of a dense sampling of the model (point-to-plane against that sample's normal), and, for
  the missing side, each predicted model point's distance to the nearest scan point (M2C), pixels occluded
  by nearer data excluded. M3C2 (py4dgeo) is not offered: see :func:`missing_peers`.

``tau = max(k_sigma * sigma, min_threshold_m)`` with sigma the scan's own per-pixel noise (the noise model
at the measured range) plus a pose allowance of ``pose_sigma_m + pose_sigma_rad * range``.

Feature labels (per a priori feature predicted visible): ``unobserved`` when fewer than ``min_pixels`` of
its predicted pixels were judged (explained or revealed; occluded ones do not count); ``unchanged`` when at
least ``present_fraction`` of them are explained; ``altered`` when a smaller share but at least
``altered_fraction`` is explained (the surface is there but off: a radius change); otherwise ``moved`` when an
unexplained cluster of comparable size (``size_ratio``) lies within ``move_radius_m`` of the feature's
predicted centroid (displacement = distance between the centroids; each cluster is claimed once, nearest
first), else ``missing``. Unclaimed clusters of at least ``new_min_pixels`` are ``new``. Objects are labelled
by counting their features' labels (:func:`recognition.change.object_label`, as the core).
"""

from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.ndimage as ndi
from scipy.spatial import cKDTree

from recognition.change import (
    PIXEL_BEHIND,
    PIXEL_EXPLAINED,
    PIXEL_FRONT,
    PIXEL_NONE,
    ChangeResult,
    FeatureChange,
    object_label,
)
from recognition.describe import core_sigma
from recognition.tuning import tuned
from scenes.model import SceneModel
from scenes.vocabulary import ALTERED, CHANGE_MAP_LABELS, MISSING, MOVED, NEW, UNCHANGED, UNOBSERVED
from sensors.range_image import Scan

__all__ = ["DiffChangeParams", "diff_changes", "available_peers", "missing_peers"]


@dataclass(frozen=True)
class DiffChangeParams:
    """Parameters of :func:`diff_changes` (lengths in metres).

    Attributes
    ----------
    distance : ``"range"`` (per-pixel differencing) or ``"c2m"`` (cloud-to-model distance).
    k_sigma, min_threshold_m, pose_sigma_m, pose_sigma_rad : the threshold ``tau`` (module docstring).
    min_pixels, present_fraction, altered_fraction : feature verdicts.
    move_radius_m, size_ratio : how far and how different in size a cluster may be to make a feature moved.
    new_min_pixels : smallest unexplained cluster reported new.
    model_spacing_m : sampling of the model for C2M.

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    distance: str = tuned("range", unit="-", chosen="per-pixel differencing (c2m_change sets c2m)")
    k_sigma: float = tuned(4.0, unit="sigma", chosen="not tuned: the core's ChangeParams.k_sigma (a837a85)")
    min_threshold_m: float = tuned(0.01, unit="m", chosen="not tuned: set in a837a85")
    pose_sigma_m: float = tuned(5e-4, unit="m", chosen="not tuned: the core's pose sigma floor (a837a85)")
    pose_sigma_rad: float = tuned(2e-4, unit="rad", chosen="not tuned: the core's pose sigma floor (a837a85)")
    min_pixels: int = tuned(40, unit="px", chosen="not tuned: the core's ChangeParams.min_pixels (a837a85)")
    present_fraction: float = tuned(0.5, unit="fraction", chosen="not tuned: the core's value (a837a85)")
    altered_fraction: float = tuned(0.2, unit="fraction", chosen="not tuned: set in a837a85")
    move_radius_m: float = tuned(0.6, unit="m", chosen="not tuned: set in a837a85")
    size_ratio: float = tuned(4.0, unit="ratio", chosen="not tuned: set in a837a85")
    new_min_pixels: int = tuned(60, unit="px", chosen="not tuned: the core's ChangeParams.new_min_pixels (a837a85)")
    model_spacing_m: float = tuned(0.01, unit="m", chosen="not tuned: set in a837a85")

    def __post_init__(self):
        if self.distance not in ("range", "c2m"):
            raise ValueError(f"distance must be 'range' or 'c2m', got {self.distance!r}")
        for name in ("k_sigma", "min_threshold_m", "present_fraction", "move_radius_m", "size_ratio",
                     "model_spacing_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0 <= self.altered_fraction <= self.present_fraction <= 1:
            raise ValueError("need 0 <= altered_fraction <= present_fraction <= 1")
        if self.min_pixels < 1 or self.new_min_pixels < 1:
            raise ValueError("min_pixels and new_min_pixels must be >= 1")

    @classmethod
    def from_dict(cls, params: dict[str, Any] | None, **defaults) -> DiffChangeParams:
        """From a suite's method parameters; unknown keys are a ``ValueError`` naming them."""
        merged = {**defaults, **(params or {})}
        unknown = set(merged) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown change parameter(s): {', '.join(sorted(unknown))}")
        return cls(**merged)


def _world(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ T[:3, :3].T + T[:3, 3]


_SAMPLES: OrderedDict[tuple, tuple[np.ndarray, np.ndarray, cKDTree]] = OrderedDict()


def _model_samples(model: SceneModel, spacing: float) -> tuple[np.ndarray, np.ndarray, cKDTree]:
    """The model sampled at ``spacing`` (fixed seed 0), outward normals and a KD-tree; cached for the last
    two (model, spacing) pairs, as a user would precompute them (its time is reported as ``model``)."""
    key = (id(model), len(model.features), round(spacing, 6))
    if key not in _SAMPLES:
        rng = np.random.default_rng(0)
        pts, nrm = zip(*(f.sample_spacing(spacing, rng) for f in model.features), strict=True)
        pts = np.concatenate(pts)
        _SAMPLES[key] = (pts, np.concatenate(nrm), cKDTree(pts))
        while len(_SAMPLES) > 2:
            _SAMPLES.popitem(last=False)
    return _SAMPLES[key]


def diff_changes(scan: Scan, model: SceneModel, T_world_sensor: np.ndarray, predicted: Any,
                 params: DiffChangeParams = DiffChangeParams()) -> ChangeResult:
    """Label every a priori feature and find new clusters by differencing the scan against the model.

    Parameters
    ----------
    scan : the registered scan.
    model : the a priori model (world frame).
    T_world_sensor : ndarray of shape (4, 4), the estimated pose.
    predicted : the model's prediction at ``T_world_sensor`` at full resolution (``range``, ``surface_id``,
        ``feature_pixels()``).
    params : DiffChangeParams

    Returns
    -------
    ChangeResult
        ``new_patches`` are cluster ids (keys of ``new_patch_pixels``), not scene-description patch ids.
    """
    t0 = time.perf_counter()
    t_model = 0.0
    T = np.asarray(T_world_sensor, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"expected T_world_sensor of shape (4, 4), got {T.shape}")
    shape = scan.range.shape
    if predicted.range.shape != shape:
        raise ValueError(f"the prediction must be at full resolution {shape}, got {predicted.range.shape}")
    valid = scan.valid
    r = np.nan_to_num(scan.range)
    tau = np.maximum(params.k_sigma * np.hypot(np.nan_to_num(core_sigma(scan)),
                                               params.pose_sigma_m + params.pose_sigma_rad * r),
                     params.min_threshold_m)
    pred_ok = np.isfinite(predicted.range)
    d = scan.range - predicted.range  # > 0: data behind the model surface
    pix = np.full(shape, PIXEL_NONE, dtype=np.int8)
    both = valid & pred_ok
    if params.distance == "range":
        explained = both & (np.abs(d) <= tau)
        unexplained_data = valid & ~explained
        model_missing = both & (d > tau)  # model surface not found: the ray went through it
    else:
        t_model = time.perf_counter()
        samples, normals, tree = _model_samples(model, params.model_spacing_m)
        t_model = time.perf_counter() - t_model
        pw = _world(T, scan.points[valid])
        dist, idx = tree.query(pw, k=1, distance_upper_bound=1.0)
        near = np.isfinite(dist)
        c2m = np.full(len(pw), np.inf)
        c2m[near] = np.hypot(np.abs(np.sum((pw[near] - samples[idx[near]]) * normals[idx[near]], axis=1)),
                             np.maximum(dist[near] - params.model_spacing_m, 0.0))
        c2m_img = np.full(shape, np.inf)
        c2m_img[valid] = c2m
        explained_data = valid & (c2m_img <= tau)
        unexplained_data = valid & ~explained_data
        # M2C: predicted model points with no scan point near them, unless nearer data occludes them
        rays = scan.sensor.ray_directions()
        mw = _world(T, rays[pred_ok] * predicted.range[pred_ok][:, None])
        scan_tree = cKDTree(pw) if len(pw) else None
        m2c = np.full(len(mw), np.inf)
        if scan_tree is not None:
            m2c, _ = scan_tree.query(mw, k=1, distance_upper_bound=1.0)
        m2c_img = np.full(shape, np.inf)
        m2c_img[pred_ok] = m2c
        occluded = both & (d < -tau)
        explained = pred_ok & (m2c_img <= tau) & ~occluded
        model_missing = both & ~explained & ~occluded
    pix[valid & ~unexplained_data] = PIXEL_EXPLAINED
    pix[unexplained_data & pred_ok & (d > 0)] = PIXEL_BEHIND
    pix[unexplained_data & ~(pred_ok & (d > 0))] = PIXEL_FRONT
    # clusters of unexplained data, not across range jumps
    clusters, n_clusters = ndi.label(unexplained_data & _no_jump(scan.range, tau), structure=np.ones((3, 3), bool))
    cl_flat = clusters.reshape(-1)
    order = np.argsort(cl_flat, kind="stable")
    starts = np.searchsorted(cl_flat[order], np.arange(1, n_clusters + 2))
    cluster_pix = {c: order[starts[c - 1]:starts[c]] for c in range(1, n_clusters + 1)
                   if starts[c] - starts[c - 1] >= params.new_min_pixels}
    pts_flat = scan.points.reshape(-1, 3)
    cluster_centroid = {c: _world(T, pts_flat[p]).mean(axis=0) for c, p in cluster_pix.items()}
    rays_flat = scan.sensor.ray_directions().reshape(-1, 3)
    pred_flat = predicted.range.reshape(-1)
    expl_flat, miss_flat = explained.reshape(-1), model_missing.reshape(-1)
    occl_flat = (both & (d < -tau)).reshape(-1)
    features: dict[str, FeatureChange] = {}
    absent: list[tuple[str, np.ndarray, int]] = []
    feature_pixels = predicted.feature_pixels()
    for fid, fp in feature_pixels.items():
        found, revealed, occl = int(expl_flat[fp].sum()), int(miss_flat[fp].sum()), int(occl_flat[fp].sum())
        judged = found + revealed
        if judged < params.min_pixels:
            features[fid] = FeatureChange(UNOBSERVED, None, (), found, revealed, occl, "too few pixels judged")
        elif found >= params.present_fraction * judged:
            features[fid] = FeatureChange(UNCHANGED, None, (), found, revealed, occl, "explained")
        elif found >= params.altered_fraction * judged:
            features[fid] = FeatureChange(ALTERED, None, (), found, revealed, occl, "partly explained")
        else:
            centroid = _world(T, rays_flat[fp] * pred_flat[fp][:, None]).mean(axis=0)
            absent.append((fid, centroid, len(fp)))
            features[fid] = FeatureChange(MISSING, None, (), found, revealed, occl, "predicted, not found")
    claimed: set[int] = set()
    pairs = sorted((float(np.linalg.norm(cluster_centroid[c] - cen)), fid, c, n)
                   for fid, cen, n in absent for c in cluster_pix)
    moved: set[str] = set()
    for dist, fid, c, n in pairs:
        if fid in moved or c in claimed or dist > params.move_radius_m:
            continue
        ratio = len(cluster_pix[c]) / max(n, 1)
        if 1 / params.size_ratio <= ratio <= params.size_ratio:
            old = features[fid]
            features[fid] = FeatureChange(MOVED, dist, (c,), old.found, old.revealed, old.occluded,
                                          "an unexplained cluster nearby")
            claimed.add(c)
            moved.add(fid)
    for f in model.features:
        features.setdefault(f.id, FeatureChange(UNOBSERVED, reason="not predicted visible"))
    new = tuple(sorted(c for c in cluster_pix if c not in claimed))
    objects = {o.id: object_label([features[f.id] for f in o.features]) for o in model.objects}
    label_map = np.full(shape, -1, dtype=np.int8)
    lm = label_map.reshape(-1)
    for fid, fp in feature_pixels.items():
        if features[fid].label != UNOBSERVED:
            lm[fp] = CHANGE_MAP_LABELS.index(features[fid].label)
    for fid in moved:
        lm[cluster_pix[features[fid].patches[0]]] = CHANGE_MAP_LABELS.index(MOVED)
    for c in new:
        lm[cluster_pix[c]] = CHANGE_MAP_LABELS.index(NEW)
    return ChangeResult(features, objects, new, pix, label_map, {c: cluster_pix[c] for c in new},
                        {"change": time.perf_counter() - t0 - t_model, "model": t_model})


def _no_jump(rng: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Pixels not on a range jump (any 4-neighbour further than 10 tau and 5 % of the range): clusters are
    split there."""
    r = np.nan_to_num(rng, nan=np.inf)
    thr = np.maximum(10 * tau, 0.05 * np.nan_to_num(rng))
    jump = np.zeros(rng.shape, dtype=bool)
    for axis in (0, 1):
        with np.errstate(invalid="ignore"):  # inf - inf between two pixels without a return
            diff = np.abs(np.diff(r, axis=axis))
        big = ~(diff <= np.minimum(np.take(thr, range(r.shape[axis] - 1), axis=axis),
                                   np.take(thr, range(1, r.shape[axis]), axis=axis)))
        if axis == 0:
            jump[:-1] |= big
            jump[1:] |= big
        else:
            jump[:, :-1] |= big
            jump[:, 1:] |= big
    return ~jump


def _runner(distance: str):
    def run(description, scan: Scan, model: SceneModel, T_world_sensor: np.ndarray, cov, predictor,
            params: dict[str, Any] | None, predicted=None) -> ChangeResult:
        """Peer ``change`` stage (``description`` and ``cov`` unused; ``predicted`` reused when given at full
        resolution, else cast here and its time reported as ``predict``)."""
        p = DiffChangeParams.from_dict(params, distance=distance)
        t0 = time.perf_counter()
        if predicted is None or predicted.range.shape != scan.range.shape:
            predicted = predictor.predict(scan.sensor, T_world_sensor)
        t_pred = time.perf_counter() - t0
        result = diff_changes(scan, model, T_world_sensor, predicted, p)
        result.timing_s["predict"] = t_pred
        return result

    run.__name__ = f"run_{distance}"
    return run


def available_peers() -> list:
    """The change peers (numpy and scipy only: always available)."""
    from recognition.peers import Peer

    return [
        Peer("diff_change", "change", _runner("range"),
             "per-pixel range differencing against the model's predicted image, clusters into labels",
             {"k_sigma": 4.0, "min_threshold_m": 0.01}),
        Peer("c2m_change", "change", _runner("c2m"),
             "cloud-to-model (C2M) and model-to-cloud distances, clusters into labels",
             {"k_sigma": 4.0, "min_threshold_m": 0.01, "model_spacing_m": 0.01}),
    ]


def missing_peers() -> dict[str, str]:
    """Change peers not offered, with the reason."""
    try:
        import py4dgeo  # noqa: F401
    except ImportError as exc:
        return {"m3c2_change": f"package 'py4dgeo' does not import ({exc}); not installed: it pulls pandas, "
                               "scikit-learn, seaborn, laspy, pooch, requests and more for one algorithm"}
    return {"m3c2_change": "py4dgeo imports but no M3C2 peer is written yet"}
