"""``harness sense``: simulate one range scan of a scene and write it with its truth and pictures.

Writes ``DIR/scan.npz`` (scan + truth, :func:`sensors.io.save_npz`), ``DIR/points.ply`` (sensor frame),
``DIR/shaded.png`` (cosine-shaded range image), ``DIR/labels.png`` (truth surfaces) and ``DIR/scan.json``
(a summary: size, valid fraction, surfaces seen with pixel counts, timings).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from scenes.mjcf import export_mjcf
from scenes.model import SceneModel
from sensors.config import load_sensor, preset_names
from sensors.io import save_labels_png, save_npz, save_shaded_png, write_ply
from sensors.range_image import FLAG_NAMES
from sensors.simulate import Simulator
from sensors.viewpoints import ViewpointSpec, sample_viewpoints

NAME = "sense"
HELP = "simulate a range scan of a scene (scan + truth .npz, PLY, PNGs, JSON summary)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene YAML file")
    parser.add_argument("--sensor", required=True,
                        help=f"sensor preset ({', '.join(preset_names())}) or sensor YAML file")
    pose = parser.add_mutually_exclusive_group()
    pose.add_argument("--viewpoint-seed", type=int, metavar="N",
                      help="draw the viewpoint with this seed, as a suite does (default: 0)")
    pose.add_argument("--sensor-pose", action="store_true",
                      help="use the pose written in the sensor file instead of drawing one")
    pose.add_argument("--position", type=float, nargs=3, metavar=("X", "Y", "Z"), help="sensor position (m)")
    parser.add_argument("--look-at", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="point the sensor looks at (with --position)")
    parser.add_argument("--seed", type=int, required=True, help="noise seed")
    parser.add_argument("--no-noise", action="store_true", help="exact ranges (noise model off)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")


def run(args: argparse.Namespace) -> int:
    if (args.position is None) != (args.look_at is None):
        raise ValueError("--position and --look-at go together")
    config = load_sensor(args.sensor)
    if args.no_noise:
        config = config.with_noise(config.noise.off())
    scene = SceneModel.load(args.scene)
    t0 = time.perf_counter()
    sim = Simulator(export_mjcf(scene), scene=scene)
    compile_s = time.perf_counter() - t0
    viewpoint = None
    if args.position is not None:
        from scenes.geometry import look_at

        T = look_at(args.position, args.look_at)
    elif not args.sensor_pose:  # a sampled viewpoint sees the scene; a preset's pose fits one scene only
        args.viewpoint_seed = 0 if args.viewpoint_seed is None else args.viewpoint_seed
        sample = sample_viewpoints(sim, scene, config.model, 1, np.random.default_rng(args.viewpoint_seed),
                                   ViewpointSpec())
        if not sample.viewpoints:
            raise ValueError(f"no acceptable viewpoint found in {sample.attempts} attempts "
                             f"(rejected: {sample.rejected})")
        viewpoint = sample
        T = sample.viewpoints[0].T_world_sensor
    elif config.T_world_sensor is not None:
        T = config.T_world_sensor
    else:
        raise ValueError(f"sensor {config.name!r} has no pose in its file: leave out --sensor-pose to draw one")
    t1 = time.perf_counter()
    scan, truth = sim.simulate(config, T, np.random.default_rng(args.seed))
    scan_s = time.perf_counter() - t1

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    save_npz(out / "scan.npz", scan, truth)
    n_points = write_ply(out / "points.ply", scan.points)
    save_shaded_png(out / "shaded.png", scan)
    save_labels_png(out / "labels.png", truth.surface_id)
    counts = truth.surface_pixel_counts(scan.valid)
    summary = {
        "scene": scene.name, "sensor": config.name, "width": scan.shape[1], "height": scan.shape[0],
        "seed": args.seed, "viewpoint_seed": args.viewpoint_seed,
        "T_world_sensor": truth.T_world_sensor.tolist(),
        "noise_terms": list(config.noise.active_terms()),
        "valid_fraction": float(scan.valid.mean()), "n_points": n_points,
        "median_range_m": float(np.nanmedian(scan.range)) if n_points else None,
        "surfaces_seen": [{"index": i, "feature_id": truth.surfaces[i].feature_id, "part": truth.surfaces[i].part,
                           "truth_class": truth.surfaces[i].truth_class, "pixels": c} for i, c in counts.items()],
        "flags": {name: int(np.count_nonzero(truth.flags & bit)) for name, bit in FLAG_NAMES.items()},
        "time_s": {"compile": compile_s, "scan": scan_s},
    }
    if viewpoint is not None:
        summary["viewpoint"] = {"attempts": viewpoint.attempts, "rejected": viewpoint.rejected,
                                "rejection_rate": viewpoint.rejection_rate,
                                "target_feature": viewpoint.viewpoints[0].target_feature}
    (out / "scan.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    print(f"{config.name}: {scan.shape[1]}x{scan.shape[0]}, {100 * summary['valid_fraction']:.1f} % valid, "
          f"{len(counts)} surfaces seen, scan {1e3 * scan_s:.0f} ms -> {out}")
    return 0
