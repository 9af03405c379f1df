"""Benchmark of localisation (matching + pose + verification + ICP) against the simulator's truth.

``python -m harness.bench.pose [--views N] [--groups mockup,factory_bay,kinect]`` scans N viewpoints of the
perturbed mock-up (``mockup_laser``) and factory bay (``factory_scanner``; ``kinect``: the bay with
``kinect_like`` under 4 m, as in the default suite), describes each scan, localises it with no pose prior
and prints per group: the success rate over the trials whose truth constrains all
6 DOF and that no twin pose explains as well (:func:`evaluation.pose.constrained_view`), median/p90 rotation
and translation errors before and after ICP, and the time per frame of matching + pose + verification + ICP
(and of the final prediction).
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np


def _stats(values):
    v = np.array([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if len(v) == 0:
        return "n/a"
    return f"median {np.median(v):.4g}, p90 {np.percentile(v, 90):.4g}"


def main(argv: list[str] | None = None) -> int:
    from evaluation.pose import changed_features, constrained_view, pose_section
    from harness.suite import suite_from_dict
    from harness.trial import prepare_scene, sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import describe
    from recognition.localisation import localise
    from sensors.simulate import Simulator

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=10, help="viewpoints per perturbation seed and group")
    ap.add_argument("--seeds", type=int, default=2, help="perturbation seeds per group")
    ap.add_argument("--groups", default="mockup,factory_bay", help="comma-separated: mockup, factory_bay, kinect")
    ap.add_argument("--suite-seed", type=int, default=11)
    args = ap.parse_args(argv)
    known = {"mockup": {"scene": "mockup", "sensor": "mockup_laser"},
             "factory_bay": {"scene": "factory_bay", "sensor": "factory_scanner"},
             "kinect": {"scene": "factory_bay", "sensor": "kinect_like", "max_range": 4.0}}
    names = args.groups.split(",")
    unknown = [g for g in names if g not in known]
    if unknown:
        ap.error(f"unknown group(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    groups = [{**known[g], "perturbation": f"{known[g]['scene']}_perturbation",
               "perturbation_seeds": list(range(args.seeds)), "viewpoints": args.views, "noise_seeds": [0]}
              for g in names]
    suite = suite_from_dict({"schema": "suite/1", "name": "bench_pose", "seed": args.suite_seed,
                             "methods": {"core": {}}, "groups": groups})
    rows: dict[str, list[dict]] = {}
    sims: dict[str, Simulator] = {}
    for spec in suite.trials:
        p = prepare_scene(spec, None)
        cfg = sensor_for(spec)
        views = trial_viewpoints(spec, p, cfg)
        if not views.viewpoints:
            continue
        scan, truth = trial_scan(spec, p, cfg, views.viewpoints[0].T_world_sensor)
        desc = describe(scan)
        if spec.scene not in sims:
            sims[spec.scene] = Simulator.from_scene(p.apriori)
        t0, c0 = time.perf_counter(), time.process_time()
        res = localise(desc, scan, p.apriori, model_simulator=sims[spec.scene])
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        med_range = float(np.nanmedian(truth.true_range))
        pts = scan.points[::8, ::8].reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        constrained, _ = constrained_view(truth, p.actual, p.apriori,
                                          functools.partial(p.predictor.predict, scan.sensor),
                                          changed_features(p.change_truth))
        sec = pose_section(res, truth.T_world_sensor, med_range, constrained, pts)
        t = res.timing_s
        sec["time_core_s"] = t["matching"] + t["pose"] + t["verification"] + t["icp"]
        sec["time_total_s"] = wall
        sec["cpu_total_s"] = cpu
        rows.setdefault(spec.group, []).append(sec)
        print(f"{spec.trial_id}: ok={sec['ok']} constrained={sec['constrained']} success={sec['success']} "
              f"R={sec['rotation_error_deg']} t={sec['translation_error_mm']} conf={sec['confidence']:.2f} "
              f"time={wall:.2f}s cpu={cpu:.2f}s {res.reason}", flush=True)
    for group, secs in rows.items():
        con = [s for s in secs if s["constrained"]]
        succ = [s for s in con if s["success"]]
        print(f"\n== {group}: {len(secs)} trials, {len(con)} constrain 6 DOF")
        if con:
            print(f"success (constrained): {len(succ)}/{len(con)} = {len(succ) / len(con):.1%}")
        print(f"success (all): {sum(s['success'] for s in secs)}/{len(secs)}")
        ok = [s for s in con if s["success"]]
        print("before ICP, rotation deg:", _stats([s["initial"]["rotation_error_deg"] for s in ok]))
        print("before ICP, translation mm:", _stats([s["initial"]["translation_error_mm"] for s in ok]))
        print("after ICP, rotation deg:", _stats([s["rotation_error_deg"] for s in ok]))
        print("after ICP, translation mm:", _stats([s["translation_error_mm"] for s in ok]))
        print("time matching+pose+verification+ICP s:", _stats([s["time_core_s"] for s in secs]))
        print("time incl. final full-res prediction s (wall):", _stats([s["time_total_s"] for s in secs]))
        print("time incl. final full-res prediction s (CPU):", _stats([s["cpu_total_s"] for s in secs]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
