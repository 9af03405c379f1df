"""Classification metrics over patches: accuracy, per-class precision and recall, confusion matrix,
multi-class Brier score, a reliability table (DESIGN 7 and 10.8) and how sure each of the classifier's decision
paths is.

Classes are the paper's PLAN, CYL, SPH, CONE, OTH. Each patch takes the truth class of the surface it
mostly covers.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from scenes.vocabulary import CLASSES

__all__ = ["CLASSES", "confusion_matrix", "accuracy", "per_class", "brier_score", "reliability_table",
           "expected_calibration_error", "optimal_floor",
           "decision_path_table"]


def confusion_matrix(truth: Sequence[str], predicted: Sequence[str], classes: Sequence[str] = CLASSES) -> np.ndarray:
    """Counts (C, C): rows are truth classes, columns predicted classes."""
    index = {c: i for i, c in enumerate(classes)}
    m = np.zeros((len(classes), len(classes)), dtype=np.int64)
    for t, p in zip(truth, predicted, strict=True):
        m[index[t], index[p]] += 1
    return m


def accuracy(truth: Sequence[str], predicted: Sequence[str]) -> float | None:
    """Fraction of patches labelled with their truth class (None for no patches)."""
    if not len(truth):
        return None
    return float(np.mean([t == p for t, p in zip(truth, predicted, strict=True)]))


def per_class(confusion: np.ndarray, classes: Sequence[str] = CLASSES) -> dict[str, dict[str, float | int | None]]:
    """Precision, recall and support (truth count) per class from a confusion matrix (None when undefined)."""
    out: dict[str, dict[str, float | int | None]] = {}
    for i, c in enumerate(classes):
        tp = int(confusion[i, i])
        predicted = int(confusion[:, i].sum())
        support = int(confusion[i].sum())
        out[c] = {"precision": tp / predicted if predicted else None, "recall": tp / support if support else None,
                  "support": support}
    return out


def brier_score(truth: Sequence[str], probabilities: np.ndarray, classes: Sequence[str] = CLASSES) -> float | None:
    """Multi-class Brier score: mean over patches of sum_c (p_c - [c = truth])^2, in [0, 2].

    Parameters
    ----------
    probabilities : ndarray of shape (N, C), rows summing to 1, columns in ``classes`` order.
    """
    if not len(truth):
        return None
    p = np.asarray(probabilities, dtype=np.float64)
    return float(np.mean(np.sum((p - _one_hot(truth, classes)) ** 2, axis=1)))


def _one_hot(truth: Sequence[str], classes: Sequence[str]) -> np.ndarray:
    """(N, C) rows with 1 in each truth's column, ``classes`` order."""
    y = np.zeros((len(truth), len(classes)))
    y[np.arange(len(truth)), [classes.index(t) for t in truth]] = 1.0
    return y


def reliability_table(truth: Sequence[str], predicted: Sequence[str], confidence: Sequence[float],
                      bins: int = 10) -> list[dict[str, float | int]]:
    """Calibration of the winning class's probability: per confidence bin, the mean confidence, the
    accuracy and the count (empty bins omitted)."""
    conf = np.asarray(confidence, dtype=np.float64)
    correct = np.array([t == p for t, p in zip(truth, predicted, strict=True)], dtype=float)
    edges = np.linspace(0, 1, bins + 1)
    idx = np.clip(np.digitize(conf, edges) - 1, 0, bins - 1)
    rows = []
    for b in range(bins):
        sel = idx == b
        if sel.any():
            rows.append({"low": float(edges[b]), "high": float(edges[b + 1]), "confidence": float(conf[sel].mean()),
                         "accuracy": float(correct[sel].mean()), "count": int(sel.sum())})
    return rows


def expected_calibration_error(table: list[dict[str, float | int]]) -> float | None:
    """Count-weighted mean |confidence - accuracy| over the reliability table's bins."""
    n = sum(r["count"] for r in table)
    if not n:
        return None
    return float(sum(r["count"] * abs(r["confidence"] - r["accuracy"]) for r in table) / n)


def optimal_floor(truth: Sequence[str], raw_probabilities: np.ndarray,
                  classes: Sequence[str] = CLASSES) -> float | None:
    """The floor ``f`` in [0, 1] minimising the Brier score of ``(1 - f) q + f / C`` (``q``: the rows of
    ``raw_probabilities``, mixed with the uniform distribution over the ``C`` classes).

    The Brier score is quadratic in ``f``: with ``u`` the uniform row and ``y`` the one-hot truth, its minimum is
    at ``f* = sum (q - y).(q - u) / sum |q - u|²``, clipped to [0, 1]. None without patches or when every row is
    already uniform.

    Parameters
    ----------
    raw_probabilities : ndarray of shape (N, C), rows summing to 1, columns in ``classes`` order.
    """
    if not len(truth):
        return None
    q = np.asarray(raw_probabilities, dtype=np.float64)
    y = _one_hot(truth, classes)
    d = q - 1.0 / q.shape[1]
    den = float(np.sum(d * d))
    if den <= 0:
        return None
    return float(np.clip(np.sum((q - y) * d) / den, 0.0, 1.0))


def _raw(row: Mapping[str, Any]) -> np.ndarray:
    """A patch record's probabilities before the floor its classifier mixed them with (``row["floor"]``)."""
    p = np.array([row["probabilities"][c] for c in CLASSES], dtype=np.float64)
    f = row.get("floor", 0.0)
    return (p - f / len(CLASSES)) / (1.0 - f)


def decision_path_table(rows: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """How sure each decision path of the classifier is: per path of the patch records ``rows`` (their ``path``;
    rows without one, e.g. patches not better than noise: ``"none"``) and ``"all"``, ``{"path", "count",
    "accuracy", "confidence", "brier", "floor", "optimal_floor"}``: the mean probability of the label, the floor the
    run applied (the path's first row's) and the one that minimises the path's Brier score on the probabilities
    before it (:func:`optimal_floor`)."""
    groups: dict[str, list[Mapping[str, Any]]] = {}
    for r in rows:
        groups.setdefault(r.get("path", "none"), []).append(r)
    out = []
    for path, rs in sorted(groups.items()) + [("all", list(rows))]:
        if not rs:
            continue
        truth = [r["truth"] for r in rs]
        probs = np.array([[r["probabilities"][c] for c in CLASSES] for r in rs])
        whole = path == "all"
        out.append({"path": path, "count": len(rs),
                    "accuracy": float(np.mean([r["label"] == r["truth"] for r in rs])),
                    "confidence": float(np.mean([r["probabilities"][r["label"]] for r in rs])),
                    "brier": brier_score(truth, probs),
                    "floor": None if whole else rs[0].get("floor"),
                    "optimal_floor": None if whole else optimal_floor(truth, np.array([_raw(r) for r in rs]))})
    return out
