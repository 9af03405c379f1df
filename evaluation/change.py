"""Change-detection evaluation against the perturbation truth (DESIGN 7, 10.6 and 10.7).

Which features count is decided here from the truth, never by the core: a feature present in the actual
scene (unchanged, moved, altered, new) is observable when the truth image shows >= 200 of its pixels; a
missing feature when the a priori model, ray cast from the true pose, shows >= 200 of its pixels
unoccluded by the actual scene; a moved feature when either its new or its old place qualifies.
Only measured pixels count (the sensor returned a point: no dropout flag), as in the segmentation scores: a
box top at grazing incidence that returned 250 of its 1200 pixels cannot be half labelled ``new``.
Unobserved features are excluded from scoring.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from evaluation.metrics import MIN_SCORED_PIXELS
from recognition.change import ChangeResult
from recognition.localisation import Prediction, pixels_by_feature
from scenes.model import SceneModel
from scenes.perturb import ChangeTruth, change_kind
from scenes.vocabulary import CHANGE_MAP_LABELS, NEW
from sensors.range_image import ScanTruth

MIN_PIXELS = MIN_SCORED_PIXELS  # features showing fewer pixels are not observable (evaluation.metrics)


def observable_features(truth: ScanTruth, change_truth: ChangeTruth, apriori_at_truth: Prediction,
                        min_pixels: int = MIN_PIXELS) -> dict[str, str]:
    """Truth label of every observable feature (a priori features and new ones)."""
    actual_pix = _measured_pixels_by_feature(truth)
    # a priori pixels not occluded by the actual scene: the model surface is at or in front of what is there
    tol = 3 * np.nan_to_num(truth.sigma, nan=0.0) + 1e-3
    unoccluded = np.isfinite(apriori_at_truth.range) & ~(truth.true_range < apriori_at_truth.range - tol) & \
        truth.measured
    sid = np.where(unoccluded, apriori_at_truth.surface_id, -1)
    old_pix = pixels_by_feature(sid, tuple(s.feature_id for s in apriori_at_truth.surfaces))
    out = {}
    for fid, change in change_truth.features.items():
        n_new = len(actual_pix.get(fid, ()))
        n_old = len(old_pix.get(fid, ()))
        if change.label == "missing":
            ok = n_old >= min_pixels
        elif change.label == "moved":
            ok = n_new >= min_pixels or n_old >= min_pixels
        else:
            ok = n_new >= min_pixels
        if ok:
            out[fid] = change.label
    for fid in change_truth.new_features:
        if len(actual_pix.get(fid, ())) >= min_pixels:
            out[fid] = "new"
    return out


def _measured_pixels_by_feature(truth: ScanTruth) -> dict[str, np.ndarray]:
    sid = np.where(truth.measured, truth.surface_id, -1)
    return pixels_by_feature(sid, tuple(s.feature_id for s in truth.surfaces))


def kinds_of_features(*models: SceneModel) -> dict[str, str]:
    """The change kind (:func:`scenes.perturb.change_kind`: ``cabinet``, ``tank``, ``sphere_tank``, ``wall``,
    ``pipe_run``, ...) of every feature of the given models, by feature id: what ``altered_by_kind`` groups by."""
    return {f.id: change_kind(o) for m in models for o in m.objects for f in o.features}


def change_section(result: ChangeResult, truth: ScanTruth, change_truth: ChangeTruth,
                   apriori_at_truth: Prediction, object_of: dict[str, str],
                   min_pixels: int = MIN_PIXELS, observable: dict[str, str] | None = None,
                   kind_of: dict[str, str] | None = None) -> dict[str, Any]:
    """Per-trial change record: (truth, predicted) pairs for observable features and objects, false ``new``
    patches, and the displacement error of correctly labelled moved features.

    ``observable``: :func:`observable_features` of this truth, when the caller has it already (it depends on
    the truth only, so every method of a trial shares it). ``kind_of``: the change kind of each a priori
    feature's object (:func:`kinds_of_features`); each feature row then says its ``kind``."""
    if observable is None:
        observable = observable_features(truth, change_truth, apriori_at_truth, min_pixels)
    actual_pix = _measured_pixels_by_feature(truth)
    label_map = result.label_map.reshape(-1)
    new_idx = CHANGE_MAP_LABELS.index(NEW)  # the core's change map indexes the shared labels
    features = []
    for fid, t in sorted(observable.items()):
        if t == "new":
            pix = actual_pix.get(fid, np.zeros(0, int))
            share = float(np.mean(label_map[pix] == new_idx)) if len(pix) else 0.0
            pred = "new" if share >= 0.5 else "none"
        else:
            pred = result.features[fid].label if fid in result.features else "none"
        row = {"feature": fid, "truth": t, "predicted": pred}
        if kind_of is not None and t != "new" and fid in kind_of:
            row["kind"] = kind_of[fid]
        features.append(row)
    # new patches lying mostly on a priori truth surfaces that are not new: false alarms
    sid_flat = truth.surface_id.reshape(-1)
    new_truth = set(change_truth.new_features)
    surface_feature = np.array([s.feature_id for s in truth.surfaces] + [""], dtype=object)
    n_false_new = 0
    for pid in result.new_patches:
        owners = surface_feature[sid_flat[result.new_patch_pixels[pid]]]
        owner, count = Counter(owners).most_common(1)[0]
        if owner not in new_truth:
            features.append({"feature": owner or None, "truth": "none", "predicted": "new", "patch": int(pid)})
            n_false_new += 1
    displacement_errors = []
    for row in features:
        if row["truth"] == "moved" and row["predicted"] == "moved":
            est = result.features[row["feature"]].displacement_m
            true = change_truth.features[row["feature"]].displacement_m
            if est is not None:
                displacement_errors.append(abs(est - true) * 1000.0)
    objects = []
    observed_objects = {object_of.get(fid) for fid in observable}
    for oid, change in change_truth.objects.items():
        if oid in observed_objects:
            objects.append({"object": oid, "truth": change.label, "predicted": result.objects.get(oid, "none")})
    for oid in change_truth.new_objects:
        if oid in observed_objects:
            feats = [r for r in features if object_of.get(r["feature"]) == oid]
            pred = "new" if any(r["predicted"] == "new" for r in feats) else "none"
            objects.append({"object": oid, "truth": "new", "predicted": pred})
    return {"features": features, "objects": objects, "displacement_error_mm": displacement_errors,
            "n_observable": len(observable), "n_false_new": n_false_new}

