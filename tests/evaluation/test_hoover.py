"""Tests of the Hoover et al. (1996) region metrics (evaluation/hoover.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from evaluation.hoover import (
    CORRECT,
    MISSED,
    NOISE,
    OVER,
    UNDER,
    UNSCORED,
    connected_truth_regions,
    hoover_score,
    hoover_sweep,
    mean_scores,
    missed_causes,
    overlap_table,
)


def _cls(score, truth_id):
    return score.truth_class[score.truth_ids.index(truth_id)]


def _mcls(score, machine_id):
    return score.machine_class[score.machine_ids.index(machine_id)]


def test_truth_fed_as_machine_scores_perfectly():
    truth = np.zeros((20, 30), int)
    truth[:, 10:] = 1
    truth[5:15, 20:25] = 2
    truth[0, 0] = -1
    for s in [hoover_score(truth, truth), *hoover_sweep(truth, truth)]:
        assert s.correct_detection_rate == 1.0
        assert s.over_rate == s.under_rate == s.missed_rate == s.noise_rate == 0.0
        assert s.n_truth == s.n_machine == 3


def test_sweep_default_tolerances():
    truth = np.zeros((4, 4), int)
    scores = hoover_sweep(truth, truth)
    assert len(scores) == 12
    assert scores[0].tolerance == pytest.approx(0.51) and scores[-1].tolerance == pytest.approx(0.95)


def test_correct_detection_with_small_error():
    truth = np.zeros((10, 10), int)
    truth[:, 5:] = 1
    machine = truth.copy()
    machine[0, 5] = 0  # one pixel of truth 1 labelled 0
    s = hoover_score(machine, truth, 0.8)
    assert s.n_correct == 2 and s.correct_detection_rate == 1.0


def test_over_segmentation():
    truth = np.zeros((10, 10), int)
    machine = np.zeros((10, 10), int)
    machine[:, 5:] = 1
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == OVER and s.over_rate == 1.0
    assert s.truth_partners[0] == (0, 1)
    assert _mcls(s, 0) == OVER and _mcls(s, 1) == OVER
    assert s.n_over_instances == 1 and s.noise_rate == 0.0


def test_under_segmentation():
    truth = np.zeros((10, 10), int)
    truth[:, 5:] = 1
    machine = np.zeros((10, 10), int)
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == UNDER and _cls(s, 1) == UNDER
    assert s.under_rate == 1.0 and s.n_under_instances == 1
    assert _mcls(s, 0) == UNDER


def test_missed_and_noise():
    truth = np.zeros((10, 10), int)
    truth[:, 5:] = 1
    machine = np.full((10, 10), -1)
    machine[:, 3:7] = 7  # straddles both halves equally: neither mostly inside the other
    machine[:, :3] = 8  # 30 of truth 0's 50 pixels: not enough for a detection
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == MISSED and _cls(s, 1) == MISSED
    assert _mcls(s, 7) == NOISE
    assert s.missed_rate == 1.0 and s.noise_rate == 1.0
    # region 8 is wholly inside truth 0 but covers too little of it: alone it is not an over-segmentation
    assert _mcls(s, 8) == NOISE


def _tie_images(c_outside: int):
    """Truth g (40 px) = m1 (36 px) + 4 px of m2; m2 has ``c_outside`` more pixels in truth h."""
    truth = np.full((1, 70), -1)
    truth[0, :40] = 0
    truth[0, 40:60] = 1
    machine = np.full((1, 70), -1)
    machine[0, :36] = 10
    machine[0, 36:40] = 11
    machine[0, 40:40 + c_outside] = 11
    machine[0, 40 + c_outside:60] = 12
    return machine, truth


def test_tie_keeps_correct_detection():
    machine, truth = _tie_images(c_outside=1)
    # correct (m1, g): (36/40 + 1) / 2 = 0.95; over g -> {m1, m2}: ((1 + 4/5)/2 + 40/40) / 2 = 0.95
    assert 0.5 * (36 / 40 + 1.0) == 0.5 * (np.mean([1.0, 4 / 5]) + 1.0)
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == CORRECT and s.truth_partners[0] == (10,)
    assert _mcls(s, 11) == NOISE


def test_strictly_better_over_segmentation_replaces_correct():
    machine, truth = _tie_images(c_outside=0)  # m2 wholly inside g: the literal fragment case
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == OVER and s.truth_partners[0] == (10, 11)


@pytest.mark.parametrize("tol, expected", [(0.8, CORRECT), (0.80001, MISSED)])
def test_tolerance_boundary_is_inclusive(tol, expected):
    truth = np.zeros((1, 10), int)
    machine = np.full((1, 10), -1)
    machine[0, :8] = 3  # O = 8 = 0.8 |g|
    s = hoover_score(machine, truth, tol)
    assert _cls(s, 0) == expected


def test_tolerance_one_needs_identity():
    truth = np.zeros((3, 3), int)
    machine = truth.copy()
    machine[0, 0] = -1
    assert hoover_score(machine, truth, 1.0).n_missed == 1
    assert hoover_score(truth, truth, 1.0).n_correct == 1


@pytest.mark.parametrize("tol", [0.5, 0.0, 1.01, -1.0])
def test_bad_tolerance(tol):
    z = np.zeros((2, 2), int)
    with pytest.raises(ValueError, match="tolerance"):
        hoover_score(z, z, tol)


@pytest.mark.parametrize(
    "m, g, msg",
    [
        (np.zeros((2, 2), int), np.zeros((2, 3), int), "differ in shape"),
        (np.zeros((2, 2, 1), int), np.zeros((2, 2, 1), int), "expected 2D"),
        (np.full((2, 2), 0.5), np.zeros((2, 2), int), "integer"),
    ],
)
def test_bad_inputs(m, g, msg):
    with pytest.raises(ValueError, match=msg):
        hoover_score(m, g)


def test_truth_minus_one_pixels_are_ignored():
    truth = np.full((4, 10), -1)
    truth[:, :5] = 0
    machine = np.zeros((4, 10), int)  # extends over unknown truth: those pixels do not count in |m|
    s = hoover_score(machine, truth, 0.95)
    assert s.n_correct == 1
    only_unknown = np.full((4, 10), -1)
    only_unknown[:, 6:] = 5
    s2 = hoover_score(only_unknown, truth)
    assert s2.n_machine == 0 and np.isnan(s2.noise_rate) and s2.n_missed == 1


def test_min_truth_pixels_small_regions_are_no_truth():
    truth = np.zeros((10, 10), int)
    truth[0, :3] = 1  # 3-pixel truth region
    machine = truth.copy()
    machine[0, :3] = 5
    s = hoover_score(machine, truth, 0.8, min_truth_pixels=10)
    assert s.n_truth == 1 and s.correct_detection_rate == 1.0
    assert _cls(s, 1) == UNSCORED and _mcls(s, 5) == UNSCORED
    # region 5 lies on the small region only: no pixel on a scored truth region, so neither noise nor counted
    assert s.n_machine == 1 and s.noise_rate == 0.0
    s_all = hoover_score(machine, truth, 0.8)
    assert s_all.n_truth == 2 and s_all.n_correct == 2


# Hand-made cases, one per kind, with and without a small truth region (T = 0.8, min_truth_pixels = 10; the
# small region ``s`` has 9 pixels). Images are single rows given as runs of (label, pixels); -1 = none. The
# expected values are worked out from the definitions in the comments ("old": the treatment before issue 35,
# when small regions joined the matching and were only left out of the rates).
HAND_MADE = {
    # O = 38 of |g| = 40 and of |m| = 38: both >= T -> correct
    "correct": ([(0, 40)], [(5, 38), (-1, 2)],
                {"classes": {0: CORRECT}, "machine": {5: CORRECT}, "rates": (1, 0, 0, 0, 0), "n": (1, 1)}),
    # two halves, each wholly inside g, together all of it -> over-segmentation
    "over": ([(0, 40)], [(1, 20), (2, 20)],
             {"classes": {0: OVER}, "machine": {1: OVER, 2: OVER}, "rates": (0, 1, 0, 0, 0), "n": (1, 2)}),
    # one machine region over two truth regions, each wholly inside it -> under-segmentation
    "under": ([(0, 20), (1, 20)], [(3, 40)],
              {"classes": {0: UNDER, 1: UNDER}, "machine": {3: UNDER}, "rates": (0, 0, 1, 0, 0), "n": (2, 1)}),
    # O = 30 < T |g| = 32 and a single fragment: missed; the fragment (inside g, too small) is noise
    "missed": ([(0, 40)], [(4, 30), (-1, 10)],
               {"classes": {0: MISSED}, "machine": {4: NOISE}, "rates": (0, 0, 0, 1, 1), "n": (1, 1),
                "causes": "unlabelled"}),
    # m6 has 4 px on each region: not mostly inside either, neither mostly inside it -> noise; the rest correct
    "noise": ([(0, 20), (1, 20)], [(7, 16), (6, 8), (8, 16)],
              {"classes": {0: CORRECT, 1: CORRECT}, "machine": {7: CORRECT, 6: NOISE, 8: CORRECT},
               "rates": (1, 0, 0, 0, 1 / 3), "n": (2, 3)}),
    # s inside a machine region that detects g: |m| = 30 (s's 9 px are no truth), O = 30 -> correct.
    # (old: |m| = 39, O = 30 < 31.2, and {g, s} both inside m with 39 >= 31.2 -> an under-segmentation)
    "small in correct": ([(0, 30), (1, 9)], [(5, 39)],
                         {"classes": {0: CORRECT, 1: UNSCORED}, "machine": {5: CORRECT}, "rates": (1, 0, 0, 0, 0),
                          "n": (1, 1)}),
    # s inside the second half of an over-segmentation: |m2| = 20 -> both halves inside g -> over.
    # (old: |m2| = 29, O = 20 < 23.2: only m1 inside g, no over-segmentation -> missed)
    "small in over": ([(0, 40), (1, 9)], [(1, 20), (2, 29)],
                      {"classes": {0: OVER, 1: UNSCORED}, "machine": {1: OVER, 2: OVER}, "rates": (0, 1, 0, 0, 0),
                       "n": (1, 2)}),
    # s inside an under-segmenting region: |m| = 40, g0 and g1 inside it, 40 >= 32 -> under (old: under too,
    # with s among its truth regions)
    "small in under": ([(0, 20), (1, 20), (2, 9)], [(3, 49)],
                       {"classes": {0: UNDER, 1: UNDER, 2: UNSCORED}, "machine": {3: UNDER}, "rates": (0, 0, 1, 0, 0),
                        "n": (2, 1)}),
    # s pads an under-segmentation: m covers g0 (10), g1 (10), 6 px of g2 (40) and s (9). |m| = 26 and
    # 10 + 10 = 20 < T |m| = 20.8 -> no under-segmentation; (m, g0): 10 < 20.8 -> not correct: g0, g1 missed,
    # merged; g2 = 34 px of m9 -> correct. (old: |m| = 35, 10 + 10 + 9 = 29 >= 28 -> under {g0, g1, s})
    "small pads under": ([(0, 10), (1, 10), (3, 9), (2, 40)], [(3, 35), (9, 34)],
                         {"classes": {0: MISSED, 1: MISSED, 2: CORRECT, 3: UNSCORED}, "machine": {3: NOISE, 9: CORRECT},
                          "rates": (1 / 3, 0, 0, 2 / 3, 1 / 2), "n": (3, 2), "causes": "merged"}),
    # m covers half of g and all of s: |m| = 20, O = 20 >= 16 but < T |g| = 32 -> missed, and labelling the
    # other half would have done: unlabelled. (old: |m| = 29, O = 20 < 23.2 -> cause "merged")
    "small in missed": ([(0, 40), (1, 9)], [(4, 20), (-1, 20), (4, 9)],
                        {"classes": {0: MISSED, 1: UNSCORED}, "machine": {4: NOISE}, "rates": (0, 0, 0, 1, 1),
                         "n": (1, 1), "causes": "unlabelled"}),
    # the noise case with s in the noise region: |m6| = 8 on scored truth -> noise, counted: 1 of 3.
    # (old: m6's largest overlap is with s, so it was left out of the noise rate: 0 of 2)
    "small in noise": ([(0, 20), (1, 9), (2, 20)], [(7, 16), (6, 17), (8, 16)],
                       {"classes": {0: CORRECT, 1: UNSCORED, 2: CORRECT}, "machine": {7: CORRECT, 6: NOISE, 8: CORRECT},
                        "rates": (1, 0, 0, 0, 1 / 3), "n": (2, 3)}),
}


def _runs(runs: list[tuple[int, int]]) -> np.ndarray:
    return np.concatenate([np.full(n, label) for label, n in runs])[None, :]


@pytest.mark.parametrize("case", list(HAND_MADE))
def test_hand_made_cases_of_each_kind(case):
    truth_runs, machine_runs, want = HAND_MADE[case]
    truth, machine = _runs(truth_runs), _runs(machine_runs)
    assert truth.shape == machine.shape
    s = hoover_score(machine, truth, 0.8, min_truth_pixels=10)
    assert {t: _cls(s, t) for t in want["classes"]} == want["classes"]
    assert {m: _mcls(s, m) for m in want["machine"]} == want["machine"]
    rates = (s.correct_detection_rate, s.over_rate, s.under_rate, s.missed_rate, s.noise_rate)
    assert rates == pytest.approx(want["rates"])
    assert (s.n_truth, s.n_machine) == want["n"]
    causes = missed_causes(machine, truth, s)
    assert causes == {k: s.n_missed * (k == want.get("causes")) for k in ("unlabelled", "split", "merged")}
    # the same figures from the sweep, which scores one overlap table at every tolerance
    (swept,) = hoover_sweep(machine, truth, [0.8], min_truth_pixels=10)
    assert swept == s


def _as_no_truth(truth: np.ndarray, min_pixels: int) -> np.ndarray:
    ids, counts = np.unique(truth[truth >= 0], return_counts=True)
    return np.where(np.isin(truth, ids[counts < min_pixels]), -1, truth)


@settings(max_examples=60, deadline=None)
@given(machine=arrays(np.int64, (6, 7), elements=st.integers(-1, 4)),
       truth=arrays(np.int64, (6, 7), elements=st.integers(-1, 5)),
       tol=st.floats(0.51, 1.0), min_pixels=st.integers(0, 12))
def test_small_truth_regions_score_as_no_truth(machine, truth, tol, min_pixels):
    """A truth region under the floor scores exactly as if its pixels had no truth label."""
    s = hoover_score(machine, truth, tol, min_truth_pixels=min_pixels)
    ref = hoover_score(machine, _as_no_truth(truth, min_pixels), tol)
    keys = ("n_truth", "n_machine", "n_correct", "n_over", "n_under", "n_missed", "n_noise",
            "n_over_instances", "n_under_instances")
    assert [getattr(s, k) for k in keys] == [getattr(ref, k) for k in keys]
    np.testing.assert_equal([s.correct_detection_rate, s.noise_rate], [ref.correct_detection_rate, ref.noise_rate])
    scored = {t: c for t, c in zip(s.truth_ids, s.truth_class, strict=True) if c != UNSCORED}
    assert scored == dict(zip(ref.truth_ids, ref.truth_class, strict=True))
    assert missed_causes(machine, truth, s) == missed_causes(machine, _as_no_truth(truth, min_pixels), ref)


def test_overlap_table_counts():
    truth = np.array([[0, 0, 1, 1], [0, 0, 1, -1]])
    machine = np.array([[4, 4, 4, -1], [2, 2, 2, 2]])
    mids, tids, msz, tsz, pairs = overlap_table(machine, truth)
    assert mids.tolist() == [2, 4] and tids.tolist() == [0, 1]
    assert msz.tolist() == [3, 3] and tsz.tolist() == [4, 3]
    table = {(int(mids[a]), int(tids[b])): int(o) for a, b, o in pairs}
    assert table == {(2, 0): 2, (2, 1): 1, (4, 0): 2, (4, 1): 1}


def test_connected_truth_regions_splits_pieces():
    ids = np.array([[3, 3, 9, 3], [3, 3, 9, 3], [-1, -1, -1, 3]])
    regions = connected_truth_regions(ids)
    assert regions.tolist() == [[0, 0, 1, 2], [0, 0, 1, 2], [-1, -1, -1, 2]]
    diag = np.array([[1, 0], [0, 1]])
    assert len(np.unique(connected_truth_regions(diag, 4))) == 4
    assert len(np.unique(connected_truth_regions(diag, 8))) == 2
    with pytest.raises(ValueError, match="connectivity"):
        connected_truth_regions(diag, 6)


def test_mean_scores():
    truth = np.zeros((4, 4), int)
    half = truth.copy()
    half[:, 2:] = 1
    out = mean_scores([hoover_score(truth, truth), hoover_score(half, truth)])
    assert out["correct_detection_rate"] == 0.5 and out["over_rate"] == 0.5 and out["tolerance"] == 0.8


label_images = arrays(np.int64, (6, 7), elements=st.integers(-1, 4))


@settings(max_examples=60, deadline=None)
@given(machine=label_images, truth=label_images, tol=st.floats(0.51, 1.0), seed=st.integers(0, 2**16))
def test_hoover_consistency_properties(machine, truth, tol, seed):
    s = hoover_score(machine, truth, tol)
    scored = [c for c in s.truth_class if c != UNSCORED]
    assert len(scored) == s.n_truth
    assert s.n_correct + s.n_over + s.n_under + s.n_missed == s.n_truth
    assert all(c in (CORRECT, OVER, UNDER, MISSED) for c in s.truth_class)
    assert all(c in (CORRECT, OVER, UNDER, NOISE) for c in s.machine_class)
    for r in (s.correct_detection_rate, s.over_rate, s.under_rate, s.missed_rate, s.noise_rate):
        assert np.isnan(r) or 0.0 <= r <= 1.0
    if s.n_truth:
        total = s.correct_detection_rate + s.over_rate + s.under_rate + s.missed_rate
        assert total == pytest.approx(1.0)
    # relabelling the machine regions by a permutation changes nothing but the ids
    perm = np.random.default_rng(seed).permutation(50) + 100
    relabelled = np.where(machine >= 0, perm[np.maximum(machine, 0)], -1)
    s2 = hoover_score(relabelled, truth, tol)
    assert (s2.n_correct, s2.n_over, s2.n_under, s2.n_missed, s2.n_noise) == (
        s.n_correct, s.n_over, s.n_under, s.n_missed, s.n_noise)
    assert s2.truth_class == s.truth_class
    # the truth scored against itself is perfect
    assert hoover_score(truth, truth, tol).n_correct == hoover_score(truth, truth, tol).n_truth
    # every missed region has exactly one cause
    assert sum(missed_causes(machine, truth, s).values()) == s.n_missed


def _strips(widths: list[int], rows: int = 10) -> np.ndarray:
    """A label image of vertical strips ``widths`` wide, labelled 0, 1, 2, ... (-1 for a width given < 0)."""
    cols = np.concatenate([np.full(abs(w), k if w > 0 else -1) for k, w in enumerate(widths)])
    return np.tile(cols, (rows, 1))


@pytest.mark.parametrize("machine_widths,cause", [
    # truth: g = columns 0-9, g2 = columns 10-49 (detected correctly in every case)
    ([7, -3, 40], "unlabelled"),  # 70 % of g labelled, the rest not: labelling it would do
    ([6, 10, 34], "split"),  # g in two pieces, the smaller one merged with 6 columns of g2
    ([16, 34], "merged"),  # one region over g and 6 columns of g2: not mostly inside g
    ([-10, 40], "unlabelled"),  # no machine pixel on g at all
])
def test_missed_causes_on_hand_made_images(machine_widths, cause):
    truth = _strips([10, 40])
    machine = _strips(machine_widths)
    s = hoover_score(machine, truth, 0.8)
    assert _cls(s, 0) == MISSED and _cls(s, 1) == CORRECT
    assert missed_causes(machine, truth, s) == {k: int(k == cause) for k in ("unlabelled", "split", "merged")}


def test_missed_causes_are_empty_without_misses():
    truth = _strips([10, 20])
    assert missed_causes(truth, truth, hoover_score(truth, truth)) == {"unlabelled": 0, "split": 0, "merged": 0}
