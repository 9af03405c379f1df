"""Sensor models and configuration files: ray conventions, presets, validation messages."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scenes.config import ConfigError
from sensors.config import load_sensor, noise_from_dict, noise_to_dict, preset_names, sensor_from_yaml
from sensors.models import PinholeCamera, ScanningLaser

PINHOLE = """
schema: sensor/1
name: test
pinhole: {width: 64, height: 48, fov_deg: 60, min_range: 0.2, max_range: 5}
"""


def test_pinhole_rays_follow_opencv_convention():
    cam = PinholeCamera.from_fov(5, 3, 90.0, min_range=0.1, max_range=10.0)
    d = cam.ray_directions()
    assert d.shape == (3, 5, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)
    np.testing.assert_allclose(d[1, 2], [0, 0, 1])  # centre pixel on the optical axis
    assert d[1, 4, 0] > 0 and d[2, 2, 1] > 0  # x right, y down
    np.testing.assert_allclose(cam.K, [[2.5, 0, 2], [0, 2.5, 1], [0, 0, 1]])
    assert cam.fov_deg[0] == pytest.approx(90.0)
    uv = cam.project(d.reshape(-1, 3) * 3.0)
    np.testing.assert_allclose(uv, np.stack(np.meshgrid(np.arange(5), np.arange(3)), -1).reshape(-1, 2), atol=1e-12)


def test_laser_grid():
    laser = ScanningLaser(4, 2, math.radians(-40), math.radians(40), math.radians(-10), math.radians(30), 0.5, 20)
    az, el = laser.angles()
    np.testing.assert_allclose(np.degrees(az), [-30, -10, 10, 30])
    np.testing.assert_allclose(np.degrees(el), [20, 0])  # row 0 at the top
    d = laser.ray_directions()
    assert d.shape == (2, 4, 3)
    np.testing.assert_allclose(d[1, 2], [math.sin(math.radians(10)), 0, math.cos(math.radians(10))])
    assert d[0, 0, 1] < 0  # looking up is -y
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0)


@pytest.mark.parametrize("name", ["mockup_laser", "factory_scanner", "kinect_like", "stereo_like"])
def test_presets_load(name):
    cfg = load_sensor(name)
    assert cfg.name == name and cfg.noise.enabled and cfg.T_world_sensor is not None
    assert name in preset_names()
    assert noise_from_dict(noise_to_dict(cfg.noise)) == cfg.noise


def test_preset_figures():
    assert load_sensor("mockup_laser").noise.sigma(1.0) == pytest.approx(2e-4)
    assert 1e-3 <= load_sensor("factory_scanner").noise.sigma(5.0) <= 2e-3
    k = load_sensor("kinect_like")
    assert k.model.shape == (480, 640)
    assert k.model.fov_deg == pytest.approx((57.0, 43.0))
    assert (k.model.min_range, k.model.max_range) == (0.5, 4.5)
    assert k.noise.sigma(2.0, 1.0, 1.0) == pytest.approx(0.0012 + 0.0019 * 1.6**2)
    assert k.noise.sigma(2.0, 1.0, 0.8) == pytest.approx((0.0012 + 0.0019 * 1.2**2) / 0.8)  # along the ray
    assert k.noise.correlation_area == 1.0  # the simulated Kinect's errors are independent
    s = load_sensor("stereo_like").noise
    assert s.matching_window_px == 7 and s.correlation_area == 49.0 and s.footprint == 1
    assert s.sigma(0.8) == pytest.approx(5e-4 + 1.6e-3 * 0.8**2)


@pytest.mark.parametrize("text, message", [
    (PINHOLE.replace("width: 64", "width: 0"), "pinhole.width: must be >= 1, got 0"),
    (PINHOLE.replace("fov_deg: 60", "fov_deg: 200"), "pinhole.fov_deg: must be < 180, got 200"),
    (PINHOLE.replace("fov_deg: 60", "fov_deg: [60, 180]"), r"pinhole.fov_deg\[1\]: must be < 180, got 180"),
    (PINHOLE.replace("max_range: 5", "max_range: 0.1"), "pinhole.max_range: must be > min_range"),
    (PINHOLE + "noise: {range: {model: laser}}\n", "noise.range.model: must be one of"),
    (PINHOLE + "noise: {specular: {chrome: 0.5}}\n", "noise.specular.chrome: unknown material"),
    (PINHOLE + "noise: {footprint: {rays: 0}}\n", "noise.footprint.rays: must be >= 1"),
    (PINHOLE + "bogus: 1\n", "unknown key"),
    (PINHOLE + "noise: {range: {matching_window_px: 0}}\n", "noise.range.matching_window_px: must be >= 1"),
    ("schema: sensor/1\nlaser: {n_azimuth: 0, n_elevation: 4, azimuth_deg: [-10, 10], elevation_deg: [-5, 5], "
     "max_range: 3}\n", "laser.n_azimuth: must be >= 1, got 0"),
    ("schema: sensor/1\nlaser: {n_azimuth: 4, n_elevation: 4, azimuth_deg: [10, -10], elevation_deg: [-5, 5], "
     "max_range: 3}\n", "laser.azimuth_deg: max must be > min"),
    ("schema: sensor/1\nname: x\n", "exactly one of the sections"),
])
def test_bad_sensor_files_give_clear_errors(text, message):
    with pytest.raises(ConfigError, match=message):
        sensor_from_yaml(text, "file.yaml")


def test_unknown_preset_and_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="unknown sensor preset 'nope'.*kinect_like"):
        load_sensor("nope")
    with pytest.raises(ConfigError, match="no such sensor file"):
        load_sensor(tmp_path / "missing.yaml")


def test_model_validation():
    with pytest.raises(ValueError, match="width must be >= 1"):
        PinholeCamera.from_fov(0, 10, 60.0, min_range=0.1, max_range=1.0)
    with pytest.raises(ValueError, match=r"fov_deg must be in \(0, 180\)"):
        PinholeCamera.from_fov(10, 10, 180.0, min_range=0.1, max_range=1.0)
    with pytest.raises(ValueError, match="n_elevation must be >= 1"):
        ScanningLaser(10, 0, -1, 1, -0.5, 0.5, 0.1, 5.0)


def test_pose_from_yaml():
    cfg = sensor_from_yaml(PINHOLE + "pose: {position: [0, -2, 1], look_at: [0, 0, 1]}\n")
    np.testing.assert_allclose(cfg.T_world_sensor[:3, 2], [0, 1, 0], atol=1e-12)
    T = np.eye(4)
    T[:3, 3] = [1, 2, 3]
    cfg2 = sensor_from_yaml(PINHOLE + f"pose: {{matrix: {T.tolist()}}}\n")
    np.testing.assert_array_equal(cfg2.T_world_sensor, T)
