"""Pose from mixed correspondences: exact recovery, free DOF of degenerate configurations, covariance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from evaluation.pose import add_mm, pose_section, rotation_error_deg, translation_error_mm
from recognition.localisation import (
    AxisPair,
    PlanePair,
    PointPair,
    apply_left,
    estimate_pose,
    pose_hypotheses,
    residuals,
)


def _random_T(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.normal(size=3) * 3
    return T


class _Maker:
    """Exact correspondences for a known ``T_world_sensor``."""

    def __init__(self, T, sigma=1e-3):
        self.T, self.Ti, self.s = T, np.linalg.inv(T), sigma
        self.rng = np.random.default_rng(0)

    def s_vec(self, v):
        return self.Ti[:3, :3] @ v

    def s_pt(self, p):
        return self.Ti[:3, :3] @ p + self.Ti[:3, 3]

    def plane(self, n, d):
        n = np.asarray(n, float) / np.linalg.norm(n)
        c = n * d + np.cross(n, self.rng.normal(size=3))
        return PlanePair(self.s_vec(n), self.s_pt(c), n, float(d), self.s, self.s)

    def axis(self, a, p, flip=1, cone_along=None):
        a = np.asarray(a, float) / np.linalg.norm(a)
        p = np.asarray(p, float)
        q = p + self.rng.normal() * a
        if cone_along is not None:
            return AxisPair(self.s_vec(a), self.s_pt(p + cone_along * a), a, p, self.s, self.s, signed=True,
                            along_m=cone_along, sigma_along=self.s)
        return AxisPair(flip * self.s_vec(a), self.s_pt(q), a, p, self.s, self.s)

    def point(self, c):
        c = np.asarray(c, float)
        return PointPair(self.s_pt(c), c, self.s)


@pytest.mark.parametrize("seed", range(5))
def test_exact_mixed_correspondences_recover_random_transform(seed):
    T = _random_T(seed)
    m = _Maker(T)
    pairs = [m.plane([0, 0, 1], 0.3), m.axis([1, 0.2, 0], [0, 1, 2], flip=-1), m.point([1, -1, 0.5]),
             m.axis([0, 1, 0.3], [2, 0, 1], cone_along=0.4)]
    est = estimate_pose(pairs)
    assert est.ok and est.free_dof == 0
    assert np.abs(est.T_world_sensor - T).max() < 1e-9
    assert est.cov_T_world_sensor.shape == (6, 6)


@pytest.mark.parametrize("name, expected", [
    ("one cylinder", 2), ("one plane", 3), ("one sphere", 3), ("two parallel cylinders", 1),
    ("two planes", 1), ("cylinder + parallel plane", 1), ("cylinder + perpendicular plane", 1),
    ("three planes", 0), ("two non-parallel cylinders", 0), ("three spheres", 0), ("cone", 1),
])
def test_degenerate_configurations_report_free_dof(name, expected):
    T = _random_T(11)
    m = _Maker(T)
    cases = {
        "one cylinder": [m.axis([1, 0, 0], [0, 1, 2])],
        "one plane": [m.plane([0, 0, 1], 1)],
        "one sphere": [m.point([0, 0, 0])],
        "two parallel cylinders": [m.axis([1, 0, 0], [0, 1, 2]), m.axis([1, 0, 0], [0, 2, 2])],
        "two planes": [m.plane([1, 0, 0], 1), m.plane([0, 1, 0], 2)],
        "cylinder + parallel plane": [m.axis([1, 0, 0], [0, 1, 2]), m.plane([0, 0, 1], 1)],
        "cylinder + perpendicular plane": [m.axis([1, 0, 0], [0, 1, 2]), m.plane([1, 0, 0], 1)],
        "three planes": [m.plane([1, 0, 0], 1), m.plane([0, 1, 0], 2), m.plane([0, 0.3, 1], 0.5)],
        "two non-parallel cylinders": [m.axis([1, 0, 0], [0, 1, 2]), m.axis([0, 1, 0.2], [1, 0, 0])],
        "three spheres": [m.point([0, 0, 0]), m.point([1, 0, 0]), m.point([0, 1, 1])],
        "cone": [m.axis([0, 0, 1], [1, 1, 0], cone_along=0.5)],
    }
    hyps = pose_hypotheses(cases[name])
    assert hyps and hyps[0].ok
    assert hyps[0].free_dof == expected, name
    # whatever is free, the estimate satisfies the constraints exactly
    assert hyps[0].cost < 1e-12


def test_no_pairs_is_a_result_not_an_exception():
    est = estimate_pose([])
    assert not est.ok and "no correspondences" in est.reason


def test_cylinder_axis_sign_ambiguity_is_resolved():
    T = _random_T(3)
    m = _Maker(T)
    pairs = [m.axis([1, 0, 0], [0, 1, 2], flip=-1), m.axis([0.3, 1, 0], [1, 0, 0]), m.plane([0.2, 0.5, 1], 0.2)]
    hyps = pose_hypotheses(pairs)
    assert len(hyps) == 1  # the plane normal orients both axes: one sign assignment survives
    est = hyps[0]
    assert np.abs(est.T_world_sensor - T).max() < 1e-9
    assert est.signs[0] == -1


def test_jacobian_matches_finite_differences():
    T = _random_T(5)
    m = _Maker(T)
    pairs = [m.plane([0, 0, 1], 0.3), m.axis([1, 0.2, 0], [0, 1, 2]), m.point([1, -1, 0.5]),
             m.axis([0, 1, 0.3], [2, 0, 1], cone_along=0.4)]
    T0 = apply_left(T, np.array([0.01, -0.02, 0.015, 0.01, 0.02, -0.01]))
    signs = (1,) * len(pairs)
    r0, J = residuals(pairs, signs, T0)
    eps = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        r1, _ = residuals(pairs, signs, apply_left(T0, d))
        assert np.allclose((r1 - r0) / eps, J[:, k], rtol=1e-4, atol=1e-2)


def test_covariance_matches_monte_carlo():
    """The 6x6 covariance (left perturbation, world frame) predicts the scatter of noisy estimates."""
    T = _random_T(7)
    sigma = 1e-3
    rng = np.random.default_rng(1)
    base = _Maker(T, sigma)
    clean = [base.plane([0, 0, 1], 0.3), base.plane([1, 0, 0.1], -0.5), base.axis([0, 1, 0.2], [1, 0, 1])]
    est0 = estimate_pose(clean)
    errs = []
    for _ in range(200):
        noisy = []
        for p in clean:
            if isinstance(p, PlanePair):
                n = p.n_s + rng.normal(scale=sigma, size=3)
                n /= np.linalg.norm(n)
                noisy.append(PlanePair(n, p.c_s + p.n_s * rng.normal(scale=sigma), p.n_m, p.d_m, sigma, sigma))
            else:
                a = p.a_s + rng.normal(scale=sigma, size=3)
                a /= np.linalg.norm(a)
                q = p.p_s + rng.normal(scale=sigma, size=3)
                noisy.append(AxisPair(a, q, p.a_m, p.p_m, sigma, sigma))
        e = estimate_pose(noisy).T_world_sensor
        dR = e[:3, :3] @ T[:3, :3].T
        w = Rotation.from_matrix(dR).as_rotvec()
        v = e[:3, 3] - dR @ T[:3, 3]
        errs.append(np.concatenate([w, v]))
    emp = np.cov(np.array(errs).T)
    pred = est0.cov_T_world_sensor
    ratio = np.sqrt(np.diag(emp) / np.diag(pred))
    assert np.all((ratio > 0.6) & (ratio < 1.6)), ratio


def test_metrics_truth_as_estimate_scores_perfectly():
    T = _random_T(2)
    pts = np.random.default_rng(0).normal(size=(50, 3))
    assert rotation_error_deg(T[:3, :3], T[:3, :3]) == pytest.approx(0.0, abs=1e-5)  # arccos near 1
    assert translation_error_mm(T[:3, 3], T[:3, 3]) == 0.0
    assert add_mm(T[:3, :3], T[:3, 3], T[:3, :3], T[:3, 3], pts) == 0.0
    R90 = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    assert rotation_error_deg(R90, np.eye(3)) == pytest.approx(90.0)
    assert translation_error_mm([0, 0, 0.001], [0, 0, 0]) == pytest.approx(1.0)


def test_pose_section_handles_failure_and_success():
    from recognition.localisation import PoseResult

    T = _random_T(4)
    ok = PoseResult(True, "", T, T, np.eye(6), 0, 0.9, (), 3, 10, None, {})
    sec = pose_section(ok, T, 2.0, True, np.zeros((4, 3)))
    assert sec["success"] and sec["rotation_error_deg"] < 1e-6 and sec["initial"]["success"]
    bad = PoseResult(False, "no hypothesis", None, None, None, 6, 0.0, (), 0, 5, None, {})
    sec = pose_section(bad, T, 2.0, True, None)
    assert not sec["success"] and sec["rotation_error_deg"] is None and sec["initial"]["success"] is False
    with pytest.raises(ValueError, match="shape"):
        rotation_error_deg(np.eye(2), np.eye(3))


def test_many_unsigned_axes_do_not_blow_up():
    """Sign assignments follow from the pairs' mutual angles (linear), not from 2^n enumeration: 24 pipes."""
    import time

    T = _random_T(7)
    m = _Maker(T)
    rng = np.random.default_rng(3)
    pairs = [m.plane([0, 0, 1], 0.0), m.plane([1, 0, 0], -2.0)]
    for k in range(24):
        a = np.eye(3)[k % 3] + 0.3 * np.eye(3)[(k + 1) % 3]
        pairs.append(m.axis(a, rng.normal(size=3), flip=-1 if k % 2 else 1))
    t0 = time.process_time()
    est = estimate_pose(pairs)
    assert time.process_time() - t0 < 2.0
    assert est.ok and est.free_dof == 0
    assert rotation_error_deg(est.T_world_sensor[:3, :3], T[:3, :3]) < 1e-3


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 5)), min_size=1, max_size=12), st.randoms())
def test_equal_fits_are_ordered_by_the_tie_rule_whatever_the_rounding(items, rnd):
    """Costs that agree up to rounding (here 1e-12 of the cost, as two floating-point paths give) are ordered by
    the tie-break, so a permuted, re-rounded input gives the same order."""
    from recognition.localisation.pose import sorted_with_ties

    costs = [0.5 + 0.25 * c for c, _ in items]
    base = [(c, k, i) for i, (c, (_, k)) in enumerate(zip(costs, items, strict=True))]
    jitter = [(c * (1 + rnd.uniform(-1e-12, 1e-12)), k, i) for c, k, i in base]
    rnd.shuffle(jitter)
    key = dict(cost=lambda x: x[0], tiebreak=lambda x: (x[1], x[2]))
    assert [x[2] for x in sorted_with_ties(base, **key)] == [x[2] for x in sorted_with_ties(jitter, **key)]
