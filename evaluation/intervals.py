"""95 % intervals of pooled figures by a cluster bootstrap over scenes (DESIGN 11.3).

Trials of one scene share its layout, its objects and their perturbations, so their figures are correlated:
the unit of resampling is the scene (a trial record's ``spec.scene``; for a generated scene family the member,
e.g. ``factory-s1003``), never the trial. A resample draws ``n_clusters`` clusters with replacement out of
the ``n_clusters`` of the scope (the whole run, or one group); a cluster drawn ``w`` times enters with weight
``w``. Row ``b`` of the weight matrix ``W``, of shape (n_boot, n_clusters), holds those counts.

Each pooled figure is a function of sums over clusters (its sufficient statistics), so the figure is
*recomputed* on every resample from the weighted sums, one matrix product per sum, as the summary computes
it from all trials; it is never an average of per-scene figures:

* :class:`Ratio`, ``sum(numerator) / sum(denominator)``: classification accuracy = correct / patches, the
  Brier score = sum of per-patch scores / patches, a Hoover rate (a mean over images) = sum of the images'
  rates / images, a success rate = successes / trials, a precision tp / n_pred, a recall tp / n_true, an F1
  2 tp / (n_pred + n_true);
* :class:`MeanOfRatios`, the mean of several ratios over those defined: macro-F1;
* :class:`CalibrationGap`, ``sum_b |sum conf_b - sum correct_b| / sum n_b``: the expected calibration error;
* :class:`Median`, the median of the pooled values, each weighted by its cluster's count (the median of the
  resample written out value by value, as ``numpy.median`` would compute it).

The interval is the bootstrap *percentile* interval (Efron & Tibshirani 1993, ch. 13): the 2.5 and 97.5
percentiles (``numpy.percentile``, linear interpolation) of the ``n_boot`` resampled figures. Resampling whole
clusters is the first strategy of Davison & Hinkley (1997, section 3.8) for hierarchical data, which keeps the
correlation inside a cluster; Field & Welsh (2007) show it is consistent as the number of clusters grows
whatever the correlation inside them.

Degenerate cases (the interval is None, never a faked zero-width interval):

* fewer than 2 clusters contribute to the figure (one scene in the scope, or a figure that only one scene
  defines, e.g. a class predicted in one scene only): resampling one cluster only repeats it, which says
  nothing about how the figure varies over scenes;
* no resample defines the figure.

A resample on which the figure is undefined (a zero denominator: no patch, no image with that rate, no truth
or predicted label among the clusters drawn; no value for a median) is left out, so the interval is
conditional on the figure being defined. With only 2 or 3 clusters the percentile interval is crude (a
resample can only mix those scenes): it shows the spread between them, not a calibrated 95 %.

Determinism: the draws come from ``numpy.random.default_rng(seed)`` alone, so the same input and parameters
give bit-identical intervals (on one numpy build: the weighted sums are matrix products).

References
----------
B. Efron and R. J. Tibshirani, *An Introduction to the Bootstrap*, Chapman & Hall, 1993,
doi:10.1201/9780429246593 (chapter 13, the percentile interval).
A. C. Davison and D. V. Hinkley, *Bootstrap Methods and their Application*, Cambridge University Press, 1997,
doi:10.1017/CBO9780511802843 (section 3.8, hierarchical data).
C. A. Field and A. H. Welsh, "Bootstrapping clustered data", *J. R. Stat. Soc. B* 69(3):369-390, 2007,
doi:10.1111/j.1467-9868.2007.00593.x.

Examples
--------
>>> w = cluster_weights(3, n_boot=1000, seed=0)
>>> acc = Ratio(numerator=np.array([8.0, 5.0, 9.0]), denominator=np.array([10.0, 10.0, 10.0]))
>>> lo, hi = interval(acc, w)
>>> bool(0.5 <= lo <= 22 / 30 <= hi <= 0.9)
True
>>> one = Ratio(numerator=np.array([8.0]), denominator=np.array([10.0]))
>>> interval(one, cluster_weights(1)) is None  # one scene: no interval over scenes
True
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

N_BOOT = 2000
SEED = 0
LEVEL = 0.95
CLUSTER_KEY = "spec.scene"
#: rows of the weight matrix handled at once by :class:`Median` (bounds its (rows, n_values) work arrays)
_MEDIAN_CHUNK_ELEMENTS = 4_000_000

Interval = tuple[float, float]


@dataclass(frozen=True)
class BootstrapParams:
    """Parameters of the cluster bootstrap behind every ``*_ci95`` of ``summary.json``.

    Attributes
    ----------
    n_boot : number of resamples. With 2000 the Monte Carlo standard error of a 2.5 % percentile is about
        ``sqrt(0.025 * 0.975 / 2000) / phi(1.96) = 0.06`` standard errors of the figure (normal case), small
        beside the interval's half-width of 1.96 standard errors.
    seed : seed of ``numpy.random.default_rng``; the same seed and clusters give the same weights.
    level : coverage of the two-sided percentile interval.
    """

    n_boot: int = N_BOOT
    seed: int = SEED
    level: float = LEVEL

    def __post_init__(self) -> None:
        if isinstance(self.n_boot, bool) or not isinstance(self.n_boot, int) or self.n_boot < 1:
            raise ValueError(f"n_boot must be a positive integer, got {self.n_boot!r}")
        if not 0.0 < float(self.level) < 1.0:
            raise ValueError(f"level must lie in (0, 1), got {self.level!r}")


#: the parameters of the summary's intervals (frozen: a constant, not shared mutable state)
DEFAULT_BOOTSTRAP = BootstrapParams()


# -- resampling ---------------------------------------------------------------------------------------------
def resample_indices(n_clusters: int, n_boot: int = N_BOOT, seed: int = SEED) -> np.ndarray:
    """The clusters drawn, with replacement, by each resample.

    Returns
    -------
    indices : ndarray of shape (n_boot, n_clusters), int64 in [0, n_clusters): row ``b`` lists the clusters
        of resample ``b`` (a cluster may appear several times).
    """
    if n_clusters < 0 or n_boot < 1:
        raise ValueError(f"expected n_clusters >= 0 and n_boot >= 1, got {n_clusters} and {n_boot}")
    if n_clusters == 0:
        return np.zeros((n_boot, 0), dtype=np.int64)
    rng = np.random.default_rng(seed)
    return rng.integers(0, n_clusters, size=(n_boot, n_clusters), dtype=np.int64)


def counts(indices: np.ndarray, n_clusters: int) -> np.ndarray:
    """How many times each cluster is drawn.

    Parameters
    ----------
    indices : ndarray of shape (n_boot, m), int, clusters drawn by each resample.

    Returns
    -------
    weights : ndarray of shape (n_boot, n_clusters), int64; row ``b`` sums to ``m``.
    """
    idx = np.asarray(indices, dtype=np.int64)
    if idx.ndim != 2:
        raise ValueError(f"expected indices of shape (n_boot, m), got {idx.shape}")
    n_boot = idx.shape[0]
    flat = (idx + n_clusters * np.arange(n_boot, dtype=np.int64)[:, None]).ravel()
    return np.bincount(flat, minlength=n_boot * n_clusters).reshape(n_boot, n_clusters)


def cluster_weights(n_clusters: int, n_boot: int = N_BOOT, seed: int = SEED) -> np.ndarray:
    """Multinomial cluster weights of the bootstrap: the counts of :func:`resample_indices`.

    Returns
    -------
    weights : ndarray of shape (n_boot, n_clusters), int64, each row summing to ``n_clusters``.
    """
    return counts(resample_indices(n_clusters, n_boot, seed), n_clusters)


def _check_weights(weights: np.ndarray, n_clusters: int) -> np.ndarray:
    w = np.asarray(weights)
    if w.ndim != 2 or w.shape[1] != n_clusters:
        raise ValueError(f"expected weights of shape (n_boot, {n_clusters}), got {w.shape}")
    return w


def _column(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 1:
        raise ValueError(f"expected {name} of shape (n_clusters,), got {a.shape}")
    return a


def _matrix(x: Any, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"expected {name} of shape (n_clusters, k), got {a.shape}")
    return a


def _divide(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """num / den, NaN where den is 0 (an undefined figure)."""
    out = np.full(np.broadcast(num, den).shape, np.nan)
    np.divide(num, den, out=out, where=den > 0)
    return out


# -- statistics ---------------------------------------------------------------------------------------------
class Statistic(Protocol):
    """A pooled figure as sufficient statistics per cluster."""

    @property
    def n_clusters(self) -> int: ...

    def samples(self, weights: np.ndarray) -> np.ndarray:
        """The figure on each resample: ndarray of shape (n_boot,), NaN where undefined."""
        ...

    def n_contributing(self) -> int:
        """How many clusters carry data for the figure."""
        ...


@dataclass(frozen=True, eq=False)
class Ratio:
    """``sum_k numerator[k] / sum_k denominator[k]`` over clusters (undefined when the denominator is 0).

    Parameters
    ----------
    numerator, denominator : ndarray of shape (n_clusters,), per-cluster sums (denominators >= 0).
    """

    numerator: np.ndarray
    denominator: np.ndarray

    def __post_init__(self) -> None:
        num, den = _column(self.numerator, "numerator"), _column(self.denominator, "denominator")
        if num.shape != den.shape:
            raise ValueError(f"numerator {num.shape} and denominator {den.shape} differ in shape")
        object.__setattr__(self, "numerator", num)
        object.__setattr__(self, "denominator", den)

    @property
    def n_clusters(self) -> int:
        return len(self.denominator)

    def samples(self, weights: np.ndarray) -> np.ndarray:
        w = _check_weights(weights, self.n_clusters)
        return _divide(w @ self.numerator, w @ self.denominator)

    def n_contributing(self) -> int:
        return int(np.count_nonzero(self.denominator > 0))


@dataclass(frozen=True, eq=False)
class MeanOfRatios:
    """The mean, over the terms defined on a resample, of ``k`` pooled ratios (macro-F1 over labels).

    Parameters
    ----------
    numerator, denominator : ndarray of shape (n_clusters, k), per-cluster sums of each term.
    """

    numerator: np.ndarray
    denominator: np.ndarray

    def __post_init__(self) -> None:
        num, den = _matrix(self.numerator, "numerator"), _matrix(self.denominator, "denominator")
        if num.shape != den.shape:
            raise ValueError(f"numerator {num.shape} and denominator {den.shape} differ in shape")
        object.__setattr__(self, "numerator", num)
        object.__setattr__(self, "denominator", den)

    @property
    def n_clusters(self) -> int:
        return self.denominator.shape[0]

    def samples(self, weights: np.ndarray) -> np.ndarray:
        w = _check_weights(weights, self.n_clusters)
        terms = _divide(w @ self.numerator, w @ self.denominator)  # (n_boot, k)
        defined = np.isfinite(terms)
        n = defined.sum(axis=1)
        return _divide(np.where(defined, terms, 0.0).sum(axis=1), n.astype(np.float64))

    def n_contributing(self) -> int:
        return int(np.count_nonzero((self.denominator > 0).any(axis=1)))


@dataclass(frozen=True, eq=False)
class CalibrationGap:
    """Expected calibration error ``sum_b |sum conf_b - sum correct_b| / sum_b n_b`` of binned confidences.

    Parameters
    ----------
    count, confidence_sum, correct_sum : ndarray of shape (n_clusters, n_bins): per cluster and confidence
        bin, the number of predictions, the sum of their confidences and the number of them that are right.
    """

    count: np.ndarray
    confidence_sum: np.ndarray
    correct_sum: np.ndarray

    def __post_init__(self) -> None:
        arrays = [_matrix(getattr(self, k), k) for k in ("count", "confidence_sum", "correct_sum")]
        if len({a.shape for a in arrays}) != 1:
            raise ValueError(f"count, confidence_sum and correct_sum differ in shape: {[a.shape for a in arrays]}")
        for k, a in zip(("count", "confidence_sum", "correct_sum"), arrays, strict=True):
            object.__setattr__(self, k, a)

    @property
    def n_clusters(self) -> int:
        return self.count.shape[0]

    def samples(self, weights: np.ndarray) -> np.ndarray:
        w = _check_weights(weights, self.n_clusters)
        gap = np.abs(w @ self.confidence_sum - w @ self.correct_sum).sum(axis=1)
        return _divide(gap, (w @ self.count).sum(axis=1))

    def n_contributing(self) -> int:
        return int(np.count_nonzero(self.count.sum(axis=1) > 0))


@dataclass(frozen=True, eq=False)
class Median:
    """The median of pooled values, each value weighted by how often its cluster is drawn.

    On integer weights it equals ``numpy.median`` of the resample written out (each value repeated as many
    times as its cluster is drawn): the middle value, or the mean of the two middle ones.

    Parameters
    ----------
    values : ndarray of shape (n_values,), finite.
    cluster : ndarray of shape (n_values,), int, the cluster of each value in [0, n_clusters).
    n_clusters : number of clusters of the scope (the weights' columns).
    """

    values: np.ndarray
    cluster: np.ndarray
    n_clusters: int

    def __post_init__(self) -> None:
        v = _column(self.values, "values")
        c = np.asarray(self.cluster, dtype=np.int64).reshape(-1)
        if c.shape != v.shape:
            raise ValueError(f"expected cluster of shape {v.shape}, got {c.shape}")
        if not np.all(np.isfinite(v)):
            raise ValueError("values must be finite (drop missing values first)")
        if c.size and (c.min() < 0 or c.max() >= self.n_clusters):
            raise ValueError(f"cluster indices must lie in [0, {self.n_clusters})")
        order = np.argsort(v, kind="stable")
        object.__setattr__(self, "values", v[order])
        object.__setattr__(self, "cluster", c[order])

    def samples(self, weights: np.ndarray) -> np.ndarray:
        w = _check_weights(weights, self.n_clusters)
        out = np.full(w.shape[0], np.nan)
        n = len(self.values)
        if n == 0:
            return out
        step = max(1, _MEDIAN_CHUNK_ELEMENTS // n)
        for start in range(0, w.shape[0], step):
            rows = slice(start, start + step)
            cum = np.cumsum(w[rows][:, self.cluster], axis=1)  # (m, n): resampled count up to each sorted value
            total = cum[:, -1]
            lower = (cum <= ((total - 1) // 2)[:, None]).sum(axis=1)  # position of the lower middle value
            upper = (cum <= (total // 2)[:, None]).sum(axis=1)
            ok = total > 0
            med = (self.values[np.minimum(lower, n - 1)] + self.values[np.minimum(upper, n - 1)]) / 2
            out[rows] = np.where(ok, med, np.nan)
        return out

    def n_contributing(self) -> int:
        return len(np.unique(self.cluster))


# -- the interval -------------------------------------------------------------------------------------------
def percentile_interval(samples: np.ndarray, level: float = LEVEL) -> Interval | None:
    """The percentile interval of resampled figures.

    Parameters
    ----------
    samples : ndarray of shape (n_boot,), NaN where the figure is undefined on a resample (left out).
    level : two-sided coverage.

    Returns
    -------
    (lo, hi), the ``(1 - level) / 2`` and ``(1 + level) / 2`` quantiles of the defined samples (linear
    interpolation), or None when no sample is defined.
    """
    s = np.asarray(samples, dtype=np.float64).reshape(-1)
    s = s[np.isfinite(s)]
    if not s.size:
        return None
    lo, hi = np.percentile(s, [50.0 * (1.0 - level), 50.0 * (1.0 + level)])
    return float(lo), float(hi)


def interval(statistic: Statistic, weights: np.ndarray, level: float = LEVEL) -> Interval | None:
    """The cluster-bootstrap percentile interval of a pooled figure (see the module docstring).

    Parameters
    ----------
    statistic : the figure's per-cluster sufficient statistics (:class:`Ratio`, :class:`MeanOfRatios`,
        :class:`CalibrationGap`, :class:`Median`).
    weights : ndarray of shape (n_boot, n_clusters), the clusters' counts in each resample
        (:func:`cluster_weights`).
    level : two-sided coverage.

    Returns
    -------
    (lo, hi), or None when fewer than 2 clusters contribute to the figure or no resample defines it.
    """
    w = _check_weights(weights, statistic.n_clusters)
    if statistic.n_contributing() < 2:
        return None
    return percentile_interval(statistic.samples(w), level)


# -- clusters of a summary scope ----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Resampling:
    """Items (trials, patches, features...), the cluster each belongs to and the clusters' bootstrap weights:
    what an aggregation needs to put an interval beside a pooled figure.

    Parameters
    ----------
    cluster : ndarray of shape (n_items,), int, each item's cluster in [0, n_clusters).
    weights : ndarray of shape (n_boot, n_clusters), the clusters' counts in each resample.
    level : two-sided coverage of the intervals.
    """

    cluster: np.ndarray
    weights: np.ndarray
    level: float = LEVEL

    def __post_init__(self) -> None:
        c = np.asarray(self.cluster, dtype=np.int64).reshape(-1)
        w = np.asarray(self.weights)
        if w.ndim != 2:
            raise ValueError(f"expected weights of shape (n_boot, n_clusters), got {w.shape}")
        if c.size and (c.min() < 0 or c.max() >= w.shape[1]):
            raise ValueError(f"cluster indices must lie in [0, {w.shape[1]})")
        object.__setattr__(self, "cluster", c)
        object.__setattr__(self, "weights", w)

    @property
    def n_clusters(self) -> int:
        return self.weights.shape[1]

    def __len__(self) -> int:
        return len(self.cluster)

    def check(self, n_items: int) -> Resampling:
        """Itself, after checking that it describes ``n_items`` items."""
        if len(self) != n_items:
            raise ValueError(f"resampling describes {len(self)} items, got {n_items}")
        return self

    def sums(self, values: Any) -> np.ndarray:
        """Per-cluster sums of per-item values.

        Parameters
        ----------
        values : array-like of shape (n_items,) or (n_items, k).

        Returns
        -------
        ndarray of shape (n_clusters,) or (n_clusters, k), float64.
        """
        v = np.asarray(values, dtype=np.float64)
        if v.shape[:1] != (len(self),):
            raise ValueError(f"expected values of shape ({len(self)}, ...), got {v.shape}")
        out = np.zeros((self.n_clusters, *v.shape[1:]))
        np.add.at(out, self.cluster, v)
        return out

    def expand(self, per_item: Sequence[int]) -> Resampling:
        """The resampling of the sub-items: item ``i`` holds ``per_item[i]`` of them (its patches...)."""
        return Resampling(np.repeat(self.cluster, np.asarray(per_item, dtype=np.int64)), self.weights, self.level)

    def select(self, keep: Any) -> Resampling:
        """The resampling of the items where ``keep`` (bool, shape (n_items,)) holds."""
        return Resampling(self.cluster[np.asarray(keep, dtype=bool)], self.weights, self.level)

    def ratio(self, numerator: Any, denominator: Any) -> list[float] | None:
        """The interval of ``sum numerator / sum denominator`` over the items, JSON-ready (or None)."""
        return as_json(interval(Ratio(self.sums(numerator), self.sums(denominator)), self.weights, self.level))

    def median(self, values: Sequence[float | None]) -> list[float] | None:
        """The interval of the median of the items' finite values (None and non-finite ones are left out)."""
        v = np.array([np.nan if x is None else float(x) for x in values], dtype=np.float64)
        if v.shape != (len(self),):
            raise ValueError(f"expected {len(self)} values, got {v.shape}")
        keep = np.isfinite(v)
        return as_json(interval(Median(v[keep], self.cluster[keep], self.n_clusters), self.weights, self.level))

    def of(self, statistic: Statistic) -> list[float] | None:
        """The interval of any statistic over this resampling's clusters, JSON-ready."""
        return as_json(interval(statistic, self.weights, self.level))


def as_json(iv: Interval | None) -> list[float] | None:
    """An interval as it is written into ``summary.json``: ``[lo, hi]`` or null."""
    return None if iv is None else [iv[0], iv[1]]


@dataclass(frozen=True, eq=False)
class Clusters:
    """The clusters (scenes) of one scope of the summary (the run, or one group) and their bootstrap weights,
    shared by every method and section of that scope so that their intervals come from the same resamples.

    Parameters
    ----------
    names : the distinct cluster names, sorted (the weights' column order).
    weights : ndarray of shape (n_boot, n_clusters).
    params : how the weights were drawn.
    """

    names: tuple[str, ...]
    weights: np.ndarray
    params: BootstrapParams = DEFAULT_BOOTSTRAP

    @classmethod
    def of(cls, names: Iterable[str], params: BootstrapParams = DEFAULT_BOOTSTRAP) -> Clusters:
        """The clusters named by ``names`` (repeats allowed), with their weights drawn from ``params``."""
        unique = tuple(sorted({str(n) for n in names}))
        return cls(unique, cluster_weights(len(unique), params.n_boot, params.seed), params)

    def resampling(self, item_clusters: Sequence[str]) -> Resampling:
        """The :class:`Resampling` of items whose clusters are named by ``item_clusters``."""
        index = {n: i for i, n in enumerate(self.names)}
        try:
            codes = np.array([index[str(n)] for n in item_clusters], dtype=np.int64)
        except KeyError as exc:
            raise ValueError(f"cluster {exc.args[0]!r} is not one of this scope's {len(self.names)}") from None
        return Resampling(codes, self.weights, self.params.level)

    def describe(self) -> dict[str, Any]:
        """How the scope's intervals were made (``ci95_bootstrap`` of ``summary.json``)."""
        return {"method": "cluster bootstrap, percentile interval", "cluster_key": CLUSTER_KEY,
                "level": self.params.level, "n_boot": self.params.n_boot, "seed": self.params.seed,
                "n_clusters": len(self.names), "clusters": list(self.names)}
