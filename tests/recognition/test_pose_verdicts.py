"""Pose verdicts that mean what they say (DESIGN 11.6): the separation of two poses' agreements, the precision
probes at the success tolerance, the smooth agreement they use, and the summary's count of ok-but-wrong poses."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation.aggregate import aggregate_pose
from evaluation.pose import rotation_error_deg
from recognition.localisation import (
    LocaliseParams,
    VerifyParams,
    agreement,
    agreement_separation,
    soft_agreement,
)
from recognition.localisation.precision import flattest_probe, probe_poses


def _desc(sizes):
    return SimpleNamespace(patches=tuple(SimpleNamespace(id=i, n_pixels=n) for i, n in enumerate(sizes)))


def test_separation_is_the_weighted_mean_difference_over_its_standard_error():
    desc = _desc([100, 1000, 10000])
    fa = {0: 0.9, 1: 0.8, 2: 0.7}
    fb = {0: 0.5, 1: 0.8, 2: 0.6}
    w = np.log([100.0, 1000.0, 10000.0])
    delta = np.array([0.4, 0.0, 0.1])
    d_ref = float(w @ delta / w.sum())
    se_ref = math.sqrt(3 / 2 * float(np.sum(w**2 * (delta - d_ref) ** 2))) / w.sum()
    d, se = agreement_separation(desc, fa, fb)
    assert d == pytest.approx(d_ref) and se == pytest.approx(se_ref)
    # antisymmetric, and patches scored by only one pose are left out
    d2, se2 = agreement_separation(desc, fb, {**fa, 7: 1.0})
    assert d2 == pytest.approx(-d_ref) and se2 == pytest.approx(se_ref)
    assert agreement_separation(desc, {0: 1.0}, {0: 0.0}) == (0.0, math.inf)  # one patch: nothing measures spread


def test_leaving_out_the_patches_that_favour_either_pose():
    """``leave_out`` drops the patches favouring A most, ``leave_out_b`` those favouring B most (ties: the larger
    patch first); the rest is scored as before."""
    desc = _desc([100, 200, 300, 400, 500])
    fa = {0: 1.0, 1: 0.9, 2: 0.5, 3: 0.2, 4: 0.5}
    fb = {0: 0.0, 1: 0.5, 2: 0.5, 3: 0.9, 4: 0.4}  # 0 favours A most, 3 favours B most
    keep = {1, 2, 4}
    ref = agreement_separation(desc, {k: fa[k] for k in keep}, {k: fb[k] for k in keep})
    assert agreement_separation(desc, fa, fb, leave_out=1, leave_out_b=1) == pytest.approx(ref)
    d_a, _ = agreement_separation(desc, fa, fb, leave_out=1)
    d_ab, _ = agreement_separation(desc, fa, fb, leave_out=1, leave_out_b=1)
    assert d_ab > d_a  # leaving out a patch that favours B never lowers d


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=2, max_size=8), st.floats(-0.5, 0.5))
def test_a_uniform_shift_of_every_patch_is_measured_exactly(fractions, shift):
    desc = _desc([50 + 10 * i for i in range(len(fractions))])
    fa = dict(enumerate(fractions))
    fb = {k: v - shift for k, v in fa.items()}
    d, se = agreement_separation(desc, fa, fb)
    assert d == pytest.approx(shift, abs=1e-12) and se == pytest.approx(0.0, abs=1e-12)


def test_probes_turn_about_the_sensor_and_move_by_the_step():
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    probes = probe_poses(T, math.radians(1.0), 0.02)
    assert len(probes) == 12
    for P in probes[:6]:
        assert rotation_error_deg(P[:3, :3], T[:3, :3]) == pytest.approx(1.0)
        assert np.array_equal(P[:3, 3], T[:3, 3])
    for k, P in enumerate(probes[6:]):
        assert np.array_equal(P[:3, :3], T[:3, :3])
        d = P[:3, 3] - T[:3, 3]
        assert abs(d[k // 2]) == pytest.approx(0.02) and np.count_nonzero(d) == 1


def test_the_flattest_probe_is_the_one_the_data_separate_least():
    desc = _desc([400, 400, 400])
    T = np.eye(4)

    def score(P):  # patch fractions fall with distance from T, least along z translation
        dr = math.radians(rotation_error_deg(P[:3, :3], T[:3, :3]))
        dt = P[:3, 3] - T[:3, 3]
        f = 1.0 - 10 * dr - 5 * abs(dt[0]) - 5 * abs(dt[1]) - 0.5 * abs(dt[2])
        return f, {0: f, 1: f - 0.1 * abs(dt[2]), 2: f + 0.05 * dr}

    z, k = flattest_probe(T, score(T)[1], score, math.radians(1.0), 0.01,
                          lambda a, b: agreement_separation(desc, a, b))
    assert k in (10, 11) and z > 0


def test_soft_agreement_counts_each_pixel_by_its_residual():
    shape = (10, 10)
    desc = SimpleNamespace(labels=np.zeros(shape, np.int32), sigma=np.full(shape, 0.0),
                           patches=(SimpleNamespace(id=0, n_pixels=100),))
    scan = SimpleNamespace(range=np.full(shape, 2.0))
    params = VerifyParams(stride=1, k_sigma=3.0, abs_m=0.01, rel=0.0, seen_through=0.0)
    exact = SimpleNamespace(stride=1, offset=0, range=np.full(shape, 2.0))
    half = SimpleNamespace(stride=1, offset=0, range=np.full(shape, 2.005))  # half the 10 mm threshold
    assert soft_agreement(desc, scan, exact, params)[0] == pytest.approx(1.0)
    assert soft_agreement(desc, scan, half, params)[0] == pytest.approx(0.75)
    assert agreement(desc, scan, half, params)[0] == pytest.approx(1.0)  # the count does not see it


def test_localise_params_validate_the_probes():
    with pytest.raises(ValueError, match="pin_angle_deg"):
        LocaliseParams(pin_rel=0.0)


def test_summary_counts_ok_poses_that_are_wrong_and_their_reliability():
    trials = [{"ok": True, "success": True, "confidence": 0.95, "rotation_error_deg": 0.1, "translation_error_mm": 1},
              {"ok": True, "success": False, "confidence": 0.92, "rotation_error_deg": 9.0, "translation_error_mm": 90},
              {"ok": False, "success": True, "confidence": 0.3, "rotation_error_deg": 0.1, "translation_error_mm": 1},
              {"ok": False, "success": False, "confidence": 0.1, "rotation_error_deg": 90, "translation_error_mm": 900}]
    out = aggregate_pose(trials)
    assert out["n_ok"] == 2 and out["ok_wrong"] == 1
    assert out["ok_wrong_rate"] == pytest.approx(0.25) and out["ok_precision"] == pytest.approx(0.5)
    (row,) = out["reliability"]  # both ok poses in the 0.9-1.0 bin
    assert row["count"] == 2 and row["accuracy"] == pytest.approx(0.5) and row["confidence"] == pytest.approx(0.935)


def test_twin_poses_put_a_twin_where_the_pose_put_the_feature():
    from recognition.localisation.twins import twin_poses
    from scenes.features import Cylinder, Plane
    from scenes.model import Object, SceneModel

    a = Plane("a", centre=np.array([0.0, 0.0, 1.0]), normal=np.array([1.0, 0, 0]), u_axis=np.array([0, 1.0, 0]),
              half_size=(0.5, 1.0))
    b = Plane("b", centre=np.array([5.0, 2.0, 1.0]), normal=np.array([-1.0, 0, 0]), u_axis=np.array([0, 1.0, 0]),
              half_size=(1.0, 0.5))  # the same rectangle turned: a twin
    c = Plane("c", centre=np.array([9.0, 0.0, 1.0]), normal=np.array([1.0, 0, 0]), u_axis=np.array([0, 1.0, 0]),
              half_size=(0.5, 2.0))  # another size: not a twin
    pipe = Cylinder("p", centre=np.array([0.0, 3.0, 1.0]), axis=np.array([0, 0, 1.0]), radius=0.1, length=2.0)
    model = SceneModel("m", (Object("o1", "cabinet", (a, b, c)), Object("o2", "pipe_run", (pipe,))))
    T = np.eye(4)
    T[:3, 3] = [2.0, 0.5, 1.2]  # the sensor, 2 m in front of a
    poses = twin_poses(T, ["a"], model)
    assert len(poses) == 3  # a turned about its normal, b both ways; nothing for c or the pipe
    p_a = np.linalg.inv(T) @ np.r_[a.centre, 1.0]  # where the sensor sees a's centre
    seen = [P @ p_a for P in poses]
    assert sum(np.allclose(x[:3], b.centre) for x in seen) == 2 and sum(np.allclose(x[:3], a.centre) for x in seen) == 1
    for P in poses:  # rigid, and the sensor faces the twin as it faced a
        assert np.allclose(P[:3, :3] @ P[:3, :3].T, np.eye(3)) and np.isclose(np.linalg.det(P[:3, :3]), 1.0)
    (flip,) = twin_poses(T, ["p"], model)  # the pipe's own other axis direction: turned 180 deg about its centre
    p_c = np.linalg.inv(T) @ np.r_[pipe.centre, 1.0]
    assert np.allclose((flip @ p_c)[:3], pipe.centre) and rotation_error_deg(flip[:3, :3], T[:3, :3]) == \
        pytest.approx(180.0)



def test_the_pose_icp_started_from_is_an_alternative_once_icp_carried_it_beyond_the_tolerance(monkeypatch):
    """ICP that leaves its hypothesis' closed-form pose by more than twice the success tolerance (the two cannot
    both be right) makes that pose an alternative the data must separate the final one from
    (``_start_alternative``); within it, nothing."""
    import importlib

    loc = importlib.import_module("recognition.localisation.localise")
    desc = SimpleNamespace(patches=tuple(SimpleNamespace(id=i, n_pixels=400, points=np.array([[0.0, 0.0, 2.0]]))
                                         for i in range(3)))
    fractions = {0: {0: 0.9, 1: 0.8, 2: 0.7}, 1: {0: 0.5, 1: 0.8, 2: 0.6}}  # final, start
    monkeypatch.setattr(loc, "predict", lambda sim, sensor, T, stride: SimpleNamespace(T=T))
    monkeypatch.setattr(loc, "agreement",
                        lambda d, s, pred, v: (0.7 - 0.2 * pred.T[0, 3], fractions[int(pred.T[0, 3])]))
    scan = SimpleNamespace(sensor=None)
    params, timing = LocaliseParams(), {"verification": 0.0}
    final, start = np.eye(4), np.eye(4)
    start[0, 3] = 1.0  # 1 m away: beyond 1 % of the 2 m range
    alt = loc._start_alternative(desc, scan, None, start, final, fractions[0], params, timing, loc._pose_scale(desc))
    d, se = agreement_separation(desc, fractions[0], fractions[1], params.separation_leave_out)
    assert np.array_equal(alt.T_world_sensor, start) and alt.agreement == pytest.approx(0.5)
    assert alt.separation == pytest.approx(d / se)
    near = np.eye(4)
    near[0, 3] = 0.03  # 30 mm: within twice 1 % of 2 m
    assert loc._start_alternative(desc, scan, None, near, final, fractions[0], params, timing,
                                  loc._pose_scale(desc)) is None


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0, 1), min_size=3, max_size=8), st.lists(st.floats(0, 1), min_size=3, max_size=8),
       st.integers(0, 2))
def test_leaving_out_the_patches_that_favour_a_most_is_the_separation_without_them(fa, fb, leave_out):
    n = min(len(fa), len(fb))
    desc = _desc([50 + 37 * i for i in range(n)])
    a, b = dict(enumerate(fa[:n])), dict(enumerate(fb[:n]))
    w = {k: 50 + 37 * k for k in range(n)}  # sizes: ties go to the larger patch
    ranked = sorted(range(n), key=lambda k: (-(a[k] - b[k]), -w[k], k))
    kept = set(ranked[leave_out:])
    expected = agreement_separation(desc, {k: a[k] for k in kept}, {k: b[k] for k in kept})
    assert agreement_separation(desc, a, b, leave_out) == pytest.approx(expected)
    # leaving a patch out never makes A look better (with two patches left to measure the spread)
    if n - leave_out >= 2:
        assert agreement_separation(desc, a, b, leave_out)[0] <= agreement_separation(desc, a, b)[0] + 1e-12


def test_one_patch_cannot_carry_the_preference_alone():
    """The per-patch agreements of the default suite's mock-up trial (``mockup-s1000-p0-v0``, as drawn at
    6df7b25) whose altered pipe ICP fitted by turning the pose 2.1 deg (0.70 of its pixels against 0.00, every
    other patch the same): separated by one standard error without leaving it out, a tie with it left out."""
    desc = _desc([261423, 25026, 10737, 2799, 1011, 729, 343, 290])
    final = {0: 1.0, 1: 0.70, 2: 1.0, 3: 0.05, 4: 0.0, 5: 1.0, 6: 0.25, 7: 1.0}
    start = {**final, 1: 0.0}
    d, se = agreement_separation(desc, final, start)
    assert d > 0 and 0.9 < d / se < 1.1
    assert agreement_separation(desc, final, start, 1) == (0.0, 0.0)
