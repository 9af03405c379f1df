"""Tests of recognition.primitives: round trips, degenerate inputs, Monte Carlo covariance, radius bias."""

from __future__ import annotations

import numpy as np
import pytest

from recognition._synthetic import sample_patch
from recognition.primitives import fit_cone, fit_cylinder, fit_plane, fit_sphere


def _angle(u, v):
    return float(np.arctan2(np.linalg.norm(np.cross(u, v)), abs(u @ v)))


@pytest.mark.parametrize("seed", range(3))
def test_noise_free_round_trip(seed):
    rng = np.random.default_rng(seed)
    p = sample_patch("plane", rng, "factory_scanner", noise_scale=0.0)
    f = fit_plane(p.points, p.sigma)
    assert f.ok and _angle(f.normal, p.truth["normal"]) < 1e-9
    assert abs(f.offset - p.truth["offset"] * np.sign(f.normal @ p.truth["normal"])) < 1e-9
    p = sample_patch("cylinder", rng, "factory_scanner", noise_scale=0.0)
    f = fit_cylinder(p.points, p.sigma)
    assert f.ok and f.radius == pytest.approx(p.truth["radius"], rel=1e-7)
    assert _angle(f.axis, p.truth["axis"]) < 1e-7
    d = f.point - p.truth["centre"]
    assert np.linalg.norm(d - (d @ f.axis) * f.axis) < 1e-7
    assert f.length <= p.truth["length"] + 1e-9
    p = sample_patch("sphere", rng, "factory_scanner", noise_scale=0.0)
    f = fit_sphere(p.points, p.sigma)
    assert f.ok and f.radius == pytest.approx(p.truth["radius"], rel=1e-7)
    np.testing.assert_allclose(f.centre, p.truth["centre"], atol=1e-7)
    p = sample_patch("cone", rng, "factory_scanner", noise_scale=0.0)
    f = fit_cone(p.points, p.sigma)
    assert f.ok and f.half_angle == pytest.approx(p.truth["half_angle"], abs=1e-7)
    assert f.axis @ p.truth["axis"] > 0.999999
    np.testing.assert_allclose(f.apex, p.truth["apex"], atol=1e-6)


def test_cone_nests_cylinder():
    rng = np.random.default_rng(4)
    p = sample_patch("cylinder", rng, "factory_scanner")
    cyl = fit_cylinder(p.points, p.sigma)
    cone = fit_cone(p.points, p.sigma, init=cyl)
    assert cone.ok and cone.chi2 <= cyl.chi2 * (1 + 1e-9)
    assert cone.half_angle < 3 * cone.half_angle_sigma + 1e-3


FITS = [fit_plane, fit_cylinder, fit_sphere, fit_cone]


@pytest.mark.parametrize("fit", FITS)
@pytest.mark.parametrize(
    ("points", "why"),
    [
        (np.zeros((2, 3)), "too few"),
        (np.full((30, 3), np.nan), "non-finite"),
        (np.c_[np.linspace(0, 1, 30), np.linspace(0, 2, 30), np.zeros(30)], ""),
    ],
)
def test_degenerate_inputs_give_reason_not_exception(fit, points, why):
    f = fit(points, 1e-3)
    assert not f.ok and not f
    assert why in f.reason and f.reason


@pytest.mark.parametrize("fit", [fit_cylinder, fit_sphere])
def test_planar_points_do_not_raise(fit):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (200, 2)), np.zeros(200)] + np.array([0, 0, 3.0])
    f = fit(pts, 1e-3)
    assert isinstance(f.ok, bool) and (f.ok or f.reason)


@pytest.mark.parametrize("fit", FITS)
def test_wrong_shapes_raise(fit):
    with pytest.raises(ValueError, match=r"expected points of shape \(N, 3\), got \(10, 2\)"):
        fit(np.zeros((10, 2)), 1e-3)
    with pytest.raises(ValueError, match="sigma"):
        fit(np.zeros((10, 3)), np.ones(4))


def _mc(kind, preset, seed, draws, extract, **fit_kw):
    rng = np.random.default_rng(seed)
    p = sample_patch(kind, rng, preset, noise_scale=0.0, n_max=1500)
    u = p.points / np.linalg.norm(p.points, axis=1, keepdims=True)
    fit = {"plane": fit_plane, "cylinder": fit_cylinder, "sphere": fit_sphere, "cone": fit_cone}[kind]
    vals, preds = [], []
    for _ in range(draws):
        noisy = p.points + (p.sigma * rng.normal(size=len(p.points)))[:, None] * u
        f = fit(noisy, p.sigma, **fit_kw)
        v, s = extract(f, p.truth)
        vals.append(v)
        preds.append(s)
    return np.asarray(vals), float(np.median(preds))


@pytest.mark.parametrize(
    ("kind", "extract"),
    [
        ("cylinder", lambda f, t: (f.radius, f.radius_sigma)),
        ("sphere", lambda f, t: (f.radius, f.radius_sigma)),
        ("cone", lambda f, t: (f.half_angle, f.half_angle_sigma)),
    ],
)
def test_monte_carlo_sigma_of_parameters(kind, extract):
    """Predicted sigma within 20 % of the spread over 200 noise draws (DESIGN 9 item 10)."""
    vals, pred = _mc(kind, "factory_scanner", 21, 200, extract)
    ratio = pred / np.std(vals, ddof=1)
    assert abs(ratio - 1) < 0.2, f"{kind}: predicted/MC = {ratio:.3f}"


def test_monte_carlo_sigma_of_plane_normal_angle():
    vals, pred = _mc("plane", "factory_scanner", 22, 200, lambda f, t: (f.normal, f.normal_sigma_rad))
    mean = vals.mean(axis=0)
    mean /= np.linalg.norm(mean)
    rms_angle = np.sqrt(np.mean([_angle(v, mean) ** 2 for v in vals]))
    assert abs(pred / rms_angle - 1) < 0.2, f"plane normal: predicted/MC = {pred / rms_angle:.3f}"


def _radius_bias(preset, n, seed):
    rng = np.random.default_rng(seed)
    rel = []
    for _ in range(n):
        p = sample_patch("cylinder", rng, preset)
        rel.append(fit_cylinder(p.points, p.sigma).radius / p.truth["radius"] - 1)
    return np.asarray(rel)


def test_radius_bias_small_at_factory_noise():
    rel = _radius_bias("factory_scanner", 30, 5)
    # measured: mean about -0.05 %, far below the prototype's 0.2-0.3 %
    assert abs(np.median(rel)) < 1e-3
    assert abs(np.mean(rel)) < 2e-3


@pytest.mark.slow
def test_radius_bias_reported_at_kinect_noise():
    rel = _radius_bias("kinect_like", 100, 6)
    # one-sided patches with sigma/r up to ~0.5: the fit is biased low (median about -1.5 %, see report)
    assert -0.05 < np.median(rel) < 0.01
