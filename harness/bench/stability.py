"""Stable verdicts: the same trials under a second floating-point path, and how many verdicts change.

``python -m harness.bench.stability [--suite default] [--per-scene N] [--out DIR]`` runs the suite's trials
twice with ``harness bench`` (``--per-scene``: the first N trials of each scene, default all), once as this
machine runs them and once on a second floating-point path: numpy without its widest SIMD dispatch
(``NPY_DISABLE_CPU_FEATURES``, the AVX-512 family where the CPU has it) and OpenBLAS with another kernel
(``OPENBLAS_CORETYPE=Haswell``). It also segments the same scans both ways (``harness.bench.segmentation``) and
compares the label images frame by frame. Printed, and written to ``DIR/stability.json``:

* pose verdicts: the share of trials whose core pose is ``ok`` in both runs or in neither;
* change labels: the share of (trial, feature) rows with the same predicted label;
* classification labels: the share of (trial, patch) rows with the same label;
* label images: the share of frames whose segmentation is bit-identical.

Exit 1 when pose verdicts agree on less than ``--min-pose`` (0.98) or change labels on less than
``--min-change`` (0.97): a verdict that flips with the rounding of one instruction set sits on a knife edge.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

#: numpy's dispatch targets above AVX2 and an OpenBLAS kernel every x86-64 machine of the last decade runs
SECOND_PATH = {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR", "OPENBLAS_CORETYPE": "Haswell"}


def _records(run: Path) -> dict[str, dict[str, Any]]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((run / "trials").glob("*.json"))}


def agreement(a: dict[str, dict[str, Any]], b: dict[str, dict[str, Any]], method: str = "core") -> dict[str, Any]:
    """Shares of equal verdicts between two runs of the same trials (trials ok in both)."""
    pose = change = classes = 0
    n_pose = n_change = n_classes = 0
    flipped: list[str] = []
    for tid in sorted(set(a) & set(b)):
        ra, rb = a[tid], b[tid]
        if ra.get("status") != "ok" or rb.get("status") != "ok":
            continue
        ma, mb = ra["methods"][method], rb["methods"][method]
        pa, pb = ma.get("pose") or {}, mb.get("pose") or {}
        n_pose += 1
        if bool(pa.get("ok")) == bool(pb.get("ok")):
            pose += 1
        else:
            flipped.append(tid)
        fa = {(r.get("feature"), r.get("patch")): r["predicted"] for r in (ma.get("change") or {}).get("features", [])}
        fb = {(r.get("feature"), r.get("patch")): r["predicted"] for r in (mb.get("change") or {}).get("features", [])}
        for key in set(fa) | set(fb):
            n_change += 1
            change += fa.get(key) == fb.get(key)
        ca = {p["patch"]: p["label"] for p in (ma.get("classification") or {}).get("patches", [])}
        cb = {p["patch"]: p["label"] for p in (mb.get("classification") or {}).get("patches", [])}
        for key in set(ca) | set(cb):
            n_classes += 1
            classes += ca.get(key) == cb.get(key)

    def share(k: int, n: int) -> float | None:
        return k / n if n else None

    return {"n_trials": n_pose, "pose_verdicts": share(pose, n_pose), "pose_flipped": flipped,
            "n_change_rows": n_change, "change_labels": share(change, n_change),
            "n_patches": n_classes, "class_labels": share(classes, n_classes)}


def label_agreement(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Share of frames whose label images hash the same in two ``harness.bench.segmentation --json`` outputs."""
    ha = {f["trial_id"]: f["labels_sha1"] for f in a["frames"]}
    hb = {f["trial_id"]: f["labels_sha1"] for f in b["frames"]}
    common = sorted(set(ha) & set(hb))
    same = sum(ha[t] == hb[t] for t in common)
    return {"n_frames": len(common), "identical_frames": same / len(common) if common else None,
            "differing": [t for t in common if ha[t] != hb[t]]}


def _run(cmd: list[str], env: dict[str, str] | None) -> None:
    full = {**os.environ, **(env or {})}
    proc = subprocess.run(cmd, env=full, capture_output=True, text=True)
    if proc.returncode not in (0, 3):  # 3: some trial failed; compared on the trials that ran
        raise RuntimeError(f"{' '.join(cmd)} exited {proc.returncode}: {proc.stderr.strip()[-500:]}")


def main(argv: list[str] | None = None) -> int:
    from harness.suite import load_suite

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="default", help="a shipped suite's name or a suite YAML file")
    ap.add_argument("--per-scene", type=int, default=None, metavar="N", help="the first N trials of each scene")
    ap.add_argument("--workers", type=int, default=2, help="local workers of each run (default 2)")
    ap.add_argument("--out", type=Path, default=Path("runs/stability"), help="where both runs go")
    ap.add_argument("--min-pose", type=float, default=0.98, help="least share of equal pose verdicts (0.98)")
    ap.add_argument("--min-change", type=float, default=0.97, help="least share of equal change labels (0.97)")
    args = ap.parse_args(argv)
    suite = load_suite(args.suite)
    ids: list[str] = []
    seen: dict[str, int] = {}
    for t in suite.trials:
        seen[t.scene] = seen.get(t.scene, 0) + 1
        if args.per_scene is None or seen[t.scene] <= args.per_scene:
            ids.append(t.trial_id)
    only = [x for tid in ids for x in ("--only", tid)]
    outs = {"native": args.out / "native", "second": args.out / "second"}
    for name, env in (("native", None), ("second", SECOND_PATH)):
        print(f"{name}: {len(ids)} trials -> {outs[name]}", file=sys.stderr, flush=True)
        _run([sys.executable, "-m", "harness", "bench", "--suite", args.suite, "--out", str(outs[name]),
              "--overwrite", "--workers", str(args.workers), "--no-report", "--progress", "log", *only], env)
        _run([sys.executable, "-m", "harness.bench.segmentation", "--suite", args.suite, "--repeat", "1",
              "--json", str(args.out / f"segmentation-{name}.json"), "--limit", str(len(ids))], env)
    result = agreement(_records(outs["native"]), _records(outs["second"]))
    result["labels"] = label_agreement(*(json.loads((args.out / f"segmentation-{n}.json").read_text())
                                         for n in ("native", "second")))
    result["second_path"] = SECOND_PATH
    (args.out / "stability.json").write_text(json.dumps(result, indent=1) + "\n")
    fmt = lambda x: "n/a" if x is None else f"{x:.3f}"  # noqa: E731
    print(f"pose verdicts equal on {fmt(result['pose_verdicts'])} of {result['n_trials']} trials"
          + (f" (flipped: {', '.join(result['pose_flipped'])})" if result["pose_flipped"] else ""))
    print(f"change labels equal on {fmt(result['change_labels'])} of {result['n_change_rows']} feature rows")
    print(f"class labels equal on {fmt(result['class_labels'])} of {result['n_patches']} patches")
    lab = result["labels"]
    print(f"label images identical on {fmt(lab['identical_frames'])} of {lab['n_frames']} frames")
    ok = (result["pose_verdicts"] or 0) >= args.min_pose and (result["change_labels"] or 0) >= args.min_change
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
