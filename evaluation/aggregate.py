"""Aggregation of per-trial evaluation sections into the run summary (DESIGN 8).

Per-trial sections (written by the runner into ``trials/<id>.json``):

* segmentation: the Hoover rates of one image at the default tolerance, plus ``sweep`` (a list of rates at
  each tolerance) and ``min_truth_pixels``;
* classification: ``patches``, a list of ``{truth, label, probabilities: {class: p}, n_pixels}``;
* pose: ``{rotation_error_deg, translation_error_mm, success, constrained, initial: {...}}``;
* change: ``{features: [{truth, predicted}], objects: [{truth, predicted}], displacement_error_mm: [...]}``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from evaluation.classification import (
    CLASSES,
    accuracy,
    brier_score,
    confusion_matrix,
    expected_calibration_error,
    per_class,
    reliability_table,
)

HOOVER_RATES = ("correct_detection_rate", "over_rate", "under_rate", "missed_rate", "noise_rate")
CHANGE_LABELS = ("moved", "missing", "new", "altered", "unchanged")
MIN_PATCH_PIXELS = 200


def stats(values: Sequence[float]) -> dict[str, float] | None:
    """Median, p90, max and mean of finite values (None when there are none)."""
    v = np.asarray([x for x in values if x is not None], dtype=np.float64)
    v = v[np.isfinite(v)]
    if not len(v):
        return None
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max()),
            "mean": float(v.mean())}


def _mean(values: list[float | None]) -> float | None:
    v = [x for x in values if x is not None]
    return float(np.mean(v)) if v else None


def aggregate_segmentation(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Hoover rates averaged over images (DESIGN 7), and the tolerance sweep averaged likewise; an image
    with nothing to count for a rate (null) does not take part in that rate's mean."""
    out: dict[str, Any] = {k: _mean([t[k] for t in trials]) for k in HOOVER_RATES}
    out["tolerance"] = trials[0]["tolerance"]
    out["min_truth_pixels"] = trials[0].get("min_truth_pixels", 0)
    out["n_images"] = len(trials)
    out["n_truth_regions"] = int(sum(t.get("n_truth", 0) for t in trials))
    causes = [t["missed_causes"] for t in trials if t.get("missed_causes")]
    if causes:
        out["missed_causes"] = {k: _mean([c.get(k) for c in causes]) for k in causes[0]}
    by_size = [t["by_size"] for t in trials if t.get("by_size")]
    if by_size:
        out["by_size"] = [_pooled_size_class([b[i] for b in by_size]) for i in range(len(by_size[0]))]
    sweeps = [t["sweep"] for t in trials if t.get("sweep")]
    if sweeps:
        out["sweep"] = [{"tolerance": row["tolerance"],
                         **{k: _mean([s[i][k] for s in sweeps]) for k in HOOVER_RATES}}
                        for i, row in enumerate(sweeps[0])]
    return out


def _pooled_size_class(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """One size class of ``by_size`` pooled over images: its regions counted together (few images hold one of
    a given size, so a mean over images would rest on a handful), and the rates of those counts."""
    n = sum(r["n_truth"] for r in rows)
    out: dict[str, Any] = {"min_pixels": rows[0]["min_pixels"], "max_pixels": rows[0]["max_pixels"], "n_truth": n}
    for c, rate in (("correct", "correct_detection_rate"), ("over", "over_rate"), ("under", "under_rate"),
                    ("missed", "missed_rate")):
        out[rate] = sum(r[f"n_{c}"] for r in rows) / n if n else None
    return out


def aggregate_classification(trials: list[dict[str, Any]], min_pixels: int = MIN_PATCH_PIXELS) -> dict[str, Any]:
    """Pooled over the patches of ``min_pixels`` pixels or more of every trial."""
    patches = [p for t in trials for p in t["patches"] if p["n_pixels"] >= min_pixels]
    truth = [p["truth"] for p in patches]
    pred = [p["label"] for p in patches]
    probs = np.array([[p["probabilities"].get(c, 0.0) for c in CLASSES] for p in patches]).reshape(-1, len(CLASSES))
    conf = confusion_matrix(truth, pred)
    winner = [p["probabilities"].get(p["label"], 0.0) for p in patches]
    table = reliability_table(truth, pred, winner)
    return {
        "accuracy": accuracy(truth, pred),
        "n_patches": len(patches),
        "min_patch_pixels": min_pixels,
        "per_class": per_class(conf),
        "brier": brier_score(truth, probs),
        "confusion": {"classes": list(CLASSES), "matrix": conf.tolist()},
        "reliability": table,
        "ece": expected_calibration_error(table),
        "n_patches_all": int(sum(len(t["patches"]) for t in trials)),
        "radius": {c: radius_errors(patches, c) for c in ("CYL", "SPH")},
    }


def radius_errors(patches: list[dict[str, Any]], label: str) -> dict[str, Any] | None:
    """Radius of the patches labelled ``label`` whose truth has that class too (issue #14): the median
    absolute and signed (bias) relative errors of the fitted radius, and the fraction within 2 of its
    predicted sigmas of the truth. None without such patches."""
    rows = [p["radius"] for p in patches if p["label"] == label and p["truth"] == label and p.get("radius")]
    if not rows:
        return None
    est = np.array([r["estimate_m"] for r in rows])
    true = np.array([r["truth_m"] for r in rows])
    sig = np.array([r["sigma_m"] for r in rows])
    rel = est / true - 1.0
    with np.errstate(invalid="ignore"):
        within = np.abs(est - true) <= 2.0 * sig
    return {"n": len(rows), "median_abs_rel_error": float(np.median(np.abs(rel))),
            "median_rel_error": float(np.median(rel)), "within_2_sigma": float(np.mean(within))}


def aggregate_pose(trials: list[dict[str, Any]]) -> dict[str, Any]:
    """Success rate and error statistics of the final (after ICP) and initial pose estimates."""

    def block(rows: list[dict[str, Any]]) -> dict[str, Any]:
        return {"success_rate": float(np.mean([bool(r["success"]) for r in rows])) if rows else None,
                "rotation_error_deg": stats([r["rotation_error_deg"] for r in rows]),
                "translation_error_mm": stats([r["translation_error_mm"] for r in rows]),
                "n": len(rows)}

    out = block(trials)
    constrained = [t for t in trials if t.get("constrained", True)]
    out["success_rate_constrained"] = block(constrained)["success_rate"]
    out["n_constrained"] = len(constrained)
    initial = [t["initial"] for t in trials if t.get("initial")]
    out["initial"] = block(initial) if initial else None
    if any("add_mm" in t for t in trials):
        out["add_mm"] = stats([t.get("add_mm") for t in trials])
    return out


def prf(truth: Sequence[str], predicted: Sequence[str], labels: Sequence[str] = CHANGE_LABELS) -> dict[str, Any]:
    """Per-label precision, recall, F1 and support; macro-F1 over moved, missing, new, altered (DESIGN 10.7)."""
    t = np.asarray(truth, dtype=object)
    p = np.asarray(predicted, dtype=object)
    per: dict[str, dict[str, float | int | None]] = {}
    for lab in labels:
        tp = int(np.sum((t == lab) & (p == lab)))
        n_pred = int(np.sum(p == lab))
        n_true = int(np.sum(t == lab))
        prec = tp / n_pred if n_pred else None
        rec = tp / n_true if n_true else None
        f1 = 2 * prec * rec / (prec + rec) if prec and rec else (0.0 if (n_pred or n_true) else None)
        per[lab] = {"precision": prec, "recall": rec, "f1": f1, "support": n_true}
    scored = [per[lab]["f1"] for lab in ("moved", "missing", "new", "altered") if per[lab]["f1"] is not None]
    return {"macro_f1": float(np.mean(scored)) if scored else None, "per_label": per}


def aggregate_change(trials: list[dict[str, Any]]) -> dict[str, Any]:
    feats = [f for t in trials for f in t["features"]]
    out = prf([f["truth"] for f in feats], [f["predicted"] for f in feats])
    objs = [o for t in trials for o in t.get("objects", [])]
    out["objects"] = prf([o["truth"] for o in objs], [o["predicted"] for o in objs]) if objs else None
    out["displacement_error_mm"] = stats([e for t in trials for e in t.get("displacement_error_mm", [])])
    return out
