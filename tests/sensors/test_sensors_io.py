"""Saving, loading and exporting scans; the ``harness sense`` command; viewpoints."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np
import pytest

from harness.bench.sensors import DEMO_POSE, demo_mockup
from harness.bench.sensors import main as bench_main
from scenes.features import Cylinder, Plane, Sphere
from scenes.model import Object, SceneModel
from sensors.config import load_sensor
from sensors.io import load_npz, read_ply_points, save_npz, shaded_image, write_ply
from sensors.models import PinholeCamera
from sensors.simulate import Simulator
from sensors.viewpoints import ViewpointSpec, sample_viewpoints

SMALL = PinholeCamera.from_fov(96, 72, 60.0, min_range=0.1, max_range=5.0)


@pytest.fixture(scope="module")
def demo():
    scene = demo_mockup()
    return scene, Simulator.from_scene(scene)


@pytest.fixture(scope="module")
def scanned(demo):
    _, sim = demo
    cfg = load_sensor("mockup_laser").with_model(SMALL)
    return sim.simulate(cfg, DEMO_POSE, np.random.default_rng(11))


def test_npz_round_trip_is_exact(tmp_path, scanned):
    scan, truth = scanned
    scan = replace(scan, pose_prior=truth.T_world_sensor + 1e-3)
    save_npz(tmp_path / "s.npz", scan, truth)
    back = load_npz(tmp_path / "s.npz")
    s2, t2 = back.scan, back.truth
    for a, b in ((scan.range, s2.range), (scan.points, s2.points), (scan.pose_prior, s2.pose_prior)):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    for name in ("T_world_sensor", "sigma", "surface_id", "normals", "true_range", "flags"):
        a, b = getattr(truth, name), getattr(t2, name)
        assert a.dtype == b.dtype and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    assert s2.sensor == scan.sensor and s2.noise == scan.noise
    assert t2.surfaces == truth.surfaces
    save_npz(tmp_path / "bare.npz", scanned[0], compress=True)
    bare = load_npz(tmp_path / "bare.npz")
    assert bare.truth is None and bare.scan.pose_prior is None
    np.testing.assert_array_equal(bare.scan.range, scanned[0].range)


def test_ply_and_shading(tmp_path, scanned):
    scan, truth = scanned
    n = write_ply(tmp_path / "p.ply", scan.points, truth.surface_id)
    assert n == scan.valid.sum() > 0
    np.testing.assert_array_equal(read_ply_points(tmp_path / "p.ply"), scan.points[scan.valid])
    shade = shaded_image(scan)
    assert shade.shape == scan.shape
    assert np.all((shade[scan.valid] >= 0) & (shade[scan.valid] <= 1))
    assert np.isnan(shade[~scan.valid]).all()


def test_scan_core_sees_no_truth(scanned):
    scan, _ = scanned
    assert set(vars(scan)) == {"range", "points", "sensor", "noise", "pose_prior"}
    assert scan.valid.dtype == bool and scan.depth.shape == scan.shape


def _scene_file(tmp_path):
    scene = SceneModel("tiny", (
        Object("floor", "floor", (Plane("floor.top", centre=[0, 0, 0], normal=[0, 0, 1], u_axis=[1, 0, 0],
                                        half_size=(2, 2)),)),
        Object("pipe", "pipe_run", (Cylinder("pipe.s", centre=[0, 0.5, 0.2], axis=[1, 0, 0], radius=0.1,
                                             length=1.5),)),
        Object("tank", "tank", (Sphere("tank.s", centre=[0.5, 0.0, 0.3], radius=0.2),)),
    ))
    path = tmp_path / "tiny.yaml"
    scene.save(path)
    sensor = tmp_path / "cam.yaml"
    sensor.write_text("schema: sensor/1\nname: cam\npinhole: {width: 80, height: 60, fov_deg: 60, min_range: 0.1, "
                      "max_range: 6}\nnoise: {range: {s0_m: 0.001}}\n")
    return path, sensor


def test_sense_command_writes_outputs(tmp_path):
    from harness.commands import sense

    scene, sensor = _scene_file(tmp_path)
    parser = argparse.ArgumentParser()
    sense.add_arguments(parser)
    args = parser.parse_args([str(scene), "--sensor", str(sensor), "--position", "0", "-2", "1", "--look-at",
                              "0", "0", "0.2", "--seed", "3", "--out", str(tmp_path / "out")])
    assert sense.run(args) == 0
    for name in ("scan.npz", "points.ply", "shaded.png", "labels.png", "scan.json"):
        assert (tmp_path / "out" / name).stat().st_size > 0
    summary = json.loads((tmp_path / "out" / "scan.json").read_text())
    assert summary["width"] == 80 and 0 < summary["valid_fraction"] <= 1
    assert {s["feature_id"] for s in summary["surfaces_seen"]} >= {"floor.top", "pipe.s", "tank.s"}
    assert load_npz(tmp_path / "out" / "scan.npz").truth is not None


def test_sense_command_errors(tmp_path, capsys):
    from harness.cli import main

    scene, sensor = _scene_file(tmp_path)
    base = [str(scene), "--seed", "1", "--out", str(tmp_path / "o")]
    assert main(["sense", *base, "--sensor", "no_such_preset", "--position", "0", "-2", "1", "--look-at",
                 "0", "0", "0"]) == 2
    assert "unknown sensor preset 'no_such_preset'" in capsys.readouterr().err
    assert main(["sense", *base, "--sensor", str(sensor), "--position", "0.5", "0", "0.3", "--look-at",
                 "0", "0", "0"]) == 2
    assert "inside the geometry of 'tank.s'" in capsys.readouterr().err
    assert main(["sense", *base, "--sensor", str(sensor), "--sensor-pose"]) == 2
    assert "has no pose in its file" in capsys.readouterr().err


def test_sense_without_a_pose_draws_a_viewpoint_that_sees_the_scene(tmp_path):
    from harness.cli import main

    scene = tmp_path / "bay.yaml"
    assert main(["scene", "generate", "--family", "factory", "--seed", "1000", "--out", str(scene)]) == 0
    assert main(["sense", str(scene), "--sensor", "factory_scanner", "--seed", "1", "--out", str(tmp_path / "o")]) == 0
    summary = json.loads((tmp_path / "o" / "scan.json").read_text())
    assert summary["viewpoint_seed"] == 0 and summary["viewpoint"]["target_feature"]
    assert sum(s["pixels"] >= 200 for s in summary["surfaces_seen"]) >= 4 and summary["valid_fraction"] > 0.3


def test_viewpoints_seeded_and_reject_poor_views(demo):
    scene, sim = demo
    spec = ViewpointSpec(min_surfaces=4, min_pixels=30, distance_m=(0.5, 1.5))
    a = sample_viewpoints(sim, scene, SMALL, 3, np.random.default_rng(5), spec)
    b = sample_viewpoints(sim, scene, SMALL, 3, np.random.default_rng(5), spec)
    assert len(a.viewpoints) == 3 and a.attempts == b.attempts and a.rejected == b.rejected
    for va, vb in zip(a.viewpoints, b.viewpoints, strict=True):
        np.testing.assert_array_equal(va.T_world_sensor, vb.T_world_sensor)
        assert len(va.surface_pixels) >= 4 and min(va.surface_pixels.values()) >= 30
        assert sim.clearance(va.T_world_sensor[:3, 3]) >= spec.clearance(SMALL)
    c = sample_viewpoints(sim, scene, SMALL, 3, np.random.default_rng(6), spec)
    assert not np.array_equal(a.viewpoints[0].T_world_sensor, c.viewpoints[0].T_world_sensor)
    strict = ViewpointSpec(min_surfaces=60, min_pixels=30, distance_m=(0.5, 1.5), max_attempts=5)
    none = sample_viewpoints(sim, scene, SMALL, 1, np.random.default_rng(5), strict)
    assert none.viewpoints == () and none.attempts == 5 and none.rejection_rate == 1.0
    assert none.rejected["too_few_surfaces"] + none.rejected["no_clearance"] + none.rejected["outside_bounds"] == 5


def test_bench_runs(tmp_path, capsys):
    assert bench_main(["--repeats", "1", "--width", "64", "--height", "48", "--json", str(tmp_path / "b.json")]) == 0
    res = json.loads((tmp_path / "b.json").read_text())
    assert set(res["cases"]) == {"noise_off", "full_noise", "footprint_4"}
    assert res["cases"]["footprint_4"]["footprint_rays"] == 4
    assert "median ms" in capsys.readouterr().out
