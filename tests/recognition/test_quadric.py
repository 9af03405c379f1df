"""Tests of the general quadric (recognition.fitting.quadric, .algebra): fit, canonical form, Jacobians, Monte
Carlo check of the covariance."""

from __future__ import annotations

import numpy as np
import pytest

from recognition._synthetic import random_rotation, sample_patch
from recognition.fitting import (
    QuadricFit,
    canonical_quantities,
    canonicalise,
    evaluate,
    fit_quadric,
    quadric_matrices,
    quadric_params,
)


def _exact_fit(params: np.ndarray) -> QuadricFit:
    """A QuadricFit holding given parameters in an identity normalisation (zero covariance)."""
    p = np.asarray(params, float) / np.linalg.norm(params)
    z = np.zeros((10, 10))
    return QuadricFit(params=p, cov=z, params_n=p, cov_n=z, mean=np.zeros(3), scale=1.0, n_points=0, chi2=0.0,
                      rms_m=0.0, rms_sigma=0.0, n_iter=0, ok=True)


def _cylinder_points(rng, centre, axis, r, n=400, arc=np.pi):
    e1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    th = rng.uniform(0, arc, n)
    h = rng.uniform(-2 * r, 2 * r, n)
    return centre + r * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2) + h[:, None] * axis


@pytest.mark.parametrize("seed", range(4))
def test_canonical_cylinder_sphere_cone_random_poses(seed):
    rng = np.random.default_rng(seed)
    Rm = random_rotation(rng)
    a = Rm[:, 2]
    c = rng.uniform(-2, 2, 3)
    r = rng.uniform(0.05, 0.5)
    # cylinder from noise-free points on half its circumference
    pts = _cylinder_points(rng, c, a, r)
    can = canonicalise(fit_quadric(pts, 1e-4), rank=2)
    np.testing.assert_allclose(can.eigenvalues, [1, 1, 0], atol=1e-6)
    assert can.c_cano < 0
    assert can.c_cano == pytest.approx(-r * r, rel=1e-6)
    assert abs(abs(can.axes[2] @ a) - 1) < 1e-8
    d = can.centre - c
    assert np.linalg.norm(d - (d @ a) * a) < 1e-6  # centre on the axis
    # sphere (exact parameters)
    A, B, C = np.eye(3), -2 * c, c @ c - r * r
    can = canonicalise(_exact_fit(-quadric_params(A, B, C)), rank=3)  # sign flipped on purpose
    np.testing.assert_allclose(can.eigenvalues, [1, 1, 1], atol=1e-9)
    assert can.c_cano == pytest.approx(-r * r, rel=1e-9)
    np.testing.assert_allclose(can.centre, c, atol=1e-9)
    # cone with apex c, axis a, half-angle alpha: (x-c)'(I - (1 + tan²) a a')(x-c) = 0
    alpha = rng.uniform(np.radians(5), np.radians(50))
    t2 = np.tan(alpha) ** 2
    A = np.eye(3) - (1 + t2) * np.outer(a, a)
    can = canonicalise(_exact_fit(quadric_params(A, -2 * A @ c, c @ A @ c)), rank=3)
    np.testing.assert_allclose(can.eigenvalues, [1, 1, -t2], atol=1e-9)
    assert can.c_cano == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(can.centre, c, atol=1e-8)
    assert abs(abs(can.axes[2] @ a) - 1) < 1e-9


def test_fit_recovers_exact_quadric_and_maps_back():
    rng = np.random.default_rng(3)
    pts = _cylinder_points(rng, np.array([3.0, -1.0, 5.0]), np.array([0.0, 0.6, 0.8]), 0.2)
    fit = fit_quadric(pts, 1e-3)
    assert fit.ok and fit.reason == ""
    f, g = evaluate(fit.params, pts)
    assert np.max(np.abs(f / np.linalg.norm(g, axis=1))) < 1e-8
    assert np.linalg.norm(fit.params) == pytest.approx(1.0)
    assert np.max(np.abs(fit.cov @ fit.params)) < 1e-12 + 1e-6 * np.max(np.abs(fit.cov))


def _fd_jacobian(fun, p, eps=1e-7):
    y0 = fun(p)
    J = np.zeros((len(y0), len(p)))
    for k in range(len(p)):
        dp = np.zeros(len(p))
        dp[k] = eps
        J[:, k] = (fun(p + dp) - fun(p - dp)) / (2 * eps)
    return J


@pytest.mark.parametrize("rank", [2, 3])
def test_jacobians_against_finite_differences(rank):
    rng = np.random.default_rng(7)
    Rm = random_rotation(rng)
    A = Rm @ np.diag([1.3, 0.9, 0.05 if rank == 2 else -0.4]) @ Rm.T
    p = quadric_params(A, rng.normal(size=3), -0.7)

    def raw(q):
        out = canonical_quantities(q, rank=rank)
        return np.append(out["eigenvalues"], out["c_cano"])

    J = canonical_quantities(p, rank=rank)["jacobian"]
    np.testing.assert_allclose(J, _fd_jacobian(raw, p), rtol=1e-5, atol=1e-6)

    # normalised (sign and scale) quantities from canonicalise
    def norm(q):
        c = canonicalise(_exact_fit(q), rank=rank)
        return np.append(c.eigenvalues, c.c_cano)

    pn = p / np.linalg.norm(p)
    Jn = canonicalise(_exact_fit(pn), rank=rank).jacobian_n
    np.testing.assert_allclose(Jn, _fd_jacobian(norm, pn), rtol=1e-5, atol=1e-6)


def test_matrices_round_trip():
    p = np.arange(1.0, 11.0)
    np.testing.assert_array_equal(quadric_params(*quadric_matrices(p)), p)


@pytest.mark.parametrize(
    ("points", "why"),
    [
        (np.zeros((5, 3)), "too few"),
        (np.c_[np.linspace(0, 1, 30), np.linspace(0, 2, 30), np.zeros(30)], "degenerate"),
        (np.c_[np.random.default_rng(0).uniform(size=(30, 2)), np.zeros(30)], "coplanar"),
        (np.where(np.arange(90).reshape(30, 3) == 4, np.nan, np.ones((30, 3))), "non-finite"),
    ],
)
def test_degenerate_fits_return_reason(points, why):
    fit = fit_quadric(points, 1e-3)
    assert not fit.ok and not fit
    assert why in fit.reason


def test_wrong_shape_raises():
    with pytest.raises(ValueError, match=r"expected points of shape \(N, 3\), got \(20, 2\)"):
        fit_quadric(np.zeros((20, 2)), 1e-3)
    with pytest.raises(ValueError, match="sigma"):
        fit_quadric(np.zeros((20, 3)), np.ones(3))


def _ellipsoid_patch(rng, n=1500):
    axes = np.array([0.20, 0.26, 0.33])
    v = rng.normal(size=(n * 3, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] < -0.2][:n]
    pts = v * axes + np.array([0.0, 0.0, 1.5])
    return pts


def _monte_carlo(clean, sigma, rng, draws, fn):
    u = clean / np.linalg.norm(clean, axis=1, keepdims=True)
    vals, preds = [], []
    for _ in range(draws):
        noisy = clean + (sigma * rng.normal(size=len(clean)))[:, None] * u
        v, s = fn(noisy)
        vals.append(v)
        preds.append(s)
    return np.std(vals, axis=0, ddof=1), np.median(preds, axis=0)


@pytest.mark.parametrize("shape", ["cylinder", "cone", "ellipsoid"])
def test_monte_carlo_sigma_of_canonical_parameters(shape):
    """Predicted sigmas of C_cano and eigenvalues within 20 % of the spread over 200 noise draws."""
    rng = np.random.default_rng(11)
    if shape == "ellipsoid":
        clean = _ellipsoid_patch(rng)
        sigma = np.full(len(clean), 1e-3)
        rank, idx = 3, [0, 1, 2, 3]
    else:
        p = sample_patch(shape, rng, "factory_scanner", noise_scale=0.0, n_max=1500)
        clean, sigma = p.points, p.sigma
        rank, idx = (2, [2, 3]) if shape == "cylinder" else (3, [2, 3])

    def fn(noisy):
        c = canonicalise(fit_quadric(noisy, sigma), rank=rank, sigma_mode="first_order")
        return np.append(c.eigenvalues, c.c_cano)[idx], c.sigmas[idx]

    mc, pred = _monte_carlo(clean, sigma, rng, 200, fn)
    ratio = pred / mc
    assert np.all(np.abs(ratio - 1) < 0.2), f"{shape}: predicted/MC sigma ratios {ratio}"


def test_bauer_fike_bounds_first_order():
    rng = np.random.default_rng(5)
    p = sample_patch("cone", rng, "mockup_laser", n_max=1000)
    fit = fit_quadric(p.points, p.sigma)
    fo = canonicalise(fit, rank=3, sigma_mode="first_order")
    bf = canonicalise(fit, rank=3, sigma_mode="bauer_fike")
    assert np.all(bf.sigmas[:3] >= 0.99 * fo.sigmas[:3])
    assert bf.c_cano == fo.c_cano
    assert bf.sigma_mode == "bauer_fike"
    with pytest.raises(ValueError, match="sigma_mode"):
        canonicalise(fit, sigma_mode="exact")


def test_automatic_rank_truncates_cylinders_only():
    rng = np.random.default_rng(8)
    cyl = sample_patch("cylinder", rng, "mockup_laser", n_max=1500)
    cone = sample_patch("cone", rng, "mockup_laser", n_max=1500)
    assert canonicalise(fit_quadric(cyl.points, cyl.sigma)).rank == 2
    c = canonicalise(fit_quadric(cone.points, cone.sigma))
    if np.degrees(cone.truth["half_angle"]) > 10:
        assert c.rank == 3


def test_gradient_scatter_from_moments_equals_the_explicit_sum():
    # taubin_fit forms sum w G'G from the 4x4 moments of (y, 1): the same matrix as the explicit sum
    from recognition.fitting.algebra import MONOMIAL_GRADIENT, design_matrices

    y = np.random.default_rng(0).normal(size=(50, 3))
    w = np.random.default_rng(1).uniform(0.5, 2.0, 50)
    _, G = design_matrices(y)
    explicit = np.einsum("kn,kni,knj->ij", np.broadcast_to(w, (3, 50)), G, G)
    Y = np.column_stack([y, np.ones(50)])
    from_moments = np.einsum("kmi,mn,knj->ij", MONOMIAL_GRADIENT, (Y * w[:, None]).T @ Y, MONOMIAL_GRADIENT)
    np.testing.assert_allclose(from_moments, explicit, rtol=1e-12, atol=1e-12)


def test_the_basis_and_gradient_by_rows_equal_those_by_points():
    """One monomial basis and one gradient: the row layout (3, N) the segmenter's batched fits use gives the
    same numbers, bit for bit, as the point layout (N, 3)."""
    from recognition.fitting import gradient, monomials

    x = np.random.default_rng(3).normal(size=(200, 3))
    p = np.random.default_rng(4).normal(size=10)
    np.testing.assert_array_equal(monomials(x.T.copy(), axis=0), monomials(x).T)
    np.testing.assert_array_equal(gradient(p[:, None], x.T.copy(), axis=0), gradient(p, x).T)
    A, B, _ = quadric_matrices(p)
    np.testing.assert_allclose(gradient(p, x), 2.0 * x @ A + B, rtol=1e-12, atol=1e-12)  # evaluate()'s product


def test_the_normalisation_map_gives_the_same_surface_in_the_input_frame():
    """``p_x = L p_y`` for ``y = (x - mean) / scale``: the quadric takes the same values at the same points."""
    from recognition.fitting import monomials, normalisation_map

    rng = np.random.default_rng(5)
    x = rng.normal(size=(100, 3)) * 2.0 + [1.0, -2.0, 4.0]
    mean, scale = x.mean(axis=0), 1.7
    p_y = rng.normal(size=10)
    np.testing.assert_allclose(monomials(x) @ (normalisation_map(mean, scale) @ p_y),
                               monomials((x - mean) / scale) @ p_y, rtol=1e-10, atol=1e-10)
