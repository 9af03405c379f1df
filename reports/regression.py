"""What moved between a base run and a candidate run, for the report's regression section.

The verdicts (pass/fail per metric, DESIGN 10.9) are ``harness compare``'s; ``harness report`` passes its rows
in. This module provides the headline metrics with their direction and the plain deltas between two summaries,
reusable by any caller that has two ``summary.json`` dicts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Metric:
    """A headline metric: its label, where it lives in a method's sections, direction and number format."""

    label: str
    path: tuple[str, ...]
    direction: str  # "higher" or "lower" is better
    digits: int = 3
    unit: str = ""


HEADLINE: tuple[Metric, ...] = (
    Metric("segmentation: correct detection rate", ("segmentation", "correct_detection_rate"), "higher"),
    Metric("segmentation: missed rate", ("segmentation", "missed_rate"), "lower"),
    Metric("classification: accuracy", ("classification", "accuracy"), "higher"),
    Metric("classification: Brier score", ("classification", "brier"), "lower"),
    Metric("classification: expected calibration error", ("classification", "ece"), "lower"),
    Metric("pose: success rate", ("pose", "success_rate"), "higher"),
    Metric("pose: rotation error, median", ("pose", "rotation_error_deg", "median"), "lower", 3, "deg"),
    Metric("pose: translation error, median", ("pose", "translation_error_mm", "median"), "lower", 1, "mm"),
    Metric("change: macro-F1", ("change", "macro_f1"), "higher"),
    Metric("time per trial, median", ("timing_s", "total", "median"), "lower", 2, "s"),
)


class Missing:
    """Why a value is absent: its section is null (``not built yet``) or the key is not there (``n/a``)."""

    def __init__(self, why: str):
        self.why = why

    def __repr__(self) -> str:
        return f"Missing({self.why!r})"


NOT_BUILT = Missing("not built yet")
NOT_AVAILABLE = Missing("n/a")


def lookup(sections: Mapping[str, Any] | None, path: tuple[str, ...]) -> float | Missing:
    """The value at ``path`` of a method's sections; :data:`NOT_BUILT` when the stage's section is null."""
    if sections is None:
        return NOT_AVAILABLE
    node: Any = sections
    for i, key in enumerate(path):
        if not isinstance(node, Mapping) or key not in node:
            return NOT_AVAILABLE
        node = node[key]
        if node is None:
            return NOT_BUILT if i == 0 else NOT_AVAILABLE
    if isinstance(node, bool) or not isinstance(node, int | float):
        return NOT_AVAILABLE
    return float(node)


def interval_path(path: tuple[str, ...]) -> tuple[str, ...]:
    """Where the 95 % interval of the figure at ``path`` lives: beside it, its key with ``_ci95`` appended."""
    return (*path[:-1], path[-1] + "_ci95")


def lookup_interval(sections: Mapping[str, Any] | None, path: tuple[str, ...]) -> tuple[float, float] | None:
    """The interval ``(lo, hi)`` beside the figure at ``path`` (DESIGN 11.3); None when there is none (a null
    interval: fewer than two scenes; or a summary written before intervals existed)."""
    node: Any = sections
    for key in interval_path(path):
        if not isinstance(node, Mapping):
            return None
        node = node.get(key)
    if not isinstance(node, list | tuple) or len(node) != 2:
        return None
    if not all(isinstance(x, int | float) and not isinstance(x, bool) and x == x for x in node):
        return None
    return float(node[0]), float(node[1])


def headline_deltas(base: Mapping[str, Any], candidate: Mapping[str, Any], method: str = "core",
                    metrics: tuple[Metric, ...] = HEADLINE) -> list[dict[str, Any]]:
    """The headline metrics of ``method`` in two summaries, with candidate - base and whether it got better.

    Returns
    -------
    list of ``{metric, label, base, candidate, delta, direction, better}``: ``base``/``candidate`` are floats
    or None (null section or absent key), ``delta`` None unless both exist, ``better`` True/False/None
    (None: unchanged or not comparable).
    """
    def sections(summary: Mapping[str, Any]) -> Mapping[str, Any] | None:
        return summary if method == "core" else (summary.get("baselines") or {}).get(method)

    rows = []
    for m in metrics:
        b, c = lookup(sections(base), m.path), lookup(sections(candidate), m.path)
        b = None if isinstance(b, Missing) else b
        c = None if isinstance(c, Missing) else c
        delta = None if b is None or c is None else c - b
        better = None if not delta else (delta > 0) == (m.direction == "higher")
        rows.append({"metric": ".".join(m.path) if method == "core" else f"baselines.{method}." + ".".join(m.path),
                     "label": m.label, "base": b, "candidate": c, "delta": delta, "direction": m.direction,
                     "better": better})
    return rows
