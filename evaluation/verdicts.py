"""Regression verdicts of a candidate run against a base run (DESIGN 10.9, 11.3): one implementation, used by
``harness compare`` and by the report's regression section.

What is judged
--------------
The verdict is on the *headline metrics* of :mod:`evaluation.metrics` (``headline=True``, where every metric
is declared once): those of each method (:func:`evaluation.metrics.judged`, :data:`HEADLINE_METRICS` in the
shipped declarations), pooled over the run (scope ``all``) and per group, plus those of the run, pooled only:
the number of failed trials (:data:`N_FAILED`) and, when asked (``Tolerances.check_time``), the median time
per trial (:data:`TIME`). Every other numeric leaf of ``summary.json`` (p90 and max of the errors, per-class
and per-label figures, counts, oracles...) is informative only: it never fails a comparison.

A metric counts once: the figures of one (method, metric) over its scopes make one :class:`MetricVerdict`,
failing when any of its scopes fails (a group is what a per-preset target means, DESIGN 10.5), and listed
once with the scopes that failed. The core always counts; another method (``baselines.<name>``) is judged
the same way and shown, but fails the comparison only when it is selected (``methods``).

The verdict of one figure (:func:`decide`), ``b`` the base's value, ``c`` the candidate's, ``d = c - b``,
``[lo, hi]`` the 95 % interval of the paired delta (below):

1. ``b`` present, ``c`` absent: ``missing`` (fails) when the candidate lost the stage (its section is null,
   or the method is absent; a group in one run only is not compared, and said so); ``not scored`` (passes)
   when the section is there but has nothing to score for this figure (no patch of 200 pixels, no
   constrained trial...).
2. ``b`` absent: ``new`` when ``c`` is present, ``n/a`` when neither is (both pass).
3. Beyond the tolerance (``harness/tolerances/*.yaml``, :class:`Tolerances`), by the metric's declared rule
   (:data:`evaluation.metrics.RULES`): a ``rate`` is *worse* when it moved the bad way by more than
   ``rate_drop`` (``b - c`` for a higher-is-better rate; a per-metric allowance replaces ``rate_drop``); an
   ``error`` (lower is better) is worse when ``c > b (1 + error_growth) + error_floor``; *better* is the mirror
   image (``c - b > rate_drop``; ``c < b (1 - error_growth) - error_floor``). A ``count`` (failed trials) is
   worse when ``c - b > n_failed_increase``, better when ``c < b``; a ``time`` when
   ``c > b (1 + time_growth) + time_floor_s``.
4. Worse beyond the tolerance: ``regression`` when the interval lies wholly on the bad side of zero
   (``hi < 0`` for a rate, ``lo > 0`` for an error; an end exactly at zero does not exclude it), or when there
   is no interval (no trial records, fewer than two scenes, failed trials, times): the tolerance alone then
   decides, as before intervals existed. Otherwise ``within noise`` (passes).
5. Better beyond the tolerance: ``improved``, or ``within noise`` when the interval reaches zero.
6. Otherwise ``pass``.

The paired interval
-------------------
Trials are paired by trial id (:class:`TrialPair`); the scene of a pair (``spec.scene``) is the unit of
resampling, as for the intervals of ``summary.json`` (:mod:`evaluation.intervals`, the same
:class:`~evaluation.intervals.Clusters` weights, 2000 resamples, seed 0). On every resample of scenes both
runs' trials of the scenes drawn are taken, each run's pooled figure is *recomputed* from per-trial
sufficient statistics summed per scene (accuracy: correct and patches; Brier: summed per-patch score and
patches; a Hoover rate: the trials' rates and their count; success: successes and trials; macro-F1: 2 tp and
n_pred + n_true per label; a median: the pooled values weighted by their scene's count), and the delta is
candidate minus base on that resample (:class:`Difference`). The interval is the percentile interval of
those deltas; it is None when fewer than two scenes contribute to either side.

"What changed most" (:func:`trial_moves`): the paired trials ranked by how far their own figures moved.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from evaluation import metrics
from evaluation.intervals import (
    DEFAULT_BOOTSTRAP,
    BootstrapParams,
    Clusters,
    Interval,
    MeanOfRatios,
    Median,
    Ratio,
    Statistic,
    interval,
)
from evaluation.metrics import MACRO_LABELS, MIN_SCORED_PIXELS, Metric
from scenes.config import Fields, load_yaml
from scenes.vocabulary import CLASSES

ALL = "all"  # the scope of the whole run
FAILING = ("missing", "regression")
#: verdicts from the most to the least serious (a metric takes the first one among its scopes)
SEVERITY = ("missing", "regression", "within noise", "improved", "not scored", "new", "pass", "n/a")
_EPS = 1e-12  # a change by exactly the tolerance is within it (rounding)


# -- the rules' parameters --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Tolerances:
    """Regression rules. Rates: absolute change allowed in the bad direction; errors, the Brier score and
    times: relative growth allowed, with an absolute floor so that tiny values do not trip on rounding.

    Attributes
    ----------
    per_metric : an allowance for one figure, by its dotted path in ``summary.json``
        (``classification.accuracy``, ``groups.<g>.pose.success_rate``, ``baselines.paper.change.macro_f1``);
        a path without ``groups.``/``baselines.`` applies to every scope and method without their own. Its
        key must name a metric declared in :mod:`evaluation.metrics`.
    """

    rate_drop: float = 0.02
    error_growth: float = 0.10
    error_floor: float = 1e-3
    time_growth: float = 0.5
    time_floor_s: float = 0.05
    n_failed_increase: int = 0
    check_time: bool = False
    per_metric: dict[str, float] = field(default_factory=dict)

    @staticmethod
    def load(path: str | Path) -> Tolerances:
        """Rules from a ``tolerances/1`` YAML file (``harness/tolerances/default.yaml``)."""
        f = Fields(load_yaml(path), str(path))
        schema = f.string("schema", "tolerances/1")
        if schema != "tolerances/1":
            raise f.error("schema", f"unsupported schema {schema!r} (expected 'tolerances/1')")
        per = f.sub("per_metric", {})
        t = Tolerances(
            rate_drop=f.number("rate_drop", 0.02, nonnegative=True),
            error_growth=f.number("error_growth", 0.10, nonnegative=True),
            error_floor=f.number("error_floor", 1e-3, nonnegative=True),
            time_growth=f.number("time_growth", 0.5, nonnegative=True),
            time_floor_s=f.number("time_floor_s", 0.05, nonnegative=True),
            n_failed_increase=f.integer("n_failed_increase", 0, min=0),
            check_time=f.boolean("check_time", False),
            per_metric={str(k): per.number(str(k), nonnegative=True) for k in per.data},
        )
        for k in per.data:
            try:
                metrics.check_allowance_key(str(k))
            except KeyError as exc:
                raise per.error(str(k), exc.args[0]) from None
        f.check_unknown()
        return t

    def allowance(self, path: str, key: str) -> float | None:
        """The per-metric allowance of the figure at dotted ``path`` (metric ``key``), if one is set."""
        return self.per_metric.get(path, self.per_metric.get(key))


#: the shipped defaults (``harness/tolerances/default.yaml`` holds the same values)
DEFAULT_TOLERANCES = Tolerances()


# -- the headline metrics (declared in evaluation.metrics) ------------------------------------------------------
#: The headline metrics of each method in the shipped declarations (:func:`evaluation.metrics.judged`).
HEADLINE_METRICS: tuple[Metric, ...] = metrics.judged()
N_FAILED = metrics.metric("n_failed")
TIME = metrics.metric("timing_s.total.median")


# -- per-trial sufficient statistics --------------------------------------------------------------------------
def _hoover(sec: Mapping[str, Any]) -> tuple[float, float]:
    v = sec.get("correct_detection_rate")
    return (0.0, 0.0) if v is None else (float(v), 1.0)


def _kept_patches(sec: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    return [p for p in sec.get("patches") or [] if p.get("n_pixels", 0) >= MIN_SCORED_PIXELS]


def _accuracy(sec: Mapping[str, Any]) -> tuple[float, float]:
    kept = _kept_patches(sec)
    return float(sum(p["truth"] == p["label"] for p in kept)), float(len(kept))


def _brier(sec: Mapping[str, Any]) -> tuple[float, float]:
    kept = _kept_patches(sec)
    total = sum(sum((float((p.get("probabilities") or {}).get(c, 0.0)) - (c == p["truth"])) ** 2 for c in CLASSES)
                for p in kept)
    return float(total), float(len(kept))


def _success(sec: Mapping[str, Any]) -> tuple[float, float]:
    return float(bool(sec.get("success"))), 1.0


def _success_constrained(sec: Mapping[str, Any]) -> tuple[float, float]:
    constrained = bool(sec.get("constrained", True))
    return float(bool(sec.get("success")) and constrained), float(constrained)


def _macro_terms(sec: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """2 tp and n_pred + n_true of each macro label (moved, missing, new, altered) over the trial's features."""
    feats = sec.get("features") or []
    num = np.array([2.0 * sum(f["truth"] == lab and f["predicted"] == lab for f in feats) for lab in MACRO_LABELS])
    den = np.array([float(sum(f["predicted"] == lab for f in feats) + sum(f["truth"] == lab for f in feats))
                    for lab in MACRO_LABELS])
    return num, den


RATIO_TERMS: dict[str, Callable[[Mapping[str, Any]], tuple[float, float]]] = {
    "segmentation.correct_detection_rate": _hoover,
    "classification.accuracy": _accuracy,
    "classification.brier": _brier,
    "pose.success_rate": _success,
    "pose.success_rate_constrained": _success_constrained,
}
MEDIAN_VALUES: dict[str, str] = {"pose.rotation_error_deg.median": "rotation_error_deg",
                                 "pose.translation_error_mm.median": "translation_error_mm"}


def _cluster_sums(values: np.ndarray, cluster: np.ndarray, n_clusters: int) -> np.ndarray:
    out = np.zeros((n_clusters, *values.shape[1:]))
    np.add.at(out, cluster, values)
    return out


def pooled_statistic(metric: Metric, sections: Sequence[Mapping[str, Any] | None], cluster: np.ndarray,
                     n_clusters: int) -> Statistic | None:
    """The pooled figure ``metric`` of some trials as per-cluster sufficient statistics.

    Parameters
    ----------
    sections : each trial's section of the metric's stage (``record.methods.<m>.<stage>``), None where the
        trial has none (failed, or the stage did not run): it then contributes nothing, as in the summary.
    cluster : ndarray of shape (n_trials,), int, each trial's cluster in [0, n_clusters).

    Returns
    -------
    A :class:`~evaluation.intervals.Ratio`, :class:`~evaluation.intervals.Median` or
    :class:`~evaluation.intervals.MeanOfRatios`; None for a metric without per-trial statistics.
    """
    cluster = np.asarray(cluster, dtype=np.int64).reshape(-1)
    if len(sections) != len(cluster):
        raise ValueError(f"expected one cluster per section, got {len(cluster)} for {len(sections)}")
    present = [s is not None for s in sections]
    if metric.key in RATIO_TERMS:
        terms = np.array([RATIO_TERMS[metric.key](s) if s is not None else (0.0, 0.0) for s in sections],
                         dtype=np.float64).reshape(-1, 2)
        return Ratio(_cluster_sums(terms[:, 0], cluster, n_clusters), _cluster_sums(terms[:, 1], cluster, n_clusters))
    if metric.key in MEDIAN_VALUES:
        name = MEDIAN_VALUES[metric.key]
        raw = [s.get(name) if s is not None else None for s in sections]
        v = np.array([np.nan if x is None else float(x) for x in raw], dtype=np.float64)
        keep = np.isfinite(v)
        return Median(v[keep], cluster[keep], n_clusters)
    if metric.key == "change.macro_f1":
        k = len(MACRO_LABELS)
        num = np.zeros((len(sections), k))
        den = np.zeros((len(sections), k))
        for i, s in enumerate(sections):
            if present[i]:
                num[i], den[i] = _macro_terms(s)
        return MeanOfRatios(_cluster_sums(num, cluster, n_clusters), _cluster_sums(den, cluster, n_clusters))
    return None


def trial_figure(metric: Metric, section: Mapping[str, Any] | None) -> float | None:
    """A trial's own value of ``metric`` (its accuracy over its patches, its macro-F1 over its features...);
    None when the trial does not define it."""
    if section is None:
        return None
    stat = pooled_statistic(metric, [section], np.zeros(1, dtype=np.int64), 1)
    if stat is None:
        return None
    v = float(stat.samples(np.ones((1, 1), dtype=np.int64))[0])
    return v if np.isfinite(v) else None


@dataclass(frozen=True, eq=False)
class Difference:
    """``candidate - base`` of two pooled figures over the same clusters, on the same resamples (paired).

    Parameters
    ----------
    base, candidate : statistics over the same ``n_clusters`` clusters.
    """

    base: Statistic
    candidate: Statistic

    def __post_init__(self) -> None:
        if self.base.n_clusters != self.candidate.n_clusters:
            raise ValueError(f"base has {self.base.n_clusters} clusters, candidate {self.candidate.n_clusters}")

    @property
    def n_clusters(self) -> int:
        return self.base.n_clusters

    def samples(self, weights: np.ndarray) -> np.ndarray:
        """The delta on each resample: ndarray of shape (n_boot,), NaN where either figure is undefined."""
        return self.candidate.samples(weights) - self.base.samples(weights)

    def n_contributing(self) -> int:
        """The clusters behind the less supported side (an interval needs two on each)."""
        return min(self.base.n_contributing(), self.candidate.n_contributing())


# -- pairs and their intervals ------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrialPair:
    """One trial id recorded by both runs: its scene (the cluster), group and the two records."""

    trial_id: str
    scene: str
    group: str
    base: Mapping[str, Any]
    candidate: Mapping[str, Any]


def method_section(record: Mapping[str, Any], method: str, stage: str) -> Mapping[str, Any] | None:
    """``record.methods.<method>.<stage>`` of a successful trial; None for a failed trial or a missing stage."""
    if record.get("status") != "ok":
        return None
    sec = ((record.get("methods") or {}).get(method) or {}).get(stage)
    return sec if isinstance(sec, Mapping) else None


def paired_interval(metric: Metric, method: str, pairs: Sequence[TrialPair], clusters: Clusters
                    ) -> tuple[float | None, Interval | None]:
    """The delta (candidate - base) of ``metric`` of ``method`` over ``pairs`` and its paired cluster-bootstrap
    interval over ``clusters`` (which must hold the pairs' scenes).

    Returns
    -------
    (delta, interval): ``delta`` recomputed from the records (equal to the summaries' delta when the pairs are
    the runs' trials; None when either side is undefined), ``interval`` None when the metric has no per-trial
    statistics or fewer than two scenes contribute to either side.
    """
    if not pairs:
        return None, None
    idx = clusters.resampling([p.scene for p in pairs]).cluster
    n = len(clusters.names)
    base = pooled_statistic(metric, [method_section(p.base, method, metric.section) for p in pairs], idx, n)
    cand = pooled_statistic(metric, [method_section(p.candidate, method, metric.section) for p in pairs], idx, n)
    if base is None or cand is None:
        return None, None
    diff = Difference(base, cand)
    point = float(diff.samples(np.ones((1, n), dtype=np.int64))[0])
    return (point if np.isfinite(point) else None), interval(diff, clusters.weights, clusters.params.level)


# -- the rule ---------------------------------------------------------------------------------------------
def tolerance_side(metric: Metric, base: float, candidate: float, tol: Tolerances,
                   allowed: float | None = None) -> int:
    """-1 when ``candidate`` is worse than ``base`` beyond the tolerance, +1 better beyond it, 0 within it
    (rule 3 of the module docstring, for the metric's declared rule and direction; the shipped counts, errors
    and times are lower-is-better, a higher-is-better one is judged in the mirror image); ``allowed``: a
    per-metric allowance."""
    b, c = base, candidate
    sign = -1 if metric.direction == "higher" else 1  # on the lower-is-better scale: worse = larger
    if metric.rule == "count":
        limit = tol.n_failed_increase if allowed is None else allowed
        up = sign * (c - b)
        return -1 if up > limit + _EPS else (1 if up < -_EPS else 0)
    if metric.rule == "time":
        growth = tol.time_growth if allowed is None else allowed
        worse = c > b * (1 + growth) + tol.time_floor_s if sign > 0 else c < b * (1 - growth) - tol.time_floor_s
        return -1 if worse else 0
    if metric.rule == "rate":
        drop = tol.rate_drop if allowed is None else allowed
        bad = sign * (c - b)
        return -1 if bad > drop + _EPS else (1 if -bad > drop + _EPS else 0)
    growth = tol.error_growth if allowed is None else allowed
    grew, shrank = c > b * (1 + growth) + tol.error_floor, c < b * (1 - growth) - tol.error_floor
    worse, better = (grew, shrank) if sign > 0 else (shrank, grew)
    return -1 if worse else (1 if better else 0)


def decide(metric: Metric, base: float | None, candidate: float | None, ci: Interval | None,
           tol: Tolerances, *, lost: bool = False, allowed: float | None = None) -> tuple[str, str]:
    """The verdict of one figure and why (the rules of the module docstring).

    Parameters
    ----------
    ci : the 95 % interval of the paired delta ``candidate - base``, None when there is none.
    lost : the candidate lost the figure's stage (null section, or no such method or group).
    allowed : a per-metric allowance replacing the tolerance's default for this figure.

    Returns
    -------
    (verdict, reason), verdict one of :data:`SEVERITY`.
    """
    if base is None:
        return ("new", "absent in the base") if candidate is not None else ("n/a", "in neither run")
    if candidate is None:
        if lost:
            return "missing", "the candidate lost this stage (null section)"
        return "not scored", "the candidate has nothing to score for it (no such patch, label or trial)"
    side = tolerance_side(metric, base, candidate, tol, allowed)
    if side == 0:
        return "pass", "within tolerance"
    if ci is None:
        why = "beyond tolerance; no interval, the tolerance alone decides"
        return ("regression", why) if side < 0 else ("improved", why)
    bad_is_down = metric.direction == "higher"
    lo, hi = ci
    worse_surely = hi < 0 if bad_is_down else lo > 0
    better_surely = lo > 0 if bad_is_down else hi < 0
    if side < 0:
        return ("regression", "beyond tolerance, interval excludes 0") if worse_surely else \
            ("within noise", "beyond tolerance, but the interval reaches 0")
    return ("improved", "beyond tolerance, interval excludes 0") if better_surely else \
        ("within noise", "beyond tolerance, but the interval reaches 0")


# -- the comparison ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FigureVerdict:
    """One figure (method, scope, metric) of both runs and its verdict."""

    method: str
    scope: str
    metric: Metric
    base: float | None
    candidate: float | None
    interval: Interval | None
    verdict: str
    reason: str
    counted: bool

    @property
    def delta(self) -> float | None:
        return None if self.base is None or self.candidate is None else self.candidate - self.base

    @property
    def path(self) -> str:
        """The figure's dotted path in ``summary.json``."""
        scope = "" if self.scope == ALL else f"groups.{self.scope}."
        method = "" if self.method == "core" else f"baselines.{self.method}."
        return f"{scope}{method}{self.metric.key}"


@dataclass(frozen=True)
class MetricVerdict:
    """A (method, metric) counted once over its scopes: the most serious verdict among them (:data:`SEVERITY`)
    and the scopes that carry it."""

    method: str
    metric: Metric
    verdict: str
    scopes: tuple[str, ...]
    counted: bool

    @property
    def fails(self) -> bool:
        return self.counted and self.verdict in FAILING

    def describe(self) -> str:
        return f"{self.method} {self.metric.title} ({self.verdict}: {', '.join(self.scopes)})"


@dataclass(frozen=True)
class FigureMove:
    """One figure of one trial in both runs."""

    label: str
    base: float | None
    candidate: float | None
    digits: int = 3


@dataclass(frozen=True)
class TrialMove:
    """A paired trial whose figures moved, with how far (``score`` in [0, 2]: a rate's absolute change, an
    error's relative change, 2 for a trial that failed in the candidate only, 1.5 for one that now runs)."""

    trial_id: str
    scene: str
    group: str
    score: float
    status: str  # "" (ok in both), "failed: <reason>", "now runs", "failed in both"
    moves: tuple[FigureMove, ...]


@dataclass(frozen=True)
class Comparison:
    """Everything ``harness compare`` and the report's regression section show."""

    figures: tuple[FigureVerdict, ...]
    metrics: tuple[MetricVerdict, ...]
    moves: tuple[TrialMove, ...]
    counted_methods: tuple[str, ...]
    reported_methods: tuple[str, ...]
    n_pairs: int
    n_scenes: int
    notes: tuple[str, ...] = ()

    @property
    def regressions(self) -> tuple[MetricVerdict, ...]:
        """The counted metrics that fail (each once)."""
        return tuple(m for m in self.metrics if m.fails)

    @property
    def passed(self) -> bool:
        return not self.regressions

    def verdict_text(self) -> str:
        """What failed, or that nothing did and what was within noise or improved (one line, no prefix)."""
        counted = [m for m in self.metrics if m.counted and m.verdict != "n/a"]
        who = ", ".join(self.counted_methods)
        if self.regressions:
            return (f"{len(self.regressions)} regression(s) in {len(counted)} headline metric(s) of {who}: "
                    + "; ".join(m.describe() for m in self.regressions))
        text = f"no regression in {len(counted)} headline metric(s) of {who}"
        for word in ("within noise", "improved"):
            hits = [m for m in counted if m.verdict == word]
            if hits:
                text += f"; {word}: " + "; ".join(f"{m.method} {m.metric.title} ({', '.join(m.scopes)})"
                                                  for m in hits)
        return text

    def verdict_line(self) -> str:
        """``PASS: ...`` or ``FAIL: ...`` (:meth:`verdict_text`)."""
        return ("PASS: " if self.passed else "FAIL: ") + self.verdict_text()

    def uncounted_line(self) -> str:
        """What failed among the methods reported only (empty when nothing did)."""
        bad = [m for m in self.metrics if not m.counted and m.verdict in FAILING]
        if not bad:
            return ""
        names = sorted({m.method for m in bad})
        return (f"not counted: {'; '.join(m.describe() for m in bad)} (reported only: count them with "
                f"--methods {','.join(names)} or --methods all)")


def _lookup(node: Any, path: Sequence[str]) -> float | None:
    for key in path:
        if not isinstance(node, Mapping):
            return None
        node = node.get(key)
    if isinstance(node, bool) or not isinstance(node, int | float) or node != node:
        return None
    return float(node)


def scope_sections(summary: Mapping[str, Any], scope: str, method: str) -> Mapping[str, Any] | None:
    """A method's sections in one scope of a summary (the top level, or ``groups.<scope>``)."""
    node = summary if scope == ALL else (summary.get("groups") or {}).get(scope)
    if not isinstance(node, Mapping):
        return None
    if method == "core":
        return node
    sec = (node.get("baselines") or {}).get(method)
    return sec if isinstance(sec, Mapping) else None


def methods_of(*summaries: Mapping[str, Any]) -> list[str]:
    """``core``, then ``paper``, then the other methods of either summary by name."""
    peers = {m for s in summaries for m in (s.get("baselines") or {})}
    return ["core", *sorted(peers, key=lambda m: (m != "paper", m))]


def figure_verdict(metric: Metric, method: str, scope: str, base: Mapping[str, Any],
                   candidate: Mapping[str, Any], pairs: Sequence[TrialPair], clusters: Clusters | None,
                   tol: Tolerances, counted: bool) -> FigureVerdict:
    """The verdict of one figure: the values from the summaries, the interval from the paired trials."""
    bsec, csec = scope_sections(base, scope, method), scope_sections(candidate, scope, method)
    b, c = _lookup(bsec, metric.path), _lookup(csec, metric.path)
    lost = bool(bsec is not None and bsec.get(metric.section) is not None
                and (csec is None or csec.get(metric.section) is None))
    ci = None
    if b is not None and c is not None and clusters is not None and metric.rule in ("rate", "error"):
        ci = paired_interval(metric, method, pairs, clusters)[1]
    fig = FigureVerdict(method, scope, metric, b, c, ci, "", "", counted)
    verdict, reason = decide(metric, b, c, ci, tol, lost=lost, allowed=tol.allowance(fig.path, metric.key))
    return FigureVerdict(method, scope, metric, b, c, ci, verdict, reason, counted)


def metric_verdicts(figures: Sequence[FigureVerdict]) -> tuple[MetricVerdict, ...]:
    """Each (method, metric) once: its most serious verdict over the scopes, and the scopes that carry it
    (every failing scope when it fails)."""
    out = []
    keys = list(dict.fromkeys((f.method, f.metric) for f in figures))
    for method, metric in keys:
        mine = [f for f in figures if f.method == method and f.metric == metric]
        worst = min((f.verdict for f in mine), key=SEVERITY.index)
        failing = worst in FAILING
        scopes = tuple(f.scope for f in mine if (f.verdict in FAILING if failing else f.verdict == worst))
        out.append(MetricVerdict(method, metric, worst, scopes, mine[0].counted))
    return tuple(out)


def compare_runs(base: Mapping[str, Any], candidate: Mapping[str, Any], pairs: Sequence[TrialPair],
                 tol: Tolerances = DEFAULT_TOLERANCES, methods: Sequence[str] | str = (),
                 params: BootstrapParams = DEFAULT_BOOTSTRAP, top: int = 10,
                 notes: Sequence[str] = ()) -> Comparison:
    """The verdict of ``candidate`` against ``base`` (two ``summary.json`` dicts) on the headline metrics.

    Parameters
    ----------
    pairs : the trials both runs recorded, paired by trial id (empty: no intervals, tolerances alone).
    methods : the methods other than the core whose verdicts count (``"all"``: every method).
    params : the bootstrap of the paired intervals (default: the summary's).
    top : how many trials "what changed most" lists.
    notes : lines the caller wants shown with the comparison (e.g. how the runs differ, under --force).
    """
    names = methods_of(base, candidate)
    chosen = set(names) if methods == "all" else {"core", *methods}
    groups = [g for g in sorted(set(base.get("groups") or {}) | set(candidate.get("groups") or {}))]
    shared = [g for g in groups if g in (base.get("groups") or {}) and g in (candidate.get("groups") or {})]
    extra_notes = list(notes)
    if len(shared) < len(groups):
        only = sorted(set(groups) - set(shared))
        extra_notes.append(f"groups in one run only (not compared): {', '.join(only)}")
    scopes = [ALL, *shared]
    scope_pairs = {s: [p for p in pairs if s == ALL or p.group == s] for s in scopes}
    clusters = {s: Clusters.of([p.scene for p in ps], params) if ps else None for s, ps in scope_pairs.items()}
    if not pairs:
        extra_notes.append("no paired trial records: no intervals, the tolerances alone decide")
    figures: list[FigureVerdict] = []
    for method in names:
        for metric in metrics.judged():
            for s in scopes:
                figures.append(figure_verdict(metric, method, s, base, candidate, scope_pairs[s], clusters[s], tol,
                                              method in chosen))
    for metric in metrics.run_checks(tol.check_time):
        figures.append(figure_verdict(metric, "core", ALL, base, candidate, (), None, tol, True))
    return Comparison(tuple(figures), metric_verdicts(figures), trial_moves(pairs, tol, top),
                      tuple(m for m in names if m in chosen), tuple(m for m in names if m not in chosen),
                      len(pairs), len(clusters[ALL].names) if clusters[ALL] is not None else 0, tuple(extra_notes))


# -- what changed most --------------------------------------------------------------------------------------
def move_metrics() -> tuple[Metric, ...]:
    """The figures "what changed most" compares per trial: the headline metrics of a method but the constrained
    pose success (per trial it is the success itself, or undefined)."""
    return tuple(m for m in metrics.judged() if m.key != "pose.success_rate_constrained")



def _move_size(metric: Metric, b: float, c: float, tol: Tolerances) -> float:
    """How far a trial's figure moved on a [0, 1] scale: a rate's absolute change (the Brier score's halved,
    it spans [0, 2]); an error's relative change ``|c - b| / max(b, c)``, counted only beyond its tolerance."""
    if metric.rule == "rate":
        return abs(c - b)
    if metric.key == "classification.brier":
        return abs(c - b) / 2
    if tolerance_side(metric, b, c, tol) == 0:
        return 0.0
    return abs(c - b) / max(abs(b), abs(c))


def trial_moves(pairs: Sequence[TrialPair], tol: Tolerances = DEFAULT_TOLERANCES, top: int = 10,
                method: str = "core") -> tuple[TrialMove, ...]:
    """The ``top`` paired trials whose figures (of ``method``) moved most, most first (ties: by trial id).

    A trial that failed in one run only ranks first; a trial whose figures did not move is left out.
    """
    out = []
    for p in pairs:
        ok_b, ok_c = p.base.get("status") == "ok", p.candidate.get("status") == "ok"
        if not ok_b or not ok_c:
            if ok_b:
                out.append(TrialMove(p.trial_id, p.scene, p.group, 2.0, f"failed: {p.candidate.get('reason', '')}",
                                     ()))
            elif ok_c:
                out.append(TrialMove(p.trial_id, p.scene, p.group, 1.5, "now runs", ()))
            continue
        moves, score = [], 0.0
        for metric in move_metrics():
            b = trial_figure(metric, method_section(p.base, method, metric.section))
            c = trial_figure(metric, method_section(p.candidate, method, metric.section))
            if b is None and c is None:
                continue
            size = 1.0 if (b is None) != (c is None) else _move_size(metric, b, c, tol)
            if size > 1e-9:
                moves.append(FigureMove(metric.title, b, c, metric.digits))
                score = max(score, size)
        if moves:
            out.append(TrialMove(p.trial_id, p.scene, p.group, score, "", tuple(moves)))
    out.sort(key=lambda m: (-m.score, m.trial_id))
    return tuple(out[:max(top, 0)])
