"""Benchmark of the H-K segmentation alone: time per frame and Hoover correct detection on a suite's scans.

``python -m harness.bench.segmentation [--suite default] [--repeat 3] [--groups mockup,...] [--limit N]
[--steps] [--json OUT]`` simulates each trial's scan as ``harness bench`` does, then segments it ``--repeat``
times in this one process, with the numerical libraries on one thread as in the runner's workers. Per group and
overall it prints the median and p90 over frames of the best-of-repeats time per frame: process time (the
machine may be shared) and wall time. Beside them: the correct detection rate at T = 0.8 over truth regions of
200 pixels or more, averaged over frames, of the segmenter's own labels (``seg.``) and of the description's
(``desc.``: after the classifier has merged touching patches that one primitive explains, untimed; the figure
``summary.json`` reports), and a SHA-1 of the segmenter's label images, so that a change made for speed can show
it left every label alone. ``--steps`` adds where the time goes: the process time of each step of
:func:`recognition.segmentation.segment` in the fastest repeat, per frame median and mean over frames.
``--json`` also writes all of it, per frame and per group.
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import numpy as np


def _mean(values: list[float | None]) -> float | None:
    rates = [x for x in values if x is not None]
    return float(np.mean(rates)) if rates else None


def _stats(cpu: list[float], wall: list[float], cd: list[float | None], cd_desc: list[float | None]) -> dict:
    return {"n": len(cpu), "cpu_median_s": float(np.median(cpu)), "cpu_p90_s": float(np.percentile(cpu, 90)),
            "wall_median_s": float(np.median(wall)), "wall_p90_s": float(np.percentile(wall, 90)),
            "correct_detection_rate": _mean(cd), "correct_detection_rate_described": _mean(cd_desc)}


def _rate(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _row(name: str, st: dict) -> str:
    return (f"{name:32s} {st['n']:4d}  {st['cpu_median_s']:.3f}  {st['cpu_p90_s']:.3f}  {st['wall_median_s']:.3f}  "
            f"{st['wall_p90_s']:.3f}  {_rate(st['correct_detection_rate'])}  "
            f"{_rate(st['correct_detection_rate_described'])}")


def _print_steps(frames: list[dict]) -> None:
    """Per step of the segmenter (in the order it runs): median and mean process time over frames, in ms,
    and its share of the total."""
    names = list(dict.fromkeys(name for f in frames for name in f["steps_s"]))
    times = np.array([[f["steps_s"].get(name, 0.0) for name in names] for f in frames]) * 1e3
    total = times.sum()
    print("\nsegmenter steps, process time per frame (ms)")
    print(f"{'step':32s} {'median':>7s} {'mean':>7s} {'share':>6s}")
    for name, col in zip(names, times.T, strict=True):
        print(f"{name:32s} {np.median(col):7.1f} {col.mean():7.1f} {col.sum() / total:6.1%}")
    print(f"{'total':32s} {np.median(times.sum(axis=1)):7.1f} {times.sum(axis=1).mean():7.1f}")


def main(argv: list[str] | None = None) -> int:
    from threadpoolctl import threadpool_limits

    from evaluation.patches import segmentation_section
    from harness.suite import load_suite
    from harness.trial import method_params, prepare_scene, sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import core_sigma, describe
    from recognition.segmentation import segment

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="default", help="a shipped suite's name or a suite YAML file")
    ap.add_argument("--repeat", type=int, default=3, help="segmentations per frame; the fastest one counts")
    ap.add_argument("--groups", default=None, help="comma-separated group names (default: all)")
    ap.add_argument("--limit", type=int, default=None, help="at most this many trials")
    ap.add_argument("--steps", action="store_true", help="also print the time of each step of the segmenter")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    suite = load_suite(args.suite)
    trials = [t for t in suite.trials if args.groups is None or t.group in args.groups.split(",")]
    if args.groups is not None and not trials:
        ap.error(f"no trial in groups {args.groups!r}; the suite's groups: "
                 f"{', '.join(sorted({t.group for t in suite.trials}))}")
    trials = trials[:args.limit]
    core = method_params("core", suite.plan.methods.get("core", {}))
    rows: dict[str, tuple[list, list, list, list]] = {}
    frames: list[dict] = []
    digest = hashlib.sha1()
    with threadpool_limits(limits=1):
        for spec in trials:
            prepared = prepare_scene(spec, None)
            config = sensor_for(spec)
            views = trial_viewpoints(spec, prepared, config)
            if not views.viewpoints:
                print(f"{spec.trial_id}: no viewpoint, skipped", flush=True)
                continue
            scan, truth = trial_scan(spec, prepared, config, views.viewpoints[0].T_world_sensor)
            sigma = core_sigma(scan)
            cpu = wall = float("inf")
            steps: dict[str, float] = {}
            for _ in range(args.repeat):
                laps: dict[str, float] | None = {} if args.steps else None
                t0, c0 = time.perf_counter(), time.process_time()
                seg = segment(scan.points, sigma, steps=laps)
                c = time.process_time() - c0
                wall = min(wall, time.perf_counter() - t0)
                if c < cpu:
                    cpu, steps = c, laps or {}
            digest.update(seg.labels.tobytes())
            cd = segmentation_section(seg.labels, truth, scan.valid)["correct_detection_rate"]
            described = describe(scan, core, seg)
            cd_desc = segmentation_section(described.labels, truth, scan.valid)["correct_detection_rate"]
            for key in (spec.group, "all"):
                acc = rows.setdefault(key, ([], [], [], []))
                for a, v in zip(acc, (cpu, wall, cd, cd_desc), strict=True):
                    a.append(v)
            h, w = scan.valid.shape
            frames.append({"trial_id": spec.trial_id, "group": spec.group, "width": w, "height": h, "cpu_s": cpu,
                           "labels_sha1": hashlib.sha1(seg.labels.tobytes()).hexdigest(),
                           "wall_s": wall, "correct_detection_rate": cd, "correct_detection_rate_described": cd_desc,
                           **({"steps_s": steps} if args.steps else {})})
            print(f"{spec.trial_id}: {w}x{h} process {cpu:.3f} s, wall {wall:.3f} s, correct detection "
                  f"{_rate(cd)} (described {_rate(cd_desc)})", flush=True)
    if not rows:
        print("no frame segmented")
        return 1
    print(f"\nsegmentation per frame, best of {args.repeat} (s); correct detection at T = 0.8, mean over frames, "
          "of the segmenter's labels and of the description's (as summary.json)")
    print(f"{'group':32s} {'n':>4s}  {'cpu50':>5s}  {'cpu90':>5s}  {'wal50':>5s}  {'wal90':>5s}  seg.   desc.")
    groups = {key: _stats(*rows[key]) for key in sorted(rows, key=lambda k: (k == "all", k))}
    for key, st in groups.items():
        print(_row(key, st))
    print(f"labels sha1 {digest.hexdigest()}")
    if args.steps:
        _print_steps(frames)
    if args.json is not None:
        from harness.store import write_json_atomic

        write_json_atomic(args.json, {"suite": args.suite, "repeat": args.repeat, "frames": frames,
                                      "groups": groups, "labels_sha1": digest.hexdigest()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
