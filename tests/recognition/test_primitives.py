"""Tests of the dedicated fits (recognition.fitting): round trips, degenerate inputs, Monte Carlo covariance,
radius bias."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from recognition import fitting
from recognition._synthetic import sample_patch
from recognition.fitting import fit_cone, fit_cylinder, fit_plane, fit_sphere, fit_torus
from recognition.fitting.cylinder import _fail_cylinder
from recognition.fitting.torus import _torus_fun, _torus_retract


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


FITS = [fit_plane, fit_cylinder, fit_sphere, fit_cone, fit_torus]


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
    fit = {"plane": fit_plane, "cylinder": fit_cylinder, "sphere": fit_sphere, "cone": fit_cone,
           "torus": fit_torus}[kind]
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
        ("torus", lambda f, t: (f.minor_radius, f.minor_radius_sigma)),
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


# ---------------------------------------------------------------------------------------------------------
# range-space refit with the beam footprint (issue 14)


def _footprint_cylinder_scan(rng, radius=0.08, dist=5.0, pixel_rad=2.2e-3, sigma=1.5e-3, k=4, fp_px=0.5):
    """A horizontal cylinder (axis along x) at ``dist`` metres in front of a sensor at the origin looking along
    +z, scanned on an angular grid; each return is the mean range of a centre ray and ``k - 1`` sub-rays on a
    circle of ``fp_px`` pixels (as the simulator's footprint), plus Gaussian noise along the ray. Pixels
    whose sub-rays do not all hit the cylinder are dropped. Returns points, sigma, sub-rays (k, N, 3)."""
    half = np.arcsin(radius / dist)
    el = np.arange(-half, half, pixel_rad)
    az = np.arange(-0.15, 0.15, pixel_rad)
    A, E = np.meshgrid(az, el)
    ang = 2 * np.pi * np.arange(k - 1) / (k - 1)
    offs = np.concatenate([[[0.0, 0.0]], fp_px * np.stack([np.cos(ang), np.sin(ang)], axis=1)])
    dirs = []
    for du, dv in offs:
        a, e = A.ravel() + du * pixel_rad, E.ravel() + dv * pixel_rad
        dirs.append(np.stack([np.cos(e) * np.sin(a), -np.sin(e), np.cos(e) * np.cos(a)], axis=1))
    dirs = np.stack(dirs)
    c = np.array([0.0, 0.0, dist])  # axis through c along x: distance to it in the (y, z) plane
    vy, vz = dirs[..., 1], dirs[..., 2]
    aa = vy * vy + vz * vz
    bb = -(vz * c[2])
    cc = c[2] ** 2 - radius**2
    disc = bb * bb - aa * cc
    with np.errstate(invalid="ignore"):
        t = (-bb - np.sqrt(disc)) / aa
    hit = np.all(disc > 0, axis=0)
    meas = np.mean(t[:, hit], axis=0) + sigma * rng.standard_normal(int(hit.sum()))
    pts = meas[:, None] * dirs[0, hit]
    return pts, np.full(len(pts), sigma), dirs[:, hit]


def test_refit_along_rays_removes_footprint_bias():
    from recognition.fitting import refit_along_rays

    rel_geo, rel_ray, z = [], [], []
    for seed in range(4):
        pts, sig, rays = _footprint_cylinder_scan(np.random.default_rng(seed))
        geo = fit_cylinder(pts, sig)
        ray = refit_along_rays(geo, pts, sig, rays)
        assert isinstance(ray, type(geo)) and ray.ok and ray.n_points == len(pts)
        rel_geo.append(geo.radius / 0.08 - 1)
        rel_ray.append(ray.radius / 0.08 - 1)
        z.append((ray.radius - 0.08) / ray.radius_sigma)
    # the geometric fit of footprint-averaged returns is biased low (about -1 %), the range-space refit not
    assert np.median(rel_geo) < -0.004
    assert abs(np.median(rel_ray)) < 0.002
    assert np.all(np.abs(z) < 3.5)


def test_refit_along_rays_sphere_and_passthrough():
    from recognition.fitting import refit_along_rays

    rng = np.random.default_rng(3)
    c, R = np.array([0.1, -0.05, 2.0]), 0.15
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d[d @ (-c / np.linalg.norm(c)) > 0.3]  # the side facing the sensor
    true = c + R * d
    rays = true / np.linalg.norm(true, axis=1, keepdims=True)
    pts = true + 2e-4 * rng.standard_normal(len(true))[:, None] * rays
    sig = np.full(len(pts), 2e-4)
    geo = fit_sphere(pts, sig)
    ray = refit_along_rays(geo, pts, sig)  # centre rays only (no footprint)
    assert ray.ok and abs(ray.radius - R) < 4 * ray.radius_sigma + 1e-6
    assert np.allclose(ray.centre, c, atol=1e-3)
    plane = fit_plane(pts, sig)
    assert refit_along_rays(plane, pts, sig) is plane


def test_trimmed_chi2_caps_outliers():
    from recognition.fitting import TRIM_SIGMA, trimmed_chi2

    r = np.array([0.5, -1.0, 100.0, -50.0])
    assert trimmed_chi2(r) == pytest.approx(0.25 + 1.0 + 2 * TRIM_SIGMA**2)
    rng = np.random.default_rng(0)
    p = sample_patch("cylinder", rng, "factory_scanner")
    f = fit_cylinder(p.points, p.sigma)
    assert f.chi2_trim <= f.chi2 and f.chi2_trim == pytest.approx(f.chi2, rel=0.05)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("preset", ["mockup_laser", "factory_scanner"])
def test_torus_noise_free_round_trip(seed, preset):
    """A pipe elbow's bend and pipe radii, axis and centre, from its visible points alone (normals
    estimated from the points: the fit is not given the true ones)."""
    p = sample_patch("torus", np.random.default_rng(seed), preset, noise_scale=0.0)
    f = fit_torus(p.points, p.sigma)
    t = p.truth
    assert f.ok, f.reason
    assert f.major_radius == pytest.approx(t["major"], rel=1e-6)
    assert f.minor_radius == pytest.approx(t["minor"], rel=1e-6)
    assert _angle(f.axis, t["axis"]) < 1e-6
    np.testing.assert_allclose(f.centre, t["centre"], atol=1e-6 * t["major"])
    assert 0 < f.sweep <= np.radians(90) + 1e-9
    assert f.rms_m < 1e-8


def test_torus_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    p = sample_patch("torus", rng, "factory_scanner")
    state = (p.truth["centre"] + 0.01, p.truth["axis"], p.truth["major"] * 1.1, p.truth["minor"] * 0.9)
    r, J = _torus_fun(state, p.points, p.sigma)
    eps = 1e-7
    for k in range(7):
        step = np.zeros(7)
        step[k] = eps
        rp = _torus_fun(_torus_retract(state, step), p.points, p.sigma)[0]
        rm = _torus_fun(_torus_retract(state, -step), p.points, p.sigma)[0]
        np.testing.assert_allclose(J[:, k], (rp - rm) / (2 * eps), rtol=1e-4, atol=1e-4 * np.abs(J[:, k]).max())


@pytest.mark.parametrize("seed", range(3))
def test_straight_tube_is_no_elbow(seed):
    """A cylinder is a torus of infinite bend radius: the fit either finds no bend or a bend radius far
    beyond an elbow's, never a tight one."""
    p = sample_patch("cylinder", np.random.default_rng(seed), "factory_scanner")
    f = fit_torus(p.points, p.sigma)
    assert (not f.ok and f.reason) or f.major_radius > 10 * f.minor_radius


def test_torus_refuses_a_bad_viewpoint_shape():
    p = sample_patch("torus", np.random.default_rng(0), "mockup_laser")
    with pytest.raises(ValueError, match="viewpoint"):
        fit_torus(p.points, p.sigma, viewpoint=np.zeros(2))


def test_torus_major_radius_sigma_is_the_first_order_one():
    """The bend radius's predicted sigma matches the spread of the linearised estimate (one Gauss-Newton
    step from the truth) within 20 % over 200 draws. The full fit spreads 1.3x wider on this patch (a 48 deg
    arc): the bend radius trades off nonlinearly with the centre, so the reported sigma is first-order."""
    rng = np.random.default_rng(21)
    p = sample_patch("torus", rng, "factory_scanner", noise_scale=0.0, n_max=1500)
    u = p.points / np.linalg.norm(p.points, axis=1, keepdims=True)
    truth = (p.truth["centre"], p.truth["axis"], p.truth["major"], p.truth["minor"])
    steps, preds = [], []
    for _ in range(200):
        noisy = p.points + (p.sigma * rng.normal(size=len(p.points)))[:, None] * u
        r, J = _torus_fun(truth, noisy, p.sigma)
        steps.append(-np.linalg.lstsq(J, r, rcond=None)[0][5])
        if len(preds) < 20:
            preds.append(fit_torus(noisy, p.sigma).major_radius_sigma)
    ratio = np.median(preds) / np.std(steps, ddof=1)
    assert abs(ratio - 1) < 0.2, f"bend radius: predicted/linearised MC = {ratio:.3f}"


def test_bend_test_tells_an_elbow_from_a_straight_tube():
    """Bending a fitted cylinder's axis predicts a large chi² decrease on an elbow, with a bend radius of the
    elbow's order, and next to none on a straight tube."""
    p = sample_patch("torus", np.random.default_rng(2), "factory_scanner")
    gain, bend = fitting.bend_test(fit_cylinder(p.points, p.sigma), p.points, p.sigma)
    assert gain > 100 and 0.3 * p.truth["major"] < bend < 3 * p.truth["major"]
    p = sample_patch("cylinder", np.random.default_rng(2), "factory_scanner")
    gain, bend = fitting.bend_test(fit_cylinder(p.points, p.sigma), p.points, p.sigma)
    assert gain < 2 * np.log(len(p.points))
    assert fitting.bend_test(_fail_cylinder(10, "x"), p.points, p.sigma) == (0.0, np.inf)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(8, 300), shape=st.sampled_from(["cube", "line", "plane", "blob"]))
def test_torus_fit_never_raises_on_odd_point_sets(seed, n, shape):
    """Point sets that are no tube (scattered, nearly collinear, planar, a tiny blob) give a fit or a reason."""
    g = np.random.default_rng(seed)
    if shape == "cube":
        pts = g.uniform(-1, 1, (n, 3)) + [0, 0, 3]
    elif shape == "line":
        pts = np.outer(g.uniform(0, 1, n), [1, 2, 3]) + [0, 0, 3] + g.normal(0, 1e-6, (n, 3))
    elif shape == "plane":
        pts = np.c_[g.uniform(-1, 1, (n, 2)), np.zeros(n)] + [0, 0, 2]
    else:
        pts = g.normal(0, 1e-3, (n, 3)) + [0, 0, 1]
    f = fit_torus(pts, 1e-3)
    assert isinstance(f.ok, bool) and (f.ok or f.reason)
    if f.ok:
        assert f.major_radius > f.minor_radius > 0 and np.isfinite(f.cov).all()


def test_both_plane_fits_give_one_plane_fit_type():
    """The dedicated (weighted) plane and the segmenter's plain total-least-squares plane are the same
    :class:`PlaneFit`, ``normal . x = offset`` with the normal facing the sensor."""
    from recognition.fitting import PlaneFit, fit_plane_lsq

    rng = np.random.default_rng(7)
    x = np.column_stack([rng.uniform(-1, 1, (300, 2)), np.full(300, 3.0) + rng.normal(0, 1e-3, 300)])
    for fit in (fit_plane(x, np.full(300, 1e-3)), fit_plane_lsq(x, np.full(300, 1e-3))):
        assert isinstance(fit, PlaneFit) and fit.ok
        np.testing.assert_allclose(fit.normal, [0, 0, -1], atol=1e-2)
        assert fit.offset == pytest.approx(-3.0, abs=1e-3)
        np.testing.assert_allclose(fit.params[6:], [*fit.normal, -fit.offset])
        assert fit.rms_sigma == pytest.approx(1.0, rel=0.2)
