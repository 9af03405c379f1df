"""Benchmark of the simulated sensor: time and memory per 640 x 480 scan.

``python -m harness.bench.sensors [--scene SCENE.yaml] [--sensor PRESET] [--viewpoint-seed N | --position X Y Z
--look-at X Y Z] [--repeats N] [--json OUT]``

Three configurations on one scene and viewpoint: noise off, the full noise model with a 1-ray beam,
and the full noise model with a 4-ray footprint. Reports the median wall time and median CPU time of
the calling thread (the machine is shared: CPU time is the steadier figure) over ``N`` repeats after a
warm-up, the time of the bare centre-ray cast, and the peak traced memory of one scan
(``tracemalloc``) relative to the size of the output arrays (``Scan`` + ``ScanTruth``).

Without ``--scene`` it scans :func:`demo_mockup`, a built-in 1:10 factory mock-up of about 40 geoms
(floor, walls, cabinets, pipe runs with elbows and reducers, tanks, a slanted pipe).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np

from scenes.features import Cone, Cylinder, Plane, Sphere, Torus, box_planes, cylinder_between
from scenes.geometry import look_at
from scenes.model import Object, SceneModel
from sensors.config import SensorConfig, load_sensor
from sensors.models import PinholeCamera, ScanningLaser
from sensors.simulate import Simulator


def demo_mockup() -> SceneModel:
    """A 1:10 factory mock-up (about 2 x 2 m, 40 geoms) used by the benchmark and tests."""
    objs: list[Object] = [
        Object("floor", "floor", (Plane("floor.top", centre=[0, 0, 0], normal=[0, 0, 1], u_axis=[1, 0, 0],
                                        half_size=(1.0, 1.0)),)),
        Object("wall_back", "wall", (Plane("wall_back.face", centre=[0, 1.0, 0.4], normal=[0, -1, 0],
                                           u_axis=[1, 0, 0], half_size=(1.0, 0.4)),)),
        Object("wall_left", "wall", (Plane("wall_left.face", centre=[-1.0, 0, 0.4], normal=[1, 0, 0],
                                           u_axis=[0, 1, 0], half_size=(1.0, 0.4)),)),
        Object("cab_a", "cabinet", box_planes("cab_a", [0.6, 0.7, 0.15], np.eye(3), (0.12, 0.08, 0.15))),
        Object("cab_b", "cabinet", box_planes("cab_b", [-0.7, -0.4, 0.1], np.eye(3), (0.1, 0.15, 0.1),
                                              material="painted")),
    ]
    # two horizontal pipe runs along x at different heights, each: straight, elbow, straight up
    for k, (y, z, r) in enumerate(((0.5, 0.25, 0.025), (0.3, 0.45, 0.02))):
        R = 0.06
        feats = [
            cylinder_between(f"run{k}.s0", [-0.9, y, z], [0.3, y, z], r, material="metal"),
            Torus(f"run{k}.e0", centre=[0.3, y, z + R], axis=[0, -1, 0], major_radius=R, minor_radius=r,
                  start=[0, 0, -1], sweep=math.pi / 2, material="metal"),
            cylinder_between(f"run{k}.s1", [0.3 + R, y, z + R], [0.3 + R, y, 0.75], r, material="metal"),
        ]
        # a reducer and a thinner section at the start of the run
        ha = math.atan((r - 0.6 * r) / 0.04)
        apex_d = 0.6 * r / math.tan(ha)
        feats.append(Cone(f"run{k}.red", apex=[-0.9 - 0.04 - apex_d, y, z], axis=[1, 0, 0], half_angle=ha,
                          start=apex_d, end=apex_d + 0.04))
        feats.append(cylinder_between(f"run{k}.s2", [-0.99, y, z], [-0.94, y, z], 0.6 * r))
        objs.append(Object(f"run{k}", "pipe_run", tuple(feats)))
    # a vertical pipe run with elbows towards the front
    objs.append(Object("run2", "pipe_run", (
        cylinder_between("run2.s0", [0.0, -0.2, 0.0], [0.0, -0.2, 0.35], 0.03),
        Torus("run2.e0", centre=[0.08, -0.2, 0.35], axis=[0, 1, 0], major_radius=0.08, minor_radius=0.03,
              start=[-1, 0, 0], sweep=math.pi / 2),
        cylinder_between("run2.s1", [0.08, -0.2, 0.43], [0.5, -0.2, 0.43], 0.03),
    )))
    # tanks: vertical cylinder with a hemispherical top, horizontal one with two ends
    objs.append(Object("tank_a", "tank", (
        Cylinder("tank_a.body", centre=[-0.45, 0.45, 0.2], axis=[0, 0, 1], radius=0.12, length=0.4),
        Sphere("tank_a.top", centre=[-0.45, 0.45, 0.4], radius=0.12, cap_axis=[0, 0, 1], cap_height=0.12),
    )))
    objs.append(Object("tank_b", "tank", (
        Cylinder("tank_b.body", centre=[0.45, 0.1, 0.15], axis=[1, 0, 0], radius=0.08, length=0.3),
        Sphere("tank_b.end0", centre=[0.3, 0.1, 0.15], radius=0.08, cap_axis=[-1, 0, 0], cap_height=0.08),
        Sphere("tank_b.end1", centre=[0.6, 0.1, 0.15], radius=0.08, cap_axis=[1, 0, 0], cap_height=0.08,
               material="glossy"),
    )))
    objs.append(Object("ball", "tank", (Sphere("ball.s", centre=[-0.2, -0.5, 0.06], radius=0.06),)))
    # a slanted pipe (like the paper's) and a few support posts
    objs.append(Object("slant", "pipe_run", (cylinder_between("slant.s", [-0.8, -0.1, 0.05], [0.2, 0.6, 0.65],
                                                               0.02),)))
    posts = [cylinder_between(f"posts.p{i}", [x, 0.8, 0.0], [x, 0.8, 0.6], 0.015) for i, x in
             enumerate((-0.6, -0.2, 0.2, 0.6))]
    objs.append(Object("posts", "structure", tuple(posts)))
    beams = [cylinder_between(f"beams.b{i}", [-0.8, yy, 0.7], [0.8, yy, 0.7], 0.012) for i, yy in
             enumerate((0.2, 0.6))]
    objs.append(Object("beams", "structure", tuple(beams)))
    return SceneModel("demo_mockup", tuple(objs))


DEMO_POSE = look_at([0.25, -1.25, 0.75], [0.0, 0.25, 0.25])


def with_resolution(config: SensorConfig, width: int, height: int) -> SensorConfig:
    """The same sensor (field of view, range limits) at another resolution."""
    m = config.model
    if isinstance(m, PinholeCamera):
        h, v = m.fov_deg
        model = PinholeCamera.from_fov(width, height, h, v, min_range=m.min_range, max_range=m.max_range)
    else:
        assert isinstance(m, ScanningLaser)
        model = replace(m, n_azimuth=width, n_elevation=height)
    return config.with_model(model)


def _outputs_nbytes(scan, truth) -> int:
    return sum(a.nbytes for a in (scan.range, scan.points, truth.sigma, truth.surface_id, truth.normals,
                                  truth.true_range, truth.flags))


def run_benchmark(scene: SceneModel, config: SensorConfig, T_world_sensor: np.ndarray, repeats: int = 10,
                  width: int = 640, height: int = 480, seed: int = 0) -> dict:
    """Time the three noise configurations; returns the figures as a plain dict (JSON-ready)."""
    config = with_resolution(config, width, height)
    t0 = time.perf_counter()
    sim = Simulator.from_scene(scene)
    compile_s = time.perf_counter() - t0
    full = config.noise if config.noise.enabled else replace(config.noise, enabled=True)
    cases = {"noise_off": full.off(), "full_noise": full.without("footprint"),
             "footprint_4": replace(full, footprint_rays=4)}
    out: dict = {"scene": scene.name, "sensor": config.name, "width": width, "height": height,
                 "n_geoms": int(sim.caster.model.ngeom), "repeats": repeats, "compile_s": compile_s, "cases": {}}
    rng = np.random.default_rng(seed)
    # bare centre-ray cast (tiled, with normals), for where the time goes
    sim.simulate(config.with_noise(cases["noise_off"]), T_world_sensor, rng)
    walls, cpus = [], []
    for _ in range(repeats):
        w, c = time.perf_counter(), time.thread_time()
        sim._cast(config.model, T_world_sensor[:3, 3].copy(), T_world_sensor[:3, :3])
        cpus.append(time.thread_time() - c)
        walls.append(time.perf_counter() - w)
    out["cast_only"] = {"median_ms": 1e3 * statistics.median(walls), "median_cpu_ms": 1e3 * statistics.median(cpus)}
    for name, noise in cases.items():
        cfg = config.with_noise(noise)
        sim.simulate(cfg, T_world_sensor, rng)  # warm-up: ray bundles are built and cached
        walls, cpus = [], []
        for _ in range(repeats):
            w, c = time.perf_counter(), time.thread_time()
            scan, truth = sim.simulate(cfg, T_world_sensor, rng)
            cpus.append(time.thread_time() - c)
            walls.append(time.perf_counter() - w)
        tracemalloc.start()
        scan, truth = sim.simulate(cfg, T_world_sensor, rng)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        size = _outputs_nbytes(scan, truth)
        out["cases"][name] = {
            "median_ms": 1e3 * statistics.median(walls), "min_ms": 1e3 * min(walls),
            "median_cpu_ms": 1e3 * statistics.median(cpus),
            "valid_fraction": float(scan.valid.mean()), "peak_mb": peak / 2**20, "outputs_mb": size / 2**20,
            "memory_ratio": peak / size, "footprint_rays": noise.footprint,
        }
    return out


def _table(res: dict) -> str:
    lines = [f"scene {res['scene']} ({res['n_geoms']} geoms), sensor {res['sensor']} at "
             f"{res['width']}x{res['height']}, "
             f"{res['repeats']} repeats; compile {res['compile_s'] * 1e3:.0f} ms; centre-ray cast alone "
             f"{res['cast_only']['median_ms']:.1f} ms (cpu {res['cast_only']['median_cpu_ms']:.1f} ms)",
             f"{'case':<14}{'median ms':>11}{'cpu ms':>9}{'min ms':>9}{'valid':>8}{'peak MB':>9}{'out MB':>8}"
             f"{'mem x':>7}"]
    for name, c in res["cases"].items():
        lines.append(f"{name:<14}{c['median_ms']:>11.1f}{c['median_cpu_ms']:>9.1f}{c['min_ms']:>9.1f}"
                     f"{c['valid_fraction']:>8.3f}{c['peak_mb']:>9.1f}{c['outputs_mb']:>8.1f}{c['memory_ratio']:>7.2f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m harness.bench.sensors", description=__doc__.splitlines()[0])
    p.add_argument("--scene", help="scene YAML (default: the built-in demo mock-up)")
    p.add_argument("--sensor", default="mockup_laser", help="preset name or sensor YAML (default mockup_laser)")
    p.add_argument("--position", type=float, nargs=3, metavar=("X", "Y", "Z"))
    p.add_argument("--look-at", type=float, nargs=3, metavar=("X", "Y", "Z"))
    p.add_argument("--viewpoint-seed", type=int, help="draw the pose with the viewpoint sampler (this seed)")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--json", type=Path, help="also write the figures to this JSON file")
    args = p.parse_args(argv)
    scene = SceneModel.load(args.scene) if args.scene else demo_mockup()
    config = load_sensor(args.sensor)
    if args.position is not None and args.look_at is not None:
        T = look_at(args.position, args.look_at)
    elif args.viewpoint_seed is not None:
        from sensors.viewpoints import sample_viewpoints

        sample = sample_viewpoints(Simulator.from_scene(scene), scene, with_resolution(config, args.width,
                                   args.height).model, 1, np.random.default_rng(args.viewpoint_seed))
        if not sample.viewpoints:
            p.error(f"no acceptable viewpoint in {sample.attempts} attempts")
        T = sample.viewpoints[0].T_world_sensor
    elif args.scene is None:
        T = DEMO_POSE
    elif config.T_world_sensor is not None:
        T = config.T_world_sensor
    else:
        p.error("give --position and --look-at for this scene")
    res = run_benchmark(scene, config, T, args.repeats, args.width, args.height)
    print(_table(res))
    if args.json:
        args.json.write_text(json.dumps(res, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
