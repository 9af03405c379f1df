"""The noise model: configured sigma recovered from scans, each term switchable, mixed pixels, determinism."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from scenes.features import Cylinder, Plane
from scenes.geometry import look_at
from scenes.model import Object, SceneModel
from sensors.config import SensorConfig, load_sensor
from sensors.models import PinholeCamera
from sensors.noise import TERMS, NoiseModel
from sensors.range_image import FLAG_GRAZING, FLAG_MIXED, FLAG_OUTLIER, FLAG_SPECULAR
from sensors.simulate import Simulator

WALL = SceneModel("wall", (Object("wall", "wall", (
    Plane("wall.face", centre=[0, 0, 0], normal=[0, -1, 0], u_axis=[1, 0, 0], half_size=(200, 200)),)),))


@pytest.fixture(scope="module")
def wall_sim() -> Simulator:
    return Simulator.from_scene(WALL)


def wall_pose(distance: float, incidence_deg: float) -> np.ndarray:
    """Sensor looking at the wall's origin from ``distance`` with the given incidence (rotated about z)."""
    a = math.radians(incidence_deg)
    position = np.array([distance * math.sin(a), -distance * math.cos(a), 0.0])
    return look_at(position, [0, 0, 0])


def plane_geometry(sensor, T) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Independent reference: exact range, cos(incidence) and ray z per pixel for the wall y = 0."""
    d = sensor.ray_directions()
    dw = d @ T[:3, :3].T
    r = -T[1, 3] / dw[..., 1]
    return r, dw[..., 1], d[..., 2]  # wall normal (0, -1, 0): cos i = d_y


def residuals(sim, sensor, noise, distance, incidence, seed):
    T = wall_pose(distance, incidence)
    scan, truth = sim.simulate(SensorConfig(sensor, noise), T, np.random.default_rng(seed))
    r, cos_i, ray_z = plane_geometry(sensor, T)
    np.testing.assert_allclose(truth.true_range, r, rtol=1e-9)
    return (scan.range - r).ravel(), r.ravel(), cos_i.ravel(), ray_z.ravel()


NARROW = PinholeCamera.from_fov(120, 120, 4.0, min_range=0.1, max_range=30.0)


@pytest.mark.parametrize("preset, distances", [("mockup_laser", (0.5, 1.0, 2.0)),
                                               ("factory_scanner", (2.0, 8.0, 16.0))])
def test_ray_model_sigma_recovered_within_10_percent(wall_sim, preset, distances):
    configured = load_sensor(preset).noise.without("quantisation", "grazing", "footprint", "specular", "outliers")
    rows, ys = [], []
    for k, dist in enumerate(distances):
        for j, inc in enumerate((0.0, 35.0, 60.0)):
            res, r, cos_i, _ = residuals(wall_sim, NARROW, configured, dist, inc, seed=10 * k + j)
            w = res * cos_i  # (s0 + s2 r^2) z, z ~ N(0, 1)
            ys.append(np.sqrt(np.mean(w**2)))
            rows.append([1.0, np.sqrt(np.mean((r**2) ** 2))])
            # incidence dependence on its own: sigma * cos is independent of the angle
    s0, s2 = np.linalg.lstsq(np.array(rows), np.array(ys), rcond=None)[0]
    assert s0 == pytest.approx(configured.s0_m, rel=0.1)
    assert s2 == pytest.approx(configured.s2_per_m, rel=0.1)
    # and the per-image sigma ratio between 60 deg and head-on is 1 / cos 60 = 2 (within 10 %)
    res0, *_ = residuals(wall_sim, NARROW, configured, distances[1], 0.0, seed=99)
    res60, *_ = residuals(wall_sim, NARROW, configured, distances[1], 60.0, seed=98)
    assert np.std(res60) / np.std(res0) == pytest.approx(1 / math.cos(math.radians(60)), rel=0.1)


def test_kinect_axial_sigma_recovered_within_10_percent(wall_sim):
    cfg = load_sensor("kinect_like")
    noise = cfg.noise.without("quantisation", "grazing", "footprint", "specular", "outliers")
    rows, ys = [], []
    for k, dist in enumerate((0.8, 1.5, 2.5, 3.5)):
        res, r, cos_i, ray_z = residuals(wall_sim, NARROW, noise, dist, 0.0, seed=k)
        z = r * ray_z
        ys.append(np.sqrt(np.mean((res * ray_z) ** 2)))  # axial sigma
        rows.append([1.0, np.sqrt(np.mean((z - 0.4) ** 4))])
    s0, s2 = np.linalg.lstsq(np.array(rows), np.array(ys), rcond=None)[0]
    assert s0 == pytest.approx(0.0012, rel=0.1)
    assert s2 == pytest.approx(0.0019, rel=0.1)
    # oblique: the whole axial sigma (with Nguyen's incidence term) per pixel, reimplemented here
    for inc in (45.0, 70.0):
        res, r, cos_i, ray_z = residuals(wall_sim, NARROW, noise, 2.0, inc, seed=int(inc))
        z = r * ray_z
        theta = np.arccos(np.minimum(cos_i, 1.0))
        sz = 0.0012 + 0.0019 * (z - 0.4) ** 2 + 0.0001 / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2
        assert np.std(res * ray_z / sz) == pytest.approx(1.0, rel=0.05)
    # the model's own sigma is the same function (for the recognition core)
    np.testing.assert_allclose(noise.sigma(r, cos_i, ray_z), sz / ray_z, rtol=1e-12)


def test_noise_off_gives_exact_range(wall_sim):
    full = load_sensor("mockup_laser").noise
    for noise in (full.off(), full.without(*TERMS)):
        scan, truth = wall_sim.simulate(SensorConfig(NARROW, noise), wall_pose(1.0, 30.0), np.random.default_rng(1))
        assert scan.valid.all()
        np.testing.assert_array_equal(scan.range, truth.true_range)
        assert (truth.flags == 0).all()


def test_each_term_switches_off_alone(wall_sim):
    """With one term off, the other terms' draws are unchanged (one generator per term)."""
    full = replace(load_sensor("mockup_laser").noise, outlier_rate=0.01, grazing_start=math.radians(40),
                   grazing_end=math.radians(80))
    sensor = PinholeCamera.from_fov(80, 60, 20.0, min_range=0.1, max_range=30.0)
    T = wall_pose(1.5, 50.0)
    ref, ref_t = wall_sim.simulate(SensorConfig(sensor, full.without("footprint")), T, np.random.default_rng(3))
    for term, bit in (("outliers", FLAG_OUTLIER), ("grazing", FLAG_GRAZING)):
        scan, truth = wall_sim.simulate(SensorConfig(sensor, full.without("footprint", term)), T,
                                        np.random.default_rng(3))
        assert (ref_t.flags & bit).any() and not (truth.flags & bit).any()
        same = (ref_t.flags == truth.flags) & scan.valid & ref.valid
        assert same.mean() > 0.5
        np.testing.assert_array_equal(scan.range[same], ref.range[same])
    scan, truth = wall_sim.simulate(SensorConfig(sensor, full.without("footprint", "range")), T,
                                    np.random.default_rng(3))
    plain = scan.valid & (truth.flags == 0)
    q = full.quantisation_step
    np.testing.assert_allclose(scan.range[plain], np.round(truth.true_range[plain] / q) * q, rtol=0, atol=1e-15)


def test_quantisation_and_outlier_rate(wall_sim):
    noise = NoiseModel(quantisation_step=0.001, outlier_rate=0.05)
    scan, truth = wall_sim.simulate(SensorConfig(NARROW, noise), wall_pose(2.0, 20.0), np.random.default_rng(4))
    out = (truth.flags & FLAG_OUTLIER) > 0
    assert out.mean() == pytest.approx(0.05, abs=0.01)
    steps = scan.range[~out] / 0.001
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)
    assert np.all(np.abs(scan.range[~out] - truth.true_range[~out]) <= 0.0005 + 1e-12)
    assert np.all((scan.range[out] >= NARROW.min_range) & (scan.range[out] <= NARROW.max_range))
    inv = NoiseModel(quantisation_step=2.85e-3, quantisation_mode="inverse_depth")
    scan, truth = wall_sim.simulate(SensorConfig(NARROW, inv), wall_pose(2.0, 0.0), np.random.default_rng(4))
    inv_depth = 1.0 / scan.depth / 2.85e-3
    np.testing.assert_allclose(inv_depth, np.round(inv_depth), atol=1e-6)


def test_grazing_and_specular_dropouts():
    sc = SceneModel("g", (
        Object("floor", "floor", (Plane("floor.top", centre=[0, 0, 0], normal=[0, 0, 1], u_axis=[1, 0, 0],
                                        half_size=(30, 30)),)),
        Object("pipe", "pipe_run", (Cylinder("pipe.s", centre=[0, 3, 0.5], axis=[1, 0, 0], radius=0.4,
                                             length=6.0, material="metal"),)),
    ))
    sim = Simulator.from_scene(sc)
    sensor = PinholeCamera.from_fov(160, 120, 60.0, min_range=0.1, max_range=50.0)
    noise = NoiseModel(grazing_start=math.radians(70), grazing_end=math.radians(85),
                       specular_dropout=(("metal", 0.3),))
    T = look_at([0, -2, 1.0], [0, 3, 0.3])
    scan, truth = sim.simulate(SensorConfig(sensor, noise), T, np.random.default_rng(5))
    d = sensor.ray_directions()
    cos_i = -np.einsum("hwk,hwk->hw", truth.normals, d)
    theta = np.degrees(np.arccos(np.clip(cos_i, -1, 1)))
    graze = (truth.flags & FLAG_GRAZING) > 0
    assert graze.any()
    assert theta[graze].min() >= 70 - 1e-9
    high = (theta > 85) & (truth.surface_id >= 0)
    assert graze[high].all()
    spec = (truth.flags & FLAG_SPECULAR) > 0
    on_pipe = np.array([truth.surfaces[i].feature_id == "pipe.s" if i >= 0 else False
                        for i in truth.surface_id.ravel()]).reshape(truth.surface_id.shape)
    assert not spec[~on_pipe].any()
    assert spec[on_pipe].mean() == pytest.approx(0.3, abs=0.05)
    assert not scan.valid[spec | graze].any()


def test_mixed_pixels_only_at_depth_edges():
    near = Plane("near.face", centre=[0, -1.0, 0], normal=[0, -1, 0], u_axis=[1, 0, 0], half_size=(0.3, 0.3))
    far = Plane("far.face", centre=[0, 1.0, 0], normal=[0, -1, 0], u_axis=[1, 0, 0], half_size=(5, 5))
    sc = SceneModel("edge", (Object("near", "wall", (near,)), Object("far", "wall", (far,))))
    sim = Simulator.from_scene(sc)
    sensor = PinholeCamera.from_fov(120, 100, 40.0, min_range=0.1, max_range=10.0)
    T = look_at([0.1, -3.0, 0.05], [0.1, 0.0, 0.05])
    one, one_t = sim.simulate(SensorConfig(sensor, NoiseModel(footprint_rays=1)), T, np.random.default_rng(0))
    assert not (one_t.flags & FLAG_MIXED).any()
    np.testing.assert_array_equal(one.range, one_t.true_range)
    for k in (4, 7):
        scan, truth = sim.simulate(SensorConfig(sensor, NoiseModel(footprint_rays=k, footprint_radius_px=0.5)), T,
                                   np.random.default_rng(0))
        mixed = (truth.flags & FLAG_MIXED) > 0
        assert mixed.sum() > 20
        sid = truth.surface_id
        pad = np.pad(sid, 1, mode="edge")
        edge = np.zeros_like(mixed)
        for dv in (-1, 0, 1):
            for du in (-1, 0, 1):
                edge |= pad[1 + dv:1 + dv + sid.shape[0], 1 + du:1 + du + sid.shape[1]] != sid
        assert edge[mixed].all()  # only next to a depth edge
        # spurious points between the surfaces, elsewhere the exact range
        assert np.all((scan.range[mixed] > 2.0) & (scan.range[mixed] < np.nanmax(truth.true_range)))
        # elsewhere the beam average of a plane: the exact range up to the footprint's curvature bias
        np.testing.assert_allclose(scan.range[~mixed & scan.valid], truth.true_range[~mixed & scan.valid],
                                   rtol=1e-5)


def test_same_seed_bit_identical_and_seed_matters(wall_sim):
    cfg = SensorConfig(NARROW, load_sensor("mockup_laser").noise)
    T = wall_pose(1.0, 40.0)
    a, at = wall_sim.simulate(cfg, T, np.random.default_rng(7))
    b, bt = wall_sim.simulate(cfg, T, np.random.default_rng(7))
    c, _ = wall_sim.simulate(cfg, T, np.random.default_rng(8))
    for x, y in ((a.range, b.range), (a.points, b.points), (at.sigma, bt.sigma), (at.flags, bt.flags),
                 (at.normals, bt.normals), (at.surface_id, bt.surface_id)):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a.range, c.range, equal_nan=True)


def test_sigma_function_properties():
    n = NoiseModel(s0_m=1e-3, s2_per_m=2e-5, max_incidence=math.radians(80))
    assert n.sigma(5.0) == pytest.approx(1.5e-3)
    assert n.sigma(5.0, math.cos(math.radians(60))) == pytest.approx(3e-3)
    assert n.sigma(5.0, 0.0) == pytest.approx(1.5e-3 / math.cos(math.radians(80)))  # clipped at grazing
    assert np.all(NoiseModel().sigma(np.array([1.0, 2.0])) == 0)
    with pytest.raises(ValueError, match="unknown noise term"):
        n.without("bogus")
    with pytest.raises(ValueError, match="footprint_rays"):
        NoiseModel(footprint_rays=0)


@pytest.mark.parametrize("window", [1, 3, 7])
def test_matching_window_correlates_errors_and_keeps_sigma(wall_sim, window):
    """Errors averaged over a w x w matching window: per-pixel sigma unchanged, neighbour correlation of a
    box average (w - 1) / w, uncorrelated beyond the window."""
    noise = replace(load_sensor("stereo_like").noise.without("grazing", "specular", "outliers"),
                    matching_window_px=window)
    assert noise.correlation_area == window**2
    camera = PinholeCamera.from_fov(400, 400, 4.0, min_range=0.1, max_range=30.0)
    T = wall_pose(1.0, 0.0)
    scan, truth = wall_sim.simulate(SensorConfig(camera, noise), T, np.random.default_rng(7))
    r, cos_i, ray_z = plane_geometry(camera, T)
    z = (scan.range - r) / noise.sigma(r, cos_i, ray_z)  # unit normal per pixel
    inner = z[window:-window, window:-window]  # away from the reflected image border
    # (sampling spreads: about window / 400 for the correlations, 3 sigma allowed)
    assert np.std(inner) == pytest.approx(1.0, rel=0.05)
    lag1 = np.mean(inner[:, 1:] * inner[:, :-1]) / np.var(inner)
    assert lag1 == pytest.approx((window - 1) / window, abs=0.06)
    beyond = np.mean(inner[:, window:] * inner[:, :-window]) / np.var(inner)
    assert abs(beyond) < 0.06


def test_matching_window_must_be_a_positive_integer():
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="matching_window_px"):
            NoiseModel(matching_window_px=bad)
