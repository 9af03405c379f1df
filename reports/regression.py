"""What moved between a base run and a candidate run, for the report's regression section and for
``harness compare``'s text.

The verdicts (DESIGN 10.9, 11.3) are :mod:`evaluation.verdicts`'s, one implementation: ``harness report``
passes the :class:`~evaluation.verdicts.Comparison` that ``harness compare`` prints, and both show its figures
through :func:`figure_cells` and :func:`move_cells`. Without a comparison the report shows the plain deltas of
the headline metrics (:func:`headline_deltas`), reusable by any caller that has two ``summary.json`` dicts.
The metrics, their directions, units and number formats are :mod:`evaluation.metrics`'s declarations.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from evaluation import metrics
from evaluation.metrics import Metric
from evaluation.verdicts import ALL, FAILING, Comparison, FigureVerdict, TrialMove


class Missing:
    """Why a value is absent: its section is null (``no figure``) or the key is not there (``n/a``)."""

    def __init__(self, why: str):
        self.why = why

    def __repr__(self) -> str:
        return f"Missing({self.why!r})"


NOT_BUILT = Missing("no figure")
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
                    shown: Sequence[Metric] | None = None) -> list[dict[str, Any]]:
    """The headline metrics (``shown``, default: :func:`evaluation.metrics.headline`) of ``method`` in two
    summaries, with candidate - base and whether it got better.

    Returns
    -------
    list of ``{metric, key, label, base, candidate, delta, direction, better}`` (``metric``: the figure's path in
    the summary, ``key``: its declaration's): ``base``/``candidate`` are floats
    or None (null section or absent key), ``delta`` None unless both exist, ``better`` True/False/None
    (None: unchanged or not comparable).
    """
    def sections(summary: Mapping[str, Any]) -> Mapping[str, Any] | None:
        return summary if method == "core" else (summary.get("baselines") or {}).get(method)

    rows = []
    for m in metrics.headline() if shown is None else shown:
        b, c = lookup(sections(base), m.path), lookup(sections(candidate), m.path)
        b = None if isinstance(b, Missing) else b
        c = None if isinstance(c, Missing) else c
        delta = None if b is None or c is None else c - b
        better = None if not delta else (delta > 0) == (m.direction == "higher")
        rows.append({"metric": m.key if method == "core" else f"baselines.{method}.{m.key}", "key": m.key,
                     "label": m.title, "base": b, "candidate": c, "delta": delta, "direction": m.direction,
                     "better": better})
    return rows


# -- verdict rows, shared by ``harness compare`` and the report ----------------------------------------------------
HEADLINE_HEADER = ("method", "metric", "scope", "base", "candidate", "delta", "95 % interval of delta", "verdict")
MOVES_HEADER = ("trial", "scene", "moved", "figures (base -> candidate)")


def _num(x: float | None, digits: int) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def figure_cells(f: FigureVerdict) -> tuple[str, ...]:
    """One verdict row as text (:data:`HEADLINE_HEADER`); a counted failure is in capitals, and a verdict
    beyond tolerance that had no interval says so."""
    d = f.metric.digits
    ci = "" if f.interval is None else f"[{f.interval[0]:+.{d}f}, {f.interval[1]:+.{d}f}]"
    verdict = f.verdict.upper() if f.verdict in FAILING and f.counted else f.verdict
    if f.verdict in ("regression", "improved") and f.interval is None and f.metric.rule in ("rate", "error"):
        verdict += " (tolerance alone)"
    delta = "" if f.delta is None else f"{f.delta:+.{d}f}"
    return (f.method, f.metric.display, f.scope, _num(f.base, d), _num(f.candidate, d), delta, ci, verdict)


def shown_figures(comparison: Comparison, counted: bool) -> list[FigureVerdict]:
    """The rows of the headline table (``counted``: the counted methods, every scope) or of the other methods'
    table (their pooled figures, and a group's only when its verdict is not ``pass``; no ``n/a`` rows)."""
    out = []
    for f in comparison.figures:
        if f.counted != counted:
            continue
        if not counted and (f.verdict == "n/a" or (f.scope != ALL and f.verdict == "pass")):
            continue
        out.append(f)
    return out


def move_cells(m: TrialMove) -> tuple[str, str, str, str]:
    """One row of "what changed most" (:data:`MOVES_HEADER`)."""
    figures = m.status or "; ".join(f"{x.label} {_num(x.base, x.digits)} -> {_num(x.candidate, x.digits)}"
                                    for x in m.moves)
    return m.trial_id, m.scene, f"{m.score:.3f}", figures
