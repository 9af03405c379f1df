"""Aggregation of per-trial evaluation sections into the run summary (DESIGN 8).

Per-trial sections (written by the runner into ``trials/<id>.json``):

* segmentation: the Hoover rates of one image at the default tolerance, plus ``sweep`` (a list of rates at
  each tolerance) and ``min_truth_pixels``;
* classification: ``patches``, a list of ``{truth, label, probabilities: {class: p}, n_pixels}``;
* pose: ``{rotation_error_deg, translation_error_mm, success, constrained, initial: {...}}``;
* change: ``{features: [{truth, predicted}], objects: [{truth, predicted}], displacement_error_mm: [...]}``.

Intervals (DESIGN 11.3). Given a :class:`evaluation.intervals.Resampling` (the scene of each trial and the
scope's bootstrap weights), every headline rate and median gets its 95 % cluster-bootstrap interval beside it,
in the same dict, under the value's key with ``_ci95`` appended: ``[lo, hi]``, or null when fewer than two
scenes contribute (see :mod:`evaluation.intervals`). The figures with an interval:

* segmentation: the five Hoover rates (``correct_detection_rate_ci95`` ... ``noise_rate_ci95``);
* classification: ``accuracy_ci95``, ``brier_ci95``, ``ece_ci95`` and ``per_class.<C>.precision_ci95`` /
  ``recall_ci95``;
* pose: ``success_rate_ci95``, ``success_rate_constrained_ci95``, ``rotation_error_deg.median_ci95``,
  ``translation_error_mm.median_ci95``, ``add_mm.median_ci95``, and in ``initial`` its success rate and
  medians;
* change (features, and ``objects``): ``macro_f1_ci95``, ``per_label.<label>.{precision,recall,f1}_ci95``,
  and ``displacement_error_mm.median_ci95``.

A statistics dict that is null (no finite value) has no interval either. p90, max, the sweep, the size
classes and the missed causes carry none. Without a resampling the sections are as before.
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
from evaluation.intervals import CalibrationGap, MeanOfRatios, Ratio, Resampling
from evaluation.metrics import HOOVER_RATES, MACRO_LABELS, MIN_SCORED_PIXELS, PER_LABEL_ORDER
from scenes.vocabulary import ALTERED, UNCHANGED

CI_SUFFIX = "_ci95"
RELIABILITY_BINS = 10


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


def beside(section: dict[str, Any], intervals: dict[str, list[float] | None]) -> dict[str, Any]:
    """``section`` with each interval inserted right after its value, as ``<key>_ci95``."""
    out: dict[str, Any] = {}
    for k, v in section.items():
        out[k] = v
        if k in intervals:
            out[k + CI_SUFFIX] = intervals[k]
    return out


def aggregate_segmentation(trials: list[dict[str, Any]], resampling: Resampling | None = None) -> dict[str, Any]:
    """Hoover rates averaged over images (DESIGN 7), and the tolerance sweep averaged likewise; an image
    with nothing to count for a rate (null) does not take part in that rate's mean.

    With ``resampling`` (one item per trial) each rate gets its interval: a mean over images is the ratio
    (sum of the images' rates) / (images with that rate), recomputed on every resample of scenes.
    """
    out: dict[str, Any] = {k: _mean([t[k] for t in trials]) for k in HOOVER_RATES}
    if resampling is not None:
        rs = resampling.check(len(trials))
        cis = {}
        for k in HOOVER_RATES:
            v = [t[k] for t in trials]
            cis[k] = rs.ratio([0.0 if x is None else float(x) for x in v], [x is not None for x in v])
        out = beside(out, cis)
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


def aggregate_classification(trials: list[dict[str, Any]], min_pixels: int = MIN_SCORED_PIXELS,
                             resampling: Resampling | None = None) -> dict[str, Any]:
    """Pooled over the patches of ``min_pixels`` pixels or more of every trial; with ``resampling`` (one item
    per trial) the intervals of accuracy, Brier score, ECE and per-class precision and recall."""
    kept = [[p for p in t["patches"] if p["n_pixels"] >= min_pixels] for t in trials]
    patches = [p for ps in kept for p in ps]
    truth = [p["truth"] for p in patches]
    pred = [p["label"] for p in patches]
    probs = np.array([[p["probabilities"].get(c, 0.0) for c in CLASSES] for p in patches]).reshape(-1, len(CLASSES))
    conf = confusion_matrix(truth, pred)
    winner = [p["probabilities"].get(p["label"], 0.0) for p in patches]
    table = reliability_table(truth, pred, winner, RELIABILITY_BINS)
    out = {
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
    if resampling is None:
        return out
    rs = resampling.check(len(trials)).expand([len(ps) for ps in kept])
    return _classification_intervals(out, rs, truth, pred, probs, np.asarray(winner, dtype=np.float64))


def _classification_intervals(out: dict[str, Any], rs: Resampling, truth: list[str], pred: list[str],
                              probs: np.ndarray, winner: np.ndarray) -> dict[str, Any]:
    """Intervals of the classification figures from per-patch terms summed per scene (``rs``: one item per
    patch). Brier: the per-patch score summed over the scene; ECE: per confidence bin as
    :func:`evaluation.classification.reliability_table` bins it, the count, summed confidence and correct
    labels."""
    n = len(truth)
    ti = np.array([CLASSES.index(t) for t in truth], dtype=np.int64)
    pi = np.array([CLASSES.index(p) for p in pred], dtype=np.int64)
    onehot_t = np.zeros((n, len(CLASSES)))
    onehot_t[np.arange(n), ti] = 1.0
    onehot_p = np.zeros((n, len(CLASSES)))
    onehot_p[np.arange(n), pi] = 1.0
    correct = (ti == pi).astype(np.float64)
    ones = np.ones(n)
    brier = np.sum((probs - onehot_t) ** 2, axis=1) if n else np.zeros(0)
    edges = np.linspace(0, 1, RELIABILITY_BINS + 1)
    bins = np.zeros((n, RELIABILITY_BINS))
    bins[np.arange(n), np.clip(np.digitize(winner, edges) - 1, 0, RELIABILITY_BINS - 1)] = 1.0
    ece = CalibrationGap(rs.sums(bins), rs.sums(bins * winner[:, None]), rs.sums(bins * correct[:, None]))
    cis = {"accuracy": rs.ratio(correct, ones), "brier": rs.ratio(brier, ones), "ece": rs.of(ece)}
    tp = onehot_t * correct[:, None]
    per = {}
    for i, c in enumerate(CLASSES):
        per[c] = beside(out["per_class"][c], {"precision": rs.ratio(tp[:, i], onehot_p[:, i]),
                                             "recall": rs.ratio(tp[:, i], onehot_t[:, i])})
    return beside({**out, "per_class": per}, cis)


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


def _median_beside(st: dict[str, float] | None, ci: list[float] | None) -> dict[str, Any] | None:
    """A :func:`stats` dict with the median's interval beside it (a null dict stays null)."""
    return None if st is None else beside(st, {"median": ci})


def aggregate_pose(trials: list[dict[str, Any]], resampling: Resampling | None = None) -> dict[str, Any]:
    """Success rate and error statistics of the final (after ICP) and initial pose estimates; with
    ``resampling`` (one item per trial) the intervals of the success rates and of the error medians."""

    def block(rows: list[dict[str, Any]], rs: Resampling | None) -> dict[str, Any]:
        out = {"success_rate": float(np.mean([bool(r["success"]) for r in rows])) if rows else None,
               "rotation_error_deg": stats([r["rotation_error_deg"] for r in rows]),
               "translation_error_mm": stats([r["translation_error_mm"] for r in rows]),
               "n": len(rows)}
        if rs is None:
            return out
        out = beside(out, {"success_rate": rs.ratio([bool(r["success"]) for r in rows], np.ones(len(rows)))})
        for k in ("rotation_error_deg", "translation_error_mm"):
            out[k] = _median_beside(out[k], rs.median([r[k] for r in rows]))
        return out

    rs = None if resampling is None else resampling.check(len(trials))
    out = block(trials, rs)
    is_constrained = [bool(t.get("constrained", True)) for t in trials]
    constrained = [t for t, c in zip(trials, is_constrained, strict=True) if c]
    out["success_rate_constrained"] = block(constrained, None)["success_rate"]
    if rs is not None:
        out["success_rate_constrained_ci95"] = rs.ratio(
            [bool(t["success"]) and c for t, c in zip(trials, is_constrained, strict=True)], is_constrained)
    out["n_constrained"] = len(constrained)
    has_initial = [bool(t.get("initial")) for t in trials]
    initial = [t["initial"] for t, h in zip(trials, has_initial, strict=True) if h]
    out["initial"] = block(initial, None if rs is None else rs.select(has_initial)) if initial else None
    if any("add_mm" in t for t in trials):
        add = [t.get("add_mm") for t in trials]
        out["add_mm"] = stats(add) if rs is None else _median_beside(stats(add), rs.median(add))
    out.update(_pose_verdicts(trials, rs))
    return out


def _pose_verdicts(trials: list[dict[str, Any]], rs: Resampling | None) -> dict[str, Any]:
    """What the core's ``ok`` verdicts are worth (DESIGN 11.6): how many ok poses are wrong (not a success),
    over all trials and over the ok ones, and the reliability table of the confidence ok poses state (the
    fraction of them that are right per confidence bin: it should be at least the confidence); and the poses
    conditional on one object (not ok, used for change detection), with how many of them are wrong."""
    ok = np.array([bool(t.get("ok")) for t in trials])
    right = np.array([bool(t.get("success")) for t in trials])
    conditional = np.array([bool(t.get("conditional_on")) for t in trials])
    wrong = ok & ~right
    conf = [float(t.get("confidence") or 0.0) for t, o in zip(trials, ok, strict=True) if o]
    out: dict[str, Any] = {
        "n_ok": int(ok.sum()),
        "n_conditional": int(conditional.sum()),
        "conditional_wrong": int((conditional & ~right).sum()),
        "ok_wrong": int(wrong.sum()),
        "ok_wrong_rate": float(wrong.mean()) if len(trials) else None,
        "ok_precision": float(right[ok].mean()) if ok.any() else None,
        "reliability": reliability_table(["right"] * len(conf), ["right" if r else "wrong" for r in right[ok]],
                                         conf, RELIABILITY_BINS),
    }
    if rs is not None:
        out = beside(out, {"ok_wrong_rate": rs.ratio(wrong, np.ones(len(trials))),
                           "ok_precision": rs.ratio(ok & right, ok)})
    return out


def prf(truth: Sequence[str], predicted: Sequence[str], labels: Sequence[str] = PER_LABEL_ORDER) -> dict[str, Any]:
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
    scored = [per[lab]["f1"] for lab in MACRO_LABELS if lab in per and per[lab]["f1"] is not None]
    return {"macro_f1": float(np.mean(scored)) if scored else None, "per_label": per}


def prf_intervals(scores: dict[str, Any], truth: Sequence[str], predicted: Sequence[str], rs: Resampling,
                  labels: Sequence[str] = PER_LABEL_ORDER) -> dict[str, Any]:
    """:func:`prf`'s result with intervals beside macro-F1 and each label's precision, recall and F1.

    Per scene and label the sufficient statistics are tp, n_pred and n_true; F1 is then the ratio
    2 tp / (n_pred + n_true) (equal to 2 P R / (P + R), and 0 when tp = 0), macro-F1 the mean of the F1s
    of moved, missing, new and altered that are defined on the resample.

    Parameters
    ----------
    rs : the resampling of the labelled items (one per element of ``truth``).
    """
    t = np.asarray(truth, dtype=object)
    p = np.asarray(predicted, dtype=object)
    tp = rs.sums(np.stack([(t == lab) & (p == lab) for lab in labels], axis=1).reshape(len(t), len(labels)))
    n_pred = rs.sums(np.stack([p == lab for lab in labels], axis=1).reshape(len(t), len(labels)))
    n_true = rs.sums(np.stack([t == lab for lab in labels], axis=1).reshape(len(t), len(labels)))
    per = {}
    for i, lab in enumerate(labels):
        per[lab] = beside(scores["per_label"][lab], {
            "precision": rs.of(Ratio(tp[:, i], n_pred[:, i])), "recall": rs.of(Ratio(tp[:, i], n_true[:, i])),
            "f1": rs.of(Ratio(2 * tp[:, i], n_pred[:, i] + n_true[:, i]))})
    scored = [labels.index(lab) for lab in MACRO_LABELS if lab in labels]
    macro = MeanOfRatios(2 * tp[:, scored], n_pred[:, scored] + n_true[:, scored])
    return beside({**scores, "per_label": per}, {"macro_f1": rs.of(macro)})


def altered_by_kind(features: list[dict[str, Any]], rs: Resampling | None = None) -> dict[str, Any] | None:
    """Precision, recall, F1 and support of ``altered`` among the features of each kind of object (the rows'
    ``kind``: ``cabinet``, ``tank``, ``sphere_tank``, ``wall``, ``pipe_run``, ...), for the kinds with an altered
    feature in the truth or the prediction; with ``rs`` (one item per feature row) their intervals. None when no
    row says its kind (records written before kinds were recorded)."""
    kinds = sorted({f["kind"] for f in features if "kind" in f and ALTERED in (f["truth"], f["predicted"])})
    if not any("kind" in f for f in features):
        return None
    k = np.array([f.get("kind") for f in features], dtype=object)
    t = np.array([f["truth"] == ALTERED for f in features], dtype=bool)
    p = np.array([f["predicted"] == ALTERED for f in features], dtype=bool)
    out: dict[str, Any] = {}
    for kind in kinds:
        m = k == kind
        tp, n_pred, n_true = int(np.sum(m & t & p)), int(np.sum(m & p)), int(np.sum(m & t))
        prec = tp / n_pred if n_pred else None
        rec = tp / n_true if n_true else None
        row: dict[str, Any] = {"precision": prec, "recall": rec, "f1": 2 * tp / (n_pred + n_true), "support": n_true}
        if rs is not None:
            tps, preds, trues = rs.sums(np.stack([m & t & p, m & p, m & t], axis=1).astype(np.float64)).T
            row = beside(row, {"precision": rs.of(Ratio(tps, preds)), "recall": rs.of(Ratio(tps, trues)),
                               "f1": rs.of(Ratio(2 * tps, preds + trues))})
        out[kind] = row
    return out


def false_alarms(features: list[dict[str, Any]], rs: Resampling | None = None) -> dict[str, Any]:
    """``false_alarm_rate``: the share of the observable features that did not change (truth ``unchanged``)
    labelled a change (moved, missing, new or altered); ``n_unchanged`` of them. With ``rs`` (one item per
    feature row) its interval."""
    unchanged = np.array([f["truth"] == UNCHANGED for f in features], dtype=bool)
    alarm = unchanged & np.array([f["predicted"] in MACRO_LABELS for f in features], dtype=bool)
    n = int(unchanged.sum())
    out: dict[str, Any] = {"false_alarm_rate": float(alarm.sum()) / n if n else None}
    if rs is not None:
        out = beside(out, {"false_alarm_rate": rs.ratio(alarm.astype(np.float64), unchanged.astype(np.float64))})
    out["n_unchanged"] = n
    return out


def aggregate_change(trials: list[dict[str, Any]], resampling: Resampling | None = None) -> dict[str, Any]:
    """Per-label and macro-F1 scores over the features (and objects) of every trial, and the displacement
    error of moved features; with ``resampling`` (one item per trial) their intervals."""
    rs = None if resampling is None else resampling.check(len(trials))
    feats = [f for t in trials for f in t["features"]]
    ft, fp = [f["truth"] for f in feats], [f["predicted"] for f in feats]
    out = prf(ft, fp)
    if rs is not None:
        out = prf_intervals(out, ft, fp, rs.expand([len(t["features"]) for t in trials]))
    frs = None if rs is None else rs.expand([len(t["features"]) for t in trials])
    out["altered_by_kind"] = altered_by_kind(feats, frs)
    out.update(false_alarms(feats, frs))
    objs = [o for t in trials for o in t.get("objects", [])]
    ot, op = [o["truth"] for o in objs], [o["predicted"] for o in objs]
    out["objects"] = prf(ot, op) if objs else None
    if objs and rs is not None:
        out["objects"] = prf_intervals(out["objects"], ot, op, rs.expand([len(t.get("objects", [])) for t in trials]))
    disp = [e for t in trials for e in t.get("displacement_error_mm", [])]
    out["displacement_error_mm"] = stats(disp)
    if rs is not None:
        drs = rs.expand([len(t.get("displacement_error_mm", [])) for t in trials])
        out["displacement_error_mm"] = _median_beside(out["displacement_error_mm"], drs.median(disp))
    return out
