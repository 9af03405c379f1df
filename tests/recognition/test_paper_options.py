"""The paper's unstated choices as options of PaperParams (issue 37), against closed forms: the "= 0" heuristic,
the eigenvalue sigma bound, and the patch's point subsample (how many, how chosen)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import norm

import recognition.classification.paper as paper
from recognition._synthetic import sample_patch
from recognition.classification import PaperParams, classify_patch
from recognition.classification.paper import _p_zero, paper_plausibilities, paper_subsample
from recognition.fitting import canonicalise, fit_quadric
from recognition.fitting.quadric import CanonicalQuadric


def test_defaults_are_todays_reading_and_choices_are_checked():
    p = PaperParams()
    assert (p.zero_rule, p.sigma_mode, p.max_points, p.subsample) == ("literal", "bauer_fike", 2000, "stride")
    for bad in ({"zero_rule": "exact"}, {"sigma_mode": "monte_carlo"}, {"subsample": "every"}, {"max_points": 9}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            PaperParams(**bad)


@pytest.mark.parametrize("z, literal, soft", [
    (0.0, 1.0, 1.0),
    (1.0, 2 * norm.sf(1.0), np.exp(-1 / 8)),      # 0.3173, 0.8825
    (-2.0, 2 * norm.sf(2.0), np.exp(-4 / 8)),     # 0.0455, 0.6065
    (3.0, 2 * norm.sf(3.0), np.exp(-9 / 8)),
])
def test_zero_rules_are_their_closed_forms(z, literal, soft):
    s = 0.02
    assert _p_zero(z * s, s, "literal") == pytest.approx(literal, rel=1e-9)
    assert _p_zero(z * s, s, "soft") == pytest.approx(soft, rel=1e-9)


def test_literal_zero_rule_is_uniform_for_an_exact_zero():
    """With x ~ N(0, sigma), 2 min(P(x>0), P(x<0)) is uniform on [0, 1]: a true primitive's "= 0" plausibility
    has median 1/2 under the literal rule, not 1."""
    x = np.random.default_rng(0).normal(size=20000)
    v = np.array([_p_zero(float(xi), 1.0, "literal") for xi in x])
    assert np.quantile(v, [0.25, 0.5, 0.75]) == pytest.approx([0.25, 0.5, 0.75], abs=0.02)


def _canonical(eigenvalues, c_cano, sigmas, rank, truncated):
    return CanonicalQuadric(eigenvalues=np.asarray(eigenvalues, float), axes=np.eye(3), centre=np.zeros(3),
                            c_cano=float(c_cano), cov=np.diag(np.square(sigmas)), sigma_mode="bauer_fike", rank=rank,
                            truncated=truncated, jacobian_n=np.zeros((4, 10)))


@pytest.mark.parametrize("rule", ["literal", "soft"])
def test_plausibilities_are_the_products_of_the_papers_conditions(monkeypatch, rule):
    c2 = _canonical([1.05, 0.95, 0.02], -4e-4, [0.05, 0.05, 0.02, 4e-4], 2, 2)
    c3 = _canonical([1.05, 0.95, -0.3], 1e-5, [0.05, 0.05, 0.1, 2e-5], 3, -1)
    monkeypatch.setattr(paper, "canonicalise", lambda fit, rank, sigma_mode: c2 if rank == 2 else c3)

    def zero(x, s):  # the two heuristics, written out
        return 2 * norm.sf(abs(x) / s) if rule == "literal" else np.exp(-((x / s) ** 2) / 8)

    pos = norm.cdf
    d = np.hypot(0.05, 0.05)
    cyl = pos(4e-4 / 4e-4) * zero(0.1, d) * pos(1.05 / 0.05) * pos(0.95 / 0.05) * zero(0.02, 0.02)
    sph = (pos(-1e-5 / 2e-5) * zero(0.1, d) * zero(1.25, np.hypot(0.05, 0.1)) * pos(1.05 / 0.05) * pos(0.95 / 0.05)
           * pos(-0.3 / 0.1))
    cone = zero(1e-5, 2e-5) * pos(1.05 / 0.05) * pos(0.95 / 0.05) * pos(0.3 / 0.1)
    got, _ = paper_plausibilities(None, PaperParams(zero_rule=rule))
    assert got == pytest.approx({"CYL": cyl, "SPH": sph, "CONE": cone}, rel=1e-9)


def _ellipsoid_fit(s: float):
    """A quadric fit of (3 x² + 2 y² + z² = 1) / norm with covariance s² I in its normalised frame."""
    pts = sample_patch("sphere", np.random.default_rng(0), "mockup_laser", n_max=500)
    fit = fit_quadric(pts.points, pts.sigma)
    p = np.array([3.0, 2.0, 1.0, 0, 0, 0, 0, 0, 0, -1.0])
    return dataclasses.replace(fit, params_n=p / np.linalg.norm(p), cov_n=s**2 * np.eye(10)), np.linalg.norm(p)


def test_bauer_fike_bound_is_the_frobenius_expectation_of_the_perturbation():
    """sigma_l = sqrt(E ||dA||_F²) = sqrt(sum var(a_ii) + 2 sum var(a_ij)) = 3 s for every eigenvalue when the six
    A-parameters have variance s²; first order gives s (axis-aligned eigenvectors). After the normalisation
    y = l / m, m = (l1 + l2) / 2: var(y_i) = sigma_l² / m² * sum_j N_ij² with N = I - y (e1 + e2)' / 2."""
    s = 1e-3
    fit, k = _ellipsoid_fit(s)
    bf = canonicalise(fit, rank=3, sigma_mode="bauer_fike")
    fo = canonicalise(fit, rank=3, sigma_mode="first_order")
    m = 2.5 / k
    y = np.array([1.2, 0.8, 0.4])
    assert bf.eigenvalues == pytest.approx(y)
    n2 = np.array([(1 - y[0] / 2) ** 2 + (y[0] / 2) ** 2, (y[1] / 2) ** 2 + (1 - y[1] / 2) ** 2,
                   2 * (y[2] / 2) ** 2 + 1])  # 0.52, 0.52, 1.08
    assert bf.sigmas[:3] == pytest.approx(3 * s / m * np.sqrt(n2), rel=1e-9)
    assert fo.sigmas[:3] == pytest.approx(s / m * np.sqrt(n2), rel=1e-6)


def test_subsample_stride_and_random():
    assert paper_subsample(50, 100, "random").tolist() == list(range(50))  # a small patch: every point
    stride = paper_subsample(1001, 11, "stride")
    assert stride.tolist() == list(range(0, 1001, 100))  # round(linspace(0, n - 1, m))
    r = paper_subsample(1000, 300, "random")
    assert len(np.unique(r)) == 300 and np.all(np.diff(r) > 0) and r.min() >= 0 and r.max() < 1000
    assert np.array_equal(r, paper_subsample(1000, 300, "random"))  # seeded by the patch size
    assert not np.array_equal(r, paper_subsample(1000, 300, "stride"))
    with pytest.raises(ValueError, match="subsample"):
        paper_subsample(1000, 300, "every")


def test_fewer_points_give_larger_canonical_sigmas_as_one_over_sqrt_n():
    """The canonical parameters' sigmas grow as sqrt(N_full / N) when the fit sees N of the patch's points: so
    ``max_points`` moves every "= 0" plausibility. 400 against 1600 points of one noisy cylinder: ratio 2."""
    p = sample_patch("cylinder", np.random.default_rng(3), "mockup_laser", n_max=6400, noise_scale=2.0)
    sig = {}
    for m in (400, 1600):
        idx = paper_subsample(len(p.points), m, "random")
        c = canonicalise(fit_quadric(p.points[idx], p.sigma[idx]), rank=2, sigma_mode="first_order")
        sig[m] = c.sigmas
    assert sig[400][3] / sig[1600][3] == pytest.approx(2.0, rel=0.25)  # C_cano
    assert sig[400][2] / sig[1600][2] == pytest.approx(2.0, rel=0.25)  # the truncated eigenvalue


def test_options_reach_the_classifier():
    p = sample_patch("cylinder", np.random.default_rng(4), "mockup_laser", n_max=3000)
    base = classify_patch(p.points, p.sigma, method="paper")
    same = classify_patch(p.points, p.sigma, method="paper", params=PaperParams(subsample="stride", max_points=2000))
    assert base.plausibilities == same.plausibilities
    other = classify_patch(p.points, p.sigma, method="paper", params=PaperParams(subsample="random"))
    assert other.plausibilities != base.plausibilities
