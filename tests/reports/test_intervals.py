"""Cluster-bootstrap intervals (DESIGN 11.3): a closed form, determinism, the weights formulation against a
slow reference that literally resamples scenes and re-aggregates, degenerate inputs, and the summary keys."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.stats import binom

from evaluation.aggregate import (
    aggregate_change,
    aggregate_classification,
    aggregate_pose,
    aggregate_segmentation,
)
from evaluation.classification import CLASSES
from evaluation.intervals import (
    BootstrapParams,
    Clusters,
    MeanOfRatios,
    Median,
    Ratio,
    Resampling,
    cluster_weights,
    counts,
    interval,
    percentile_interval,
    resample_indices,
)
from harness.compare import compare, flatten, regressions
from harness.summary import comparable, summarise
from scenes.vocabulary import CHANGE_LABELS

Z95 = 1.959963984540054
PHI_Z95 = math.exp(-Z95 ** 2 / 2) / math.sqrt(2 * math.pi)  # normal density at the 97.5 % point


def pose_trials(successes: int, n: int) -> list[dict]:
    return [{"rotation_error_deg": None, "translation_error_mm": None, "success": i < successes,
             "constrained": True} for i in range(n)]


def mc_sd_of_quantile(n_boot: int, se: float, q: float = 0.025) -> float:
    """Monte Carlo standard deviation of the q-quantile of n_boot draws from a normal of sd ``se``."""
    return math.sqrt(q * (1 - q) / n_boot) * se / PHI_Z95


# -- closed form --------------------------------------------------------------------------------------------
def test_binomial_proportion_with_one_trial_per_scene_matches_closed_forms():
    """One trial per scene: resampling scenes resamples Bernoulli outcomes, so the resampled success count is
    exactly Binomial(n, p_hat) and the percentile interval tends (n_boot -> inf) to its 2.5 and 97.5 % points,
    which for large n are the normal (Wald) interval p_hat +- z SE, and Wilson's up to O(z^2 / n).

    Tolerances: the Monte Carlo sd of a sample 2.5 % quantile is sqrt(q (1 - q) / B) / f(x_q)
    (``mc_sd_of_quantile``: 0.00043 here, B = 20000) and we allow 4 of them; the bootstrap distribution has
    atoms 1 / n apart (the percentile falls within one atom of the exact quantile); the binomial's skewness
    moves its quantiles from the normal ones by |1 - 2p| (z^2 - 1) / 6 / sqrt(n p (1 - p)) sd (Cornish-Fisher,
    0.2 counts); Wilson's centre is (z^2 / 2n) |1 - 2p| / (1 + z^2 / n) from p_hat.
    """
    n, k, n_boot = 400, 120, 20000
    p = k / n
    rs = Clusters.of([f"scene{i:03d}" for i in range(n)], BootstrapParams(n_boot=n_boot, seed=7)).resampling(
        [f"scene{i:03d}" for i in range(n)])
    out = aggregate_pose(pose_trials(k, n), resampling=rs)
    assert out["success_rate"] == p
    lo, hi = out["success_rate_ci95"]
    se = math.sqrt(p * (1 - p) / n)
    mc = 4 * mc_sd_of_quantile(n_boot, se)
    # the exact bootstrap distribution's quantiles
    exact = binom.ppf([0.025, 0.975], n, p) / n
    assert abs(lo - exact[0]) <= 1 / n + mc and abs(hi - exact[1]) <= 1 / n + mc
    # normal (Wald)
    skew = abs(1 - 2 * p) * (Z95 ** 2 - 1) / 6 / math.sqrt(n * p * (1 - p)) * se
    tol = 1 / n + mc + skew
    assert abs(lo - (p - Z95 * se)) <= tol and abs(hi - (p + Z95 * se)) <= tol
    # Wilson
    d = 1 + Z95 ** 2 / n
    centre = (p + Z95 ** 2 / (2 * n)) / d
    half = Z95 / d * math.sqrt(p * (1 - p) / n + Z95 ** 2 / (4 * n ** 2))
    tol_w = tol + Z95 ** 2 / (2 * n) * abs(1 - 2 * p) / d + abs(half - Z95 * se)
    assert abs(lo - (centre - half)) <= tol_w and abs(hi - (centre + half)) <= tol_w
    assert tol_w < 0.25 * Z95 * se  # the check is tighter than a quarter of the half-width


def test_ratio_is_pooled_not_a_mean_of_scene_figures():
    # scene A: 1 of 1 right, scene B: 0 of 9; every resample drawing each once pools 1 / 10, not 0.5
    ratio = Ratio(np.array([1.0, 0.0]), np.array([1.0, 9.0]))
    w = np.array([[1, 1], [2, 0], [0, 2]])
    assert ratio.samples(w).tolist() == [0.1, 1.0, 0.0]


# -- determinism --------------------------------------------------------------------------------------------
def test_same_seed_same_interval_other_seed_close():
    n, k = 60, 21
    names = [f"s{i}" for i in range(n)]

    def ci(seed: int) -> list[float]:
        rs = Clusters.of(names, BootstrapParams(seed=seed)).resampling(names)
        return aggregate_pose(pose_trials(k, n), resampling=rs)["success_rate_ci95"]

    a, b, c = ci(0), ci(0), ci(1)
    assert a == b  # bit-identical
    assert np.array_equal(cluster_weights(n, 2000, 0), cluster_weights(n, 2000, 0))
    assert not np.array_equal(cluster_weights(n, 2000, 0), cluster_weights(n, 2000, 1))
    p = k / n
    se = math.sqrt(p * (1 - p) / n)
    # two independent Monte Carlo estimates of the same quantile: difference sd is sqrt(2) times one's; atoms
    # are 1/n apart
    tol = 1 / n + 4 * math.sqrt(2) * mc_sd_of_quantile(2000, se)
    assert all(abs(x - y) <= tol for x, y in zip(a, c, strict=True))


def test_weights_are_the_counts_of_the_draws():
    idx = resample_indices(5, 300, seed=3)
    w = cluster_weights(5, 300, seed=3)
    assert w.shape == (300, 5) and w.dtype == np.int64 and np.all(w.sum(axis=1) == 5)
    for b in (0, 17, 299):
        assert w[b].tolist() == np.bincount(idx[b], minlength=5).tolist()
    assert counts(np.zeros((2, 0), dtype=np.int64), 3).tolist() == [[0, 0, 0], [0, 0, 0]]


# -- the weights formulation against a slow reference -------------------------------------------------------
RATE_KEYS = ("correct_detection_rate", "over_rate", "under_rate", "missed_rate", "noise_rate")
unit = st.floats(0.0, 1.0, allow_nan=False)
maybe_unit = st.one_of(st.none(), unit)
error = st.one_of(st.none(), st.floats(0.0, 50.0, allow_nan=False), st.just(float("inf")))


@st.composite
def probabilities(draw) -> dict[str, float]:
    raw = np.array(draw(st.lists(st.floats(0.01, 1.0), min_size=len(CLASSES), max_size=len(CLASSES))))
    return dict(zip(CLASSES, (raw / raw.sum()).tolist(), strict=True))


patch = st.fixed_dictionaries({"truth": st.sampled_from(CLASSES), "label": st.sampled_from(CLASSES),
                               "n_pixels": st.sampled_from([50, 200, 900]), "probabilities": probabilities()})
labelled = st.fixed_dictionaries({"truth": st.sampled_from(CHANGE_LABELS),
                                  "predicted": st.sampled_from(CHANGE_LABELS)})


@st.composite
def trial(draw) -> dict[str, Any]:
    seg = {k: draw(maybe_unit) for k in RATE_KEYS}
    seg.update(tolerance=0.8, n_truth=4)
    pose = {"rotation_error_deg": draw(error), "translation_error_mm": draw(error), "success": draw(st.booleans()),
            "constrained": draw(st.booleans())}
    if draw(st.booleans()):
        pose["initial"] = {"rotation_error_deg": draw(error), "translation_error_mm": draw(error),
                           "success": draw(st.booleans())}
    if draw(st.booleans()):
        pose["add_mm"] = draw(error)
    change = {"features": draw(st.lists(labelled, max_size=4)), "objects": draw(st.lists(labelled, max_size=2)),
              "displacement_error_mm": draw(st.lists(st.floats(0.0, 80.0), max_size=2))}
    return {"segmentation": seg, "classification": {"patches": draw(st.lists(patch, max_size=4))}, "pose": pose,
            "change": change}


scenes = st.lists(st.lists(trial(), min_size=1, max_size=3), min_size=1, max_size=5)

FIGURES: dict[str, tuple[Any, list[tuple[str, ...]]]] = {
    "segmentation": (aggregate_segmentation, [(k,) for k in RATE_KEYS]),
    "classification": (aggregate_classification, [("accuracy",), ("brier",), ("ece",)]
                       + [("per_class", c, k) for c in CLASSES for k in ("precision", "recall")]),
    "pose": (aggregate_pose, [("success_rate",), ("success_rate_constrained",), ("rotation_error_deg", "median"),
                              ("translation_error_mm", "median"), ("add_mm", "median"),
                              ("initial", "success_rate"), ("initial", "rotation_error_deg", "median"),
                              ("initial", "translation_error_mm", "median")]),
    "change": (aggregate_change, [("macro_f1",), ("displacement_error_mm", "median"), ("objects", "macro_f1")]
               + [("per_label", lab, k) for lab in CHANGE_LABELS for k in ("precision", "recall", "f1")]
               + [("objects", "per_label", lab, "f1") for lab in CHANGE_LABELS]),
}


def get(node: Any, path: tuple) -> Any:
    for key in path:
        if not isinstance(node, dict):
            return None
        node = node.get(key)
    return node


def ci_path(path: tuple) -> tuple:
    return (*path[:-1], path[-1] + "_ci95")


def reference(by_scene: list[list[dict]], section: str, n_boot: int, seed: int) -> dict[tuple, list[float] | None]:
    """Literally resample scenes with replacement (the same draws as the weights), re-aggregate each resample
    with the existing functions, and take the percentile interval of each figure; no interval unless at least
    two scenes define the figure on their own."""
    agg, paths = FIGURES[section]

    def figures(trials: list[dict]) -> list[float]:
        out = agg([t[section] for t in trials]) if trials else None
        return [np.nan if (v := get(out, path)) is None else float(v) for path in paths]

    own = np.array([figures(s) for s in by_scene])  # (n_scenes, n_figures)
    idx = resample_indices(len(by_scene), n_boot, seed)
    samples = np.array([figures([t for k in row for t in by_scene[k]]) for row in idx])  # (n_boot, n_figures)
    result = {}
    for j, path in enumerate(paths):
        iv = percentile_interval(samples[:, j]) if np.isfinite(own[:, j]).sum() >= 2 else None
        result[path] = None if iv is None else list(iv)
    return result


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(by_scene=scenes, seed=st.integers(0, 2 ** 32 - 1))
def test_weights_formulation_equals_literal_resampling(by_scene, seed):
    n_boot = 48
    names = [f"scene{k}" for k, s in enumerate(by_scene) for _ in s]
    trials = [t for s in by_scene for t in s]
    rs = Clusters.of(names, BootstrapParams(n_boot=n_boot, seed=seed)).resampling(names)
    assert np.array_equal(rs.weights, counts(resample_indices(len(by_scene), n_boot, seed), len(by_scene)))
    for section, (agg, paths) in FIGURES.items():
        fast = agg([t[section] for t in trials], resampling=rs)
        want = reference(by_scene, section, n_boot, seed)
        for path in paths:
            got = get(fast, ci_path(path))
            if want[path] is None:
                assert got is None, (section, path)
            else:
                assert got == pytest.approx(want[path], rel=1e-9, abs=1e-12), (section, path)


@settings(max_examples=60, deadline=None)
@given(data=st.lists(st.tuples(st.integers(0, 3), st.integers(-3, 3).map(float)), max_size=12),
       seed=st.integers(0, 1000))
def test_weighted_median_is_the_median_of_the_written_out_resample(data, seed):
    values = np.array([v for _, v in data])
    cluster = np.array([c for c, _ in data], dtype=np.int64)
    idx = resample_indices(4, 30, seed)
    got = Median(values, cluster, 4).samples(counts(idx, 4))
    for b, row in enumerate(idx):
        written = np.concatenate([values[cluster == k] for k in row] + [np.zeros(0)])
        want = np.median(written) if written.size else np.nan
        assert (np.isnan(got[b]) and np.isnan(want)) or got[b] == want


# -- degenerate inputs --------------------------------------------------------------------------------------
def test_one_scene_gives_no_interval():
    rs = Clusters.of(["mockup"] * 5).resampling(["mockup"] * 5)
    out = aggregate_pose(pose_trials(3, 5), resampling=rs)
    assert out["success_rate"] == 0.6 and out["success_rate_ci95"] is None
    assert interval(Ratio([3.0], [5.0]), cluster_weights(1)) is None


def test_empty_input_gives_no_interval():
    assert interval(Ratio([], []), cluster_weights(0)) is None
    assert interval(Median([], [], 0), cluster_weights(0)) is None
    assert percentile_interval(np.full(10, np.nan)) is None
    assert Clusters.of([]).weights.shape == (2000, 0)


def test_undefined_resamples_are_left_out():
    # scene 0 has no patch: a resample drawing only scene 0 has no accuracy and is left out
    ratio = Ratio([0.0, 3.0, 1.0], [0.0, 4.0, 2.0])
    w = cluster_weights(3, 4000, seed=5)
    s = ratio.samples(w)
    only_empty = w[:, 0] == 3
    assert only_empty.any() and np.all(np.isnan(s[only_empty])) and np.all(np.isfinite(s[~only_empty]))
    assert interval(ratio, w) == percentile_interval(s[~only_empty])
    # a figure that only one scene defines has no interval (resampling it only repeats it)
    assert interval(Ratio([0.0, 3.0, 0.0], [0.0, 4.0, 0.0]), w) is None
    assert interval(MeanOfRatios([[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [2.0, 0.0]]), cluster_weights(2)) is None


def test_no_patches_gives_null_accuracy_and_null_interval():
    trials = [{"patches": [{"truth": "CYL", "label": "CYL", "n_pixels": 10, "probabilities": {"CYL": 1.0}}]}] * 3
    rs = Clusters.of(["a", "b", "c"]).resampling(["a", "b", "c"])
    out = aggregate_classification(trials, resampling=rs)
    assert out["accuracy"] is None and out["accuracy_ci95"] is None and out["brier_ci95"] is None


@pytest.mark.parametrize(("make", "match"), [
    (lambda: Ratio([1.0, 2.0], [1.0]), "differ in shape"),
    (lambda: interval(Ratio([1.0, 2.0], [1.0, 2.0]), cluster_weights(3)), r"shape \(n_boot, 2\)"),
    (lambda: Median([1.0, np.nan], [0, 1], 2), "finite"),
    (lambda: Median([1.0], [2], 2), r"in \[0, 2\)"),
    (lambda: BootstrapParams(n_boot=0), "n_boot"),
    (lambda: BootstrapParams(level=1.0), "level"),
    (lambda: Clusters.of(["a"]).resampling(["b"]), "not one of"),
    (lambda: Resampling(np.zeros(2, dtype=int), cluster_weights(1)).check(3), "describes 2 items"),
])
def test_misuse_raises(make, match):
    with pytest.raises(ValueError, match=match):
        make()


# -- the summary ----------------------------------------------------------------------------------------------
def records(scenes: list[str]) -> list[dict]:
    from test_reports import make_records

    recs = make_records(pose=True, change=True, groups=("a/x", "b/y"), methods=("core", "paper"))
    for r, s in zip(recs, scenes, strict=True):
        r["spec"]["scene"] = s
    return recs


def summary(scenes: list[str], **kw) -> dict:
    return summarise(records(scenes), suite="t", config_hash="c", version="v", methods=["core", "paper"], **kw)


HEADLINE_CI = [("segmentation", k) for k in RATE_KEYS] + [
    ("classification", "accuracy"), ("classification", "brier"), ("pose", "success_rate"),
    ("pose", "success_rate_constrained"), ("pose", "rotation_error_deg", "median"),
    ("pose", "translation_error_mm", "median"), ("pose", "add_mm", "median"), ("change", "macro_f1")] + [
    ("change", "per_label", lab, "f1") for lab in CHANGE_LABELS]


def test_summary_carries_intervals_beside_every_headline_figure():
    s = summary(["s0", "s1", "s2", "s3"])
    scopes = [s, s["baselines"]["paper"], *s["groups"].values(), s["groups"]["a/x"]["baselines"]["paper"]]
    for scope in scopes:
        for path in HEADLINE_CI:
            assert get(scope, path) is not None, path
            ci = get(scope, ci_path(path))
            assert isinstance(ci, list) and len(ci) == 2 and ci[0] <= ci[1], path
    assert list(s["segmentation"])[:2] == ["correct_detection_rate", "correct_detection_rate_ci95"]
    assert s["ci95_bootstrap"]["n_clusters"] == 4 and s["groups"]["a/x"]["ci95_bootstrap"]["clusters"] == ["s0", "s1"]
    assert s["ci95_bootstrap"]["n_boot"] == 2000 and s["ci95_bootstrap"]["cluster_key"] == "spec.scene"


def test_one_scene_summary_has_null_intervals_and_keeps_section_8():
    s = summary(["mockup"] * 4)
    for path in HEADLINE_CI:
        assert get(s, path) is not None and get(s, ci_path(path)) is None, path
    for key in ("correct_detection_rate", "over_rate", "under_rate", "missed_rate", "noise_rate", "tolerance"):
        assert key in s["segmentation"]
    assert set(s["pose"]["rotation_error_deg"]) >= {"median", "p90", "max"}


def test_intervals_are_comparable_and_ignored_by_compare():
    a, b = summary(["s0", "s1", "s2", "s3"]), summary(["s0", "s1", "s2", "s3"])
    assert comparable(a) == comparable(b)
    assert comparable(a)["classification"]["accuracy_ci95"] == a["classification"]["accuracy_ci95"]
    assert not any("ci95" in m for m in flatten(a))
    other = summary(["s0", "s1", "s2", "s3"], bootstrap=BootstrapParams(seed=1))
    one_scene = summary(["mockup"] * 4)  # every interval null
    for cand in (other, one_scene):
        rows = compare(a, cand)
        assert regressions(rows) == [] and not any("ci95" in r.metric for r in rows)
        assert not any(r.delta for r in rows)
