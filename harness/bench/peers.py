"""Peers beside the core, stage by stage: ``python -m harness.bench.peers [--suite smoke] [-n 2]``.

For the first ``n`` trials of every group of a suite (same scans as the runner: same scene preparation,
viewpoint and noise seeds), each stage is run by the core and by every registered peer that replaces it,
and scored against the truth with the project's evaluation:

* description - Hoover correct-detection rate at T = 0.8 (``evaluation.patches``) and classification
  accuracy over patches on a truth surface; time of segmentation + classification.
* pose - success (rotation <= 1 deg and translation <= 1 % of the median true range), median errors; time
  of matching + ICP (model preparation, cached, apart). Registration peers are swept over ``--voxels``
  (default: 1 %, 2 % and 3 % of the median range) and, with ``--prior-deg/--prior-m``, given a noisy pose
  prior that crops the model; the best voxel per group is reported.
* change - macro-F1 over moved, missing, new, altered (counts pooled over the group's trials), all methods
  given the *true* pose (a stage-isolating oracle, DESIGN 10.10), so only the change stage differs.

Prints one table per stage: accuracy and time per method and group, with peer / core ratios. Peers that
did not register are listed with the reason. This is a developer's tool (the harness's ``baselines``
sections are the product); it imports the harness only to build the same trials.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from collections import defaultdict
from typing import Any

import numpy as np

from evaluation.metrics import MACRO_LABELS as CHANGE_LABELS  # the labels macro-F1 averages
from evaluation.pose import rotation_error_deg, translation_error_mm
from recognition.peers import MISSING, PEERS


def _trials(suite_name: str, per_group: int):
    from harness.suite import load_suite
    from harness.trial import TrialContext, prepare_scene, sensor_for, trial_scan, trial_viewpoints

    suite = load_suite(suite_name)
    seen: dict[str, int] = defaultdict(int)
    for spec in suite.trials:
        if seen[spec.group] >= per_group:
            continue
        seen[spec.group] += 1
        prepared = prepare_scene(spec, None)
        config = sensor_for(spec)
        views = trial_viewpoints(spec, prepared, config)
        if not views.viewpoints:
            continue
        scan, truth = trial_scan(spec, prepared, config, views.viewpoints[0].T_world_sensor)
        yield spec, TrialContext(scan, truth, prepared)


def _pose_errors(T: np.ndarray | None, T_gt: np.ndarray) -> tuple[float, float]:
    if T is None:
        return math.nan, math.nan
    return rotation_error_deg(T[:3, :3], T_gt[:3, :3]), translation_error_mm(T[:3, 3], T_gt[:3, 3])


def _prior(T_gt: np.ndarray, deg: float, metres: float, rng: np.random.Generator) -> np.ndarray:
    from recognition.localisation import exp_so3

    D = np.eye(4)
    D[:3, :3] = exp_so3(rng.normal(0, math.radians(deg) / math.sqrt(3), 3))
    D[:3, 3] = rng.normal(0, metres / math.sqrt(3), 3)
    return D @ T_gt


def _description_row(desc, ctx) -> dict[str, float]:
    from evaluation.patches import classification_section, segmentation_section

    seg = segmentation_section(desc.labels, ctx.truth, ctx.scan.valid)
    rows = [r for r in classification_section(desc, ctx.truth, ctx.prepared.actual)["patches"]
            if r["truth_feature"] is not None]
    correct = sum(r["label"] == r["truth"] for r in rows)
    return {"cdr": seg["correct_detection_rate"], "correct": correct, "n": len(rows),
            "time_s": sum(desc.timing_s.get(k, 0.0) for k in ("segmentation", "classification"))}


def _change_counts(result, ctx) -> dict[str, np.ndarray]:
    from evaluation.change import change_section

    sec = change_section(result, ctx.truth, ctx.prepared.change_truth, ctx.apriori_at_truth, ctx.object_of,
                         kind_of=ctx.kind_of)
    out = {}
    for lab in CHANGE_LABELS:
        tp = sum(r["truth"] == lab and r["predicted"] == lab for r in sec["features"])
        fp = sum(r["truth"] != lab and r["predicted"] == lab for r in sec["features"])
        fn = sum(r["truth"] == lab and r["predicted"] != lab for r in sec["features"])
        out[lab] = np.array([tp, fp, fn])
    return out


def _macro_f1(counts: dict[str, np.ndarray]) -> float:
    f1 = []
    for lab in CHANGE_LABELS:
        tp, fp, fn = counts[lab]
        if tp + fp + fn:
            f1.append(2 * tp / (2 * tp + fp + fn))
    return float(np.mean(f1)) if f1 else math.nan


def run_bench(suite: str = "smoke", per_group: int = 2, voxels: list[float] | None = None,
              prior_deg: float | None = None, prior_m: float | None = None, stages: tuple[str, ...] = (
                  "description", "pose", "change"), peers: list[str] | None = None) -> dict[str, Any]:
    """Run the comparison and return ``{stage: {group: {method: metrics}}}`` (see the module docstring)."""
    from recognition.change import detect_changes
    from recognition.describe import DescribeParams, describe

    try:
        from recognition.localisation import LocaliseParams, localise
    except ImportError:
        localise = LocaliseParams = None
    chosen = {n: p for n, p in PEERS.items() if peers is None or n in peers}
    desc_acc: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    pose_acc: dict = defaultdict(lambda: defaultdict(lambda: defaultdict(list)))
    change_acc: dict = defaultdict(lambda: defaultdict(lambda: {"counts": None, "time_s": []}))
    for spec, ctx in _trials(suite, per_group):
        group = spec.group
        scan, truth, prepared = ctx.scan, ctx.truth, ctx.prepared
        print(f"# {spec.trial_id}", flush=True)
        core_desc = describe(scan, DescribeParams())
        if "description" in stages:
            for k, v in _description_row(core_desc, ctx).items():
                desc_acc[group]["core"][k].append(v)
            for name, peer in chosen.items():
                if peer.replaces == "description":
                    for k, v in _description_row(peer.run(scan, {}), ctx).items():
                        desc_acc[group][name][k].append(v)
        if "pose" in stages:
            T_gt = truth.T_world_sensor
            limit_mm = 10.0 * (ctx.median_range or math.nan)
            pscan = scan
            if prior_deg is not None:
                pscan = dataclasses.replace(scan, pose_prior=_prior(T_gt, prior_deg, prior_m or 0.0,
                                                                    np.random.default_rng(spec.index)))
            if localise is not None:
                sim = getattr(prepared.predictor, "simulator", prepared.predictor)
                res = localise(core_desc, pscan, prepared.apriori, LocaliseParams(), sim)
                t = res.timing_s
                dt = sum(t.get(k, 0.0) for k in ("matching", "pose", "verification", "icp"))
                _pose_row(pose_acc[group]["core"], res.T_world_sensor if res.usable else None, T_gt, limit_mm, dt)
                print(f"  core: ok={res.ok} {res.reason} errors {_pose_errors(res.T_world_sensor, T_gt)}",
                      flush=True)
            med = ctx.median_range or 5.0
            for name, peer in chosen.items():
                if peer.replaces != "pose":
                    continue
                sweep = [(v, f"{v:g} m") for v in voxels] if voxels else [
                    (round(f * med, 3), f"{100 * f:g}% range") for f in (0.01, 0.02, 0.03)]
                for v, tag in sweep:
                    res = peer.run(core_desc, pscan, prepared.apriori, {"voxel_size": v}, prepared.predictor)
                    t = res.timing_s
                    _pose_row(pose_acc[group][f"{name}@{tag}"], res.T_world_sensor if res.ok else None, T_gt,
                              limit_mm, t.get("matching", 0.0) + t.get("icp", 0.0))
                    print(f"  {name} voxel {v:g}: ok={res.ok} {res.reason} "
                          f"errors {_pose_errors(res.T_world_sensor, T_gt)}", flush=True)
        if "change" in stages:
            T_gt = truth.T_world_sensor
            predicted = prepared.predictor.predict(scan.sensor, T_gt)
            t0 = time.perf_counter()
            core = detect_changes(core_desc, scan, prepared.apriori, T_gt, np.zeros((6, 6)), predicted=predicted,
                                  predictor=prepared.predictor)
            _change_row(change_acc[group]["core"], _change_counts(core, ctx), time.perf_counter() - t0)
            for name, peer in chosen.items():
                if peer.replaces == "change":
                    t0 = time.perf_counter()
                    res = peer.run(core_desc, scan, prepared.apriori, T_gt, None, prepared.predictor, {},
                                   predicted=predicted)
                    dt = time.perf_counter() - t0 - res.timing_s.get("model", 0.0)
                    _change_row(change_acc[group][name], _change_counts(res, ctx), dt)
    return _summarise(desc_acc, pose_acc, change_acc)


def _pose_row(acc, T, T_gt, limit_mm, time_s) -> None:
    rot, tr = _pose_errors(T, T_gt)
    acc["success"].append(bool(T is not None and rot <= 1.0 and tr <= limit_mm))
    acc["rot_deg"].append(rot)
    acc["trans_mm"].append(tr)
    acc["time_s"].append(time_s)


def _change_row(acc, counts, time_s) -> None:
    acc["counts"] = counts if acc["counts"] is None else {k: acc["counts"][k] + counts[k] for k in counts}
    acc["time_s"].append(time_s)


def _summarise(desc_acc, pose_acc, change_acc) -> dict[str, Any]:
    out: dict[str, Any] = {"description": {}, "pose": {}, "change": {}}
    for group, methods in desc_acc.items():
        out["description"][group] = {
            m: {"correct_detection_rate": float(np.mean(a["cdr"])),
                "accuracy": float(np.sum(a["correct"]) / max(np.sum(a["n"]), 1)),
                "time_s": float(np.median(a["time_s"]))} for m, a in methods.items()}
    for group, methods in pose_acc.items():
        out["pose"][group] = {
            m: {"success_rate": float(np.mean(a["success"])), "rot_deg_median": float(np.nanmedian(a["rot_deg"]))
                if np.isfinite(a["rot_deg"]).any() else math.nan,
                "trans_mm_median": float(np.nanmedian(a["trans_mm"])) if np.isfinite(a["trans_mm"]).any()
                else math.nan, "time_s": float(np.median(a["time_s"]))} for m, a in methods.items()}
    for group, methods in change_acc.items():
        out["change"][group] = {m: {"macro_f1": _macro_f1(a["counts"]), "time_s": float(np.median(a["time_s"]))}
                                for m, a in methods.items()}
    return out


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b and np.isfinite(a) and np.isfinite(b) else "-"


def format_tables(result: dict[str, Any]) -> str:
    """Markdown tables, one per stage: each method's accuracy and time, and its ratios to the core's."""
    lines = []
    keys = {"description": ("correct_detection_rate", "accuracy"), "pose": ("success_rate", "rot_deg_median",
                                                                           "trans_mm_median"),
            "change": ("macro_f1",)}
    for stage, groups in result.items():
        if not groups:
            continue
        lines.append(f"\n## {stage}\n")
        cols = keys[stage]
        lines.append("| group | method | " + " | ".join(cols) + " | time_s | acc / core | time / core |")
        lines.append("|" + "---|" * (len(cols) + 5))
        for group, methods in groups.items():
            core = methods.get("core", {})
            for m, v in methods.items():
                vals = " | ".join(f"{v[c]:.3f}" for c in cols)
                lines.append(f"| {group} | {m} | {vals} | {v['time_s']:.2f} | {_ratio(v[cols[0]], core.get(cols[0]))} "
                             f"| {_ratio(v['time_s'], core.get('time_s'))} |")
    if MISSING:
        lines.append("\nNot registered: " + "; ".join(f"{k}: {v}" for k, v in MISSING.items()))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.bench.peers", description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="smoke")
    ap.add_argument("-n", "--per-group", type=int, default=2, help="trials per group")
    ap.add_argument("--voxels", type=lambda s: [float(x) for x in s.split(",")], default=None,
                    help="registration voxel sizes to sweep (m, comma-separated; default 1/2/3 %% of the range)")
    ap.add_argument("--prior-deg", type=float, default=None, help="give a pose prior with this rotation noise")
    ap.add_argument("--prior-m", type=float, default=None, help="... and this translation noise (m)")
    ap.add_argument("--stages", default="description,pose,change")
    ap.add_argument("--peers", default=None, help="comma-separated peer names (default: all registered)")
    args = ap.parse_args(argv)
    result = run_bench(args.suite, args.per_group, args.voxels, args.prior_deg, args.prior_m,
                       tuple(args.stages.split(",")), args.peers.split(",") if args.peers else None)
    print(format_tables(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
