"""Every metric the harness knows, declared once (DESIGN 10.9, 11.8), and the scoring vocabulary.

A metric is one :class:`Metric` line of :data:`METRICS`: where it lives in ``summary.json``, its title, which
way is better, its tolerance rule, its unit and number format, and whether it is a headline figure. Everything
that judges or shows figures reads these declarations and nothing else:

* :mod:`evaluation.verdicts` (``harness compare`` and the report's regression section) judges the headline
  metrics (``headline=True``): those of each method pooled and per group, and the run's own (failed trials;
  the time per trial with ``--check-time``);
* ``harness compare --all`` (:func:`harness.compare.compare`) gives every numeric leaf the direction and
  rule of the declaration that covers it, and marks a leaf no declaration covers ``undeclared``;
* the report (:mod:`reports.render`, :mod:`reports.regression`) shows the headline metrics in its headline,
  oracle and regression tables and the ``compact`` ones in its per-group and per-method tables;
  :mod:`reports.results` writes the ``compact`` ones (times excepted, DESIGN 11.7) into the README's table;
* :mod:`evaluation.attribution` explains the gap of each headline metric of a method to its ideal value.

Adding a metric: compute it in :mod:`evaluation.aggregate` (it then appears in ``summary.json``), declare it
here; a headline metric also wants its per-trial sufficient statistics in :mod:`evaluation.verdicts`
(``RATIO_TERMS``, ``MEDIAN_VALUES``) for its paired interval (without them the tolerance alone decides).
A numeric leaf of a summary that is not a metric (a count, a setting, a diagnostic) is declared
:class:`Informative`; a test checks that every leaf of a summary is one or the other.

Keys are dotted paths inside a method's sections (``pose.rotation_error_deg.median``), the same under every
scope: the top level (the core, pooled), ``groups.<group>.``, ``baselines.<method>.`` and ``oracles.<oracle>.``
(:func:`split_scope`). In a key, ``*`` stands for any one key (``classification.per_class.*.precision``) and a
final ``**`` for a whole subtree (``provenance.**``). The most specific declaration (fewest wildcards) wins.

Tolerance rules (their values are in ``harness/tolerances/*.yaml``, :class:`evaluation.verdicts.Tolerances`):

* ``rate``: an absolute change, ``rate_drop`` (a fraction in [0, 1]);
* ``error``: a relative growth, ``error_growth``, plus an absolute ``error_floor``;
* ``count``: an absolute increase, ``n_failed_increase``;
* ``time``: a relative growth, ``time_growth``, plus ``time_floor_s``; judged only with ``--check-time``.

A ``per_metric`` allowance of a tolerances file is keyed by a declared metric (optionally after a scope).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from scenes.vocabulary import ALTERED, MISSING, MOVED, NEW, UNCHANGED

__all__ = ["Metric", "Informative", "METRICS", "INFORMATIVE", "DIRECTIONS", "RULES", "MIN_SCORED_PIXELS",
           "MACRO_LABELS", "PER_LABEL_ORDER", "HOOVER_RATES", "TIMING_STAGES", "SECTIONS", "metric", "headline",
           "judged", "run_checks", "compact", "declaration", "covers_node", "split_scope", "is_interval_key", "leaves",
           "undeclared", "check_allowance_key"]

# -- the scoring vocabulary --------------------------------------------------------------------------------
#: The scoring floor (DESIGN 10.6): truth regions, patches and features of fewer pixels are not scored, a
#: surface of fewer visible pixels does not constrain the pose.
MIN_SCORED_PIXELS = 200
#: The change labels macro-F1 averages (DESIGN 10.7), in the results contract's order (DESIGN 8).
MACRO_LABELS: tuple[str, ...] = (MOVED, MISSING, NEW, ALTERED)
#: The order of ``change.per_label`` in ``summary.json``: the changes, then ``unchanged`` beside them.
PER_LABEL_ORDER: tuple[str, ...] = (*MACRO_LABELS, UNCHANGED)
#: The Hoover et al. (1996) rates of a segmentation (DESIGN 7), in table order.
HOOVER_RATES: tuple[str, ...] = ("correct_detection_rate", "over_rate", "under_rate", "missed_rate", "noise_rate")
#: The stages of ``timing_s`` (``sensor`` and ``total`` per trial, the others per method).
TIMING_STAGES: tuple[str, ...] = ("sensor", "segmentation", "classification", "matching", "icp", "change", "total")
#: The stage sections of a method in ``summary.json`` (null when the stage did not run).
SECTIONS: tuple[str, ...] = ("segmentation", "classification", "pose", "change")

DIRECTIONS = ("higher", "lower")
RULES: dict[str, str] = {
    "rate": "absolute change beyond rate_drop",
    "error": "relative growth beyond error_growth, plus error_floor",
    "count": "increase beyond n_failed_increase",
    "time": "relative growth beyond time_growth, plus time_floor_s (only with --check-time)",
}
_SCOPES = ("groups",)
_METHOD_TREES = ("baselines", "oracles")


# -- declarations -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Metric:
    """One figure of ``summary.json`` that has a better direction.

    Attributes
    ----------
    key : its dotted path in a method's sections (``classification.accuracy``; ``n_failed`` at a scope's top);
        ``*`` matches any one key.
    title : what tables call it (``classification accuracy``).
    direction : ``higher`` or ``lower`` is better.
    rule : the tolerance rule, one of :data:`RULES`.
    unit : shown after the value (``deg``, ``mm``, ``s``; empty for fractions).
    digits : decimals shown.
    headline : the verdict of ``harness compare`` is on it, and the report's headline table shows it.
    compact : its column title in the compact tables (the report's per-group and per-method tables, the README's
        results table); empty: not in them.
    per_method : a figure of each method, judged pooled and per group; False: of the run (judged once, pooled,
        for the core: the failed trials, the time per trial).
    """

    key: str
    title: str
    direction: str
    rule: str
    unit: str = ""
    digits: int = 3
    headline: bool = False
    compact: str = ""
    per_method: bool = True

    def __post_init__(self) -> None:
        if self.direction not in DIRECTIONS:
            raise ValueError(f"metric {self.key}: direction must be one of {', '.join(DIRECTIONS)}, got "
                             f"{self.direction!r}")
        if self.rule not in RULES:
            raise ValueError(f"metric {self.key}: rule must be one of {', '.join(RULES)}, got {self.rule!r}")
        if "**" in self.key:
            raise ValueError(f"metric {self.key}: a metric is a leaf ('*' for one key), not a subtree ('**')")

    @property
    def path(self) -> tuple[str, ...]:
        return tuple(self.key.split("."))

    @property
    def section(self) -> str:
        return self.path[0]

    @property
    def display(self) -> str:
        """The title with its unit (``rotation error, median deg``), as the verdict tables show it."""
        return f"{self.title} {self.unit}" if self.unit else self.title

    @property
    def ideal(self) -> float | None:
        """The best value it can take: 1 for a rate that should be high, 0 for other rates, errors and counts;
        None for times."""
        if self.rule == "time":
            return None
        return 1.0 if self.rule == "rate" and self.direction == "higher" else 0.0

    def matches(self, path: Sequence[str]) -> bool:
        return _match(self.path, tuple(path))


@dataclass(frozen=True)
class Informative:
    """Numeric leaves of ``summary.json`` that are not metrics: counts, settings, diagnostics without a better
    direction (``key`` as for :class:`Metric`; a final ``**`` covers a subtree), and why."""

    key: str
    why: str

    @property
    def path(self) -> tuple[str, ...]:
        return tuple(self.key.split("."))

    @property
    def tree(self) -> bool:
        """Whether it covers a whole subtree (``harness compare`` lists none of its leaves)."""
        return self.path[-1] == "**"

    def matches(self, path: Sequence[str]) -> bool:
        return _match(self.path, tuple(path))


def _stats(key: str, title: str, unit: str, digits: int) -> tuple[Metric, ...]:
    """The median, p90, max and mean of an error (an ``evaluation.aggregate.stats`` dict)."""
    return tuple(Metric(f"{key}.{s}", f"{title}, {s}", "lower", "error", unit, digits) for s in
                 ("median", "p90", "max", "mean"))


def _prf(prefix: str, what: str) -> tuple[Metric, ...]:
    return (Metric(f"{prefix}.*.precision", f"{what} precision", "higher", "rate"),
            Metric(f"{prefix}.*.recall", f"{what} recall", "higher", "rate"))


#: Every metric, in the order of the tables (the headline ones in the order the verdict lists them).
METRICS: tuple[Metric, ...] = (
    # segmentation (Hoover et al. 1996 at T = 0.8, DESIGN 7)
    Metric("segmentation.correct_detection_rate", "segmentation correct detection", "higher", "rate",
           headline=True, compact="correct detection (T=0.8)"),
    Metric("segmentation.over_rate", "segmentation over-segmentation rate", "lower", "rate"),
    Metric("segmentation.under_rate", "segmentation under-segmentation rate", "lower", "rate"),
    Metric("segmentation.missed_rate", "segmentation missed rate", "lower", "rate"),
    Metric("segmentation.noise_rate", "segmentation noise rate", "lower", "rate"),
    # classification (DESIGN 7, 10.8)
    Metric("classification.accuracy", "classification accuracy", "higher", "rate", headline=True,
           compact="class. accuracy"),
    Metric("classification.brier", "classification Brier score", "lower", "error", headline=True, compact="Brier"),
    Metric("classification.ece", "classification expected calibration error", "lower", "error"),
    *_prf("classification.per_class", "per-class"),
    # pose (bop_toolkit definitions, DESIGN 7 and 10.6)
    Metric("pose.success_rate", "pose success", "higher", "rate", headline=True),
    Metric("pose.success_rate_constrained", "pose success, constrained", "higher", "rate", headline=True,
           compact="constrained pose success"),
    Metric("pose.rotation_error_deg.median", "rotation error, median", "lower", "error", "deg", 3, headline=True),
    Metric("pose.translation_error_mm.median", "translation error, median", "lower", "error", "mm", 1,
           headline=True),
    *_stats("pose.rotation_error_deg", "rotation error", "deg", 3)[1:],
    *_stats("pose.translation_error_mm", "translation error", "mm", 1)[1:],
    *_stats("pose.add_mm", "ADD", "mm", 1),
    Metric("pose.ok_wrong_rate", "poses ok but wrong", "lower", "rate"),
    Metric("pose.ok_wrong", "poses ok but wrong, count", "lower", "count", digits=0),
    Metric("pose.ok_precision", "poses ok that are right", "higher", "rate"),
    Metric("pose.initial.success_rate", "pose success before ICP", "higher", "rate"),
    *_stats("pose.initial.rotation_error_deg", "rotation error before ICP", "deg", 3),
    *_stats("pose.initial.translation_error_mm", "translation error before ICP", "mm", 1),
    # change (DESIGN 7, 10.7)
    Metric("change.macro_f1", "change macro-F1", "higher", "rate", headline=True, compact="change macro-F1"),
    *_prf("change.per_label", "per-label"),
    Metric("change.per_label.*.f1", "per-label F1", "higher", "rate"),
    Metric("change.objects.macro_f1", "change macro-F1 of objects", "higher", "rate"),
    *_prf("change.objects.per_label", "per-label (objects)"),
    Metric("change.objects.per_label.*.f1", "per-label F1 (objects)", "higher", "rate"),
    *_stats("change.displacement_error_mm", "displacement error of moved features", "mm", 1),
    Metric("change.altered_by_kind.*.f1", "altered F1 by kind of object", "higher", "rate"),
    *_prf("change.altered_by_kind", "altered by kind of object"),
    Metric("change.false_alarm_rate", "false alarms on unchanged features", "lower", "rate"),
    # the run
    Metric("n_failed", "failed trials", "lower", "count", digits=0, headline=True, per_method=False),
    Metric("timing_s.total.median", "time per trial, median", "lower", "time", "s", 2, headline=True,
           compact="time per trial", per_method=False),
    Metric("timing_s.*.median", "stage time, median", "lower", "time", "s"),
    Metric("timing_s.*.p90", "stage time, p90", "lower", "time", "s"),
)

#: Numeric leaves that are not metrics, and why.
INFORMATIVE: tuple[Informative, ...] = (
    Informative("n_trials", "how many trials"),
    Informative("n_planned", "how many trials the suite plans (an incomplete run has fewer)"),
    Informative("segmentation.tolerance", "setting: the Hoover overlap tolerance T"),
    Informative("segmentation.min_truth_pixels", "setting: the scoring floor of truth regions"),
    Informative("segmentation.n_images", "how many images"),
    Informative("segmentation.n_truth_regions", "how many truth regions were scored"),
    Informative("segmentation.missed_causes.*", "diagnostic: the missed rate split by cause"),
    Informative("classification.n_patches", "how many patches were scored"),
    Informative("classification.n_patches_all", "how many patches there were"),
    Informative("classification.min_patch_pixels", "setting: the scoring floor of patches"),
    Informative("classification.per_class.*.support", "how many truth patches of the class"),
    Informative("classification.radius.*.*", "diagnostic: fitted radii against the truth (signed bias, "
                "coverage of 2 sigma: no better direction)"),
    Informative("pose.n", "how many trials have a pose"),
    Informative("pose.n_constrained", "how many trials constrain all 6 DOF"),
    Informative("pose.initial.n", "how many trials have a pose before ICP"),
    Informative("pose.n_ok", "how many trials have an ok pose"),
    Informative("pose.n_conditional", "how many trials have a pose conditional on one object (not ok)"),
    Informative("pose.conditional_wrong", "how many of the conditional poses are wrong (not a success)"),
    Informative("change.per_label.*.support", "how many truth features of the label"),
    Informative("change.objects.per_label.*.support", "how many truth objects of the label"),
    Informative("change.altered_by_kind.*.support", "how many truth altered features of the kind of object"),
    Informative("change.n_unchanged", "how many observable features did not change (the false alarms' base)"),
    # whole subtrees: tables and records, not figures
    Informative("segmentation.sweep.**", "the Hoover rates over the tolerance sweep (a report figure)"),
    Informative("segmentation.by_size.**", "correct detection per region size (a report table)"),
    Informative("classification.confusion.**", "the confusion matrix (a report figure)"),
    Informative("classification.reliability.**", "the reliability table (a report figure)"),
    Informative("pose.reliability.**", "the reliability table of ok poses' confidence (a report figure)"),
    Informative("view.**", "the viewing conditions of the trials (DESIGN 10.5)"),
    Informative("failures.**", "the failed trials and why"),
    Informative("provenance.**", "how and where the run was made"),
    Informative("run.**", "wall time and workers of the run"),
    Informative("ci95_bootstrap.**", "how the intervals were drawn"),
)


# -- lookups (read the declarations when called, so a test or a plug-in may extend them) ----------------------
def metric(key: str) -> Metric:
    """The metric declared with exactly ``key``.

    Raises
    ------
    KeyError
        No such declaration (the message lists the close ones).
    """
    for m in METRICS:
        if m.key == key:
            return m
    close = difflib.get_close_matches(key, [m.key for m in METRICS], n=3)
    raise KeyError(f"no metric {key!r} in evaluation/metrics.py" + (f" (did you mean {', '.join(close)}?)"
                                                                      if close else ""))


def headline() -> tuple[Metric, ...]:
    """The headline metrics, in table order."""
    return tuple(m for m in METRICS if m.headline)


def judged() -> tuple[Metric, ...]:
    """The headline metrics of each method (judged pooled and per group)."""
    return tuple(m for m in METRICS if m.headline and m.per_method)


def run_checks(check_time: bool = False) -> tuple[Metric, ...]:
    """The headline metrics of the run (judged once, pooled): time rules only when asked."""
    return tuple(m for m in METRICS if m.headline and not m.per_method and (check_time or m.rule != "time"))


def compact() -> tuple[Metric, ...]:
    """The metrics of the compact tables, in table order."""
    return tuple(m for m in METRICS if m.compact)


def _match(pattern: tuple[str, ...], path: tuple[str, ...]) -> bool:
    if pattern and pattern[-1] == "**":
        head = pattern[:-1]
        return len(path) >= len(head) and _match(head, path[:len(head)])
    return len(pattern) == len(path) and all(p in ("*", k) for p, k in zip(pattern, path, strict=True))


def _is_prefix(pattern: tuple[str, ...], path: tuple[str, ...]) -> bool:
    """Whether ``path`` is an inner node of ``pattern`` (a null section, a null statistics dict...)."""
    head = pattern[:-1] if pattern[-1:] == ("**",) else pattern
    return len(path) < len(head) and all(p in ("*", k) for p, k in zip(head, path, strict=False))


def split_scope(path: Sequence[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(scope, rest)``: the scope part of a summary path (``groups.<g>``, ``baselines.<m>``, ``oracles.<o>``,
    or both) and the path inside that scope's sections."""
    path = tuple(path)
    i = 0
    if len(path) > 2 and path[0] in _SCOPES:
        i = 2
    if len(path) > i + 2 and path[i] in _METHOD_TREES:
        i += 2
    return path[:i], path[i:]


def declaration(path: Sequence[str]) -> Metric | Informative | None:
    """The declaration that covers the summary leaf at ``path`` (a tuple of keys, with or without its scope);
    None when none does. The most specific wins (fewest wildcards; then the first declared)."""
    _, rest = split_scope(path)
    best, best_n = None, 0
    for d in (*METRICS, *INFORMATIVE):
        if d.matches(rest):
            n = sum(p in ("*", "**") for p in d.path)
            if best is None or n < best_n:
                best, best_n = d, n
    return best


def covers_node(path: Sequence[str]) -> bool:
    """Whether ``path`` is a leaf or an inner node of some declaration (a null value there is expected)."""
    _, rest = split_scope(path)
    return declaration(path) is not None or any(_is_prefix(d.path, rest) for d in (*METRICS, *INFORMATIVE))


def is_interval_key(key: str) -> bool:
    """Whether a summary key holds an interval (``accuracy_ci95``) or how intervals were made (``ci95_bootstrap``):
    not a figure of its own (DESIGN 11.3)."""
    return key.endswith("_ci95") or key.startswith("ci95")


def leaves(summary: Mapping[str, Any]) -> Iterator[tuple[tuple[str, ...], float | None]]:
    """The numeric leaves of a summary (and its null values) as ``(path, value)``, walking dicts only, skipping
    intervals and the subtrees declared :class:`Informative` with ``**`` (the leaves ``harness compare`` lists)."""

    def walk(node: Mapping[str, Any], prefix: tuple[str, ...]) -> Iterator[tuple[tuple[str, ...], float | None]]:
        for k, v in node.items():
            key = str(k)
            path = (*prefix, key)
            if is_interval_key(key) or _is_tree(path):
                continue
            if v is None:
                yield path, None
            elif isinstance(v, Mapping):
                yield from walk(v, path)
            elif isinstance(v, bool):
                continue
            elif isinstance(v, int | float) and v == v and abs(v) != float("inf"):
                yield path, float(v)

    yield from walk(summary, ())


def _is_tree(path: tuple[str, ...]) -> bool:
    d = declaration(path)
    return isinstance(d, Informative) and d.tree


def undeclared(summary: Mapping[str, Any]) -> list[str]:
    """The dotted paths (scopes written ``groups.*``, ``baselines.*``, ``oracles.*``) of the numeric leaves and
    null values of ``summary`` that no declaration covers, lists included (``key[]``: any of its items)."""
    out: set[str] = set()

    def show(path: tuple[str, ...]) -> str:
        scope, rest = split_scope(path)
        generic = tuple(p if i % 2 == 0 else "*" for i, p in enumerate(scope))
        return ".".join((*generic, *rest)).replace(".[]", "[]")

    def walk(node: Any, path: tuple[str, ...]) -> None:
        if path and (is_interval_key(path[-1]) or _is_tree(tuple(p for p in path if p != "[]"))):
            return
        clean = tuple(p for p in path if p != "[]")
        if isinstance(node, Mapping):
            for k, v in node.items():
                walk(v, (*path, str(k)))
        elif isinstance(node, list | tuple):
            for v in node:
                walk(v, (*path, "[]"))
        elif node is None:
            if path and not covers_node(clean):
                out.add(show(path))
        elif isinstance(node, int | float) and not isinstance(node, bool):
            if declaration(clean) is None or "[]" in path:
                out.add(show(path))

    walk(summary, ())
    return sorted(out)


def _valid_scope(scope: Sequence[str]) -> bool:
    if not scope:
        return True
    if scope[0] in _METHOD_TREES:
        return len(scope) == 2
    return scope[0] in _SCOPES and len(scope) >= 2  # a group's name may hold dots


def check_allowance_key(key: str) -> Metric:
    """The metric a ``per_metric`` allowance of a tolerances file names (``classification.accuracy``,
    ``groups.<group>.pose.success_rate``, ``baselines.paper.change.macro_f1``).

    Raises
    ------
    KeyError
        ``key`` names no declared metric (the message says what would).
    """
    parts = tuple(key.split("."))
    for i in range(len(parts)):
        if not _valid_scope(parts[:i]):
            continue
        found = [m for m in METRICS if m.matches(parts[i:])]
        if found:
            return min(found, key=lambda m: m.path.count("*"))
    close = difflib.get_close_matches(key, [m.key for m in METRICS], n=1)
    raise KeyError("not a declared metric (a key of evaluation/metrics.py, optionally after groups.<group>. and "
                   "baselines.<method>.)" + (f"; did you mean {close[0]}?" if close else ""))
