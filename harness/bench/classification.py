"""Benchmark of the patch classifiers on synthetic one-sided noisy patches.

Run ``python -m harness.bench.classification [--n 40] [--seed 0] [--presets mockup_laser,...]``. For each
noise preset (see :data:`recognition._synthetic.PRESETS`) and each classifier (``select``, ``paper``) it
prints the accuracy per true class (plane, cylinder, sphere, cone, torus = OTH), the overall accuracy and
the multi-class Brier score (DESIGN 10.8), the relative radius error of the cylinder and sphere fits against
truth (bias), the CPU time per patch (``time.process_time``: the machine may be shared), and the time to
classify a frame-like batch of patches (sizes 200-20000 points, about 300k points in all, as in a 640x480
frame).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from recognition._synthetic import KINDS, PRESETS, TRUE_CLASS, sample_patch
from recognition.classification import CLASSES, classify_patch
from recognition.fitting import fit_cylinder, fit_sphere

__all__ = ["main", "run_preset", "frame_batch_time"]


def _brier(probs: dict[str, float], truth: str) -> float:
    return float(sum((probs[c] - (1.0 if c == truth else 0.0)) ** 2 for c in CLASSES))


def run_preset(preset: str, n: int, seed: int) -> dict:
    """Classify ``n`` patches per kind with both methods.

    Returns
    -------
    dict
        ``{method: {"acc": {kind: float}, "overall": float, "brier": float, "time_ms": float}}`` plus
        ``"radius_bias"``: ``{"cylinder"|"sphere": (median, mean, p10, p90) of fitted/true - 1}``.
    """
    out: dict = {}
    patches = [(kind, sample_patch(kind, np.random.default_rng([seed, i, KINDS.index(kind)]), preset))
               for kind in KINDS for i in range(n)]
    for method in ("select", "paper"):
        ok = {k: 0 for k in KINDS}
        brier, times = [], []
        for kind, p in patches:
            t0 = time.process_time()
            r = classify_patch(p.points, p.sigma, method=method)
            times.append(time.process_time() - t0)
            ok[kind] += r.label == TRUE_CLASS[kind]
            brier.append(_brier(r.probabilities, TRUE_CLASS[kind]))
        acc = {k: v / n for k, v in ok.items()}
        out[method] = {
            "acc": acc, "overall": float(np.mean(list(acc.values()))), "brier": float(np.mean(brier)),
            "time_ms": 1e3 * float(np.median(times)), "time_p90_ms": 1e3 * float(np.percentile(times, 90)),
        }
    bias = {}
    for kind, fit in (("cylinder", fit_cylinder), ("sphere", fit_sphere)):
        rel = np.array([fit(p.points, p.sigma).radius / p.truth["radius"] - 1
                        for k, p in patches if k == kind])
        rel = rel[np.isfinite(rel)]
        bias[kind] = (float(np.median(rel)), float(np.mean(rel)), float(np.percentile(rel, 10)),
                      float(np.percentile(rel, 90)))
    out["radius_bias"] = bias
    return out


def frame_batch_time(
    seed: int, method: str, n_patches: int = 40, total_points: int = 300_000, preset: str = "kinect_like",
    params=None,
) -> tuple[float, float, int]:
    """Wall-clock and CPU seconds to classify a frame-like batch, and the number of points in it.

    Patch sizes are log-uniform in [200, 20000] points, scaled so the batch holds ``total_points``.
    """
    rng = np.random.default_rng(seed)
    sizes = np.exp(rng.uniform(np.log(200), np.log(20000), n_patches))
    sizes = np.clip(sizes * total_points / sizes.sum(), 200, 20000).astype(int)
    patches = []
    for i, m in enumerate(sizes):
        kind = KINDS[i % len(KINDS)]
        p = sample_patch(kind, rng, preset, n_max=int(m), n_min=int(m))
        patches.append(p)
    t0, c0 = time.perf_counter(), time.process_time()
    for p in patches:
        classify_patch(p.points, p.sigma, method=method, params=params)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return wall, cpu, int(sum(len(p.points) for p in patches))


def main(argv: list[str] | None = None) -> int:
    """Print the benchmark tables (Markdown); returns 0."""
    ap = argparse.ArgumentParser(prog="python -m harness.bench.classification", description=__doc__)
    ap.add_argument("--n", type=int, default=40, help="patches per kind and preset")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--frames", type=int, default=3, help="frame-like batches to time (0: skip)")
    args = ap.parse_args(argv)
    print(f"# Patch classification benchmark (n = {args.n} per kind, seed {args.seed})\n")
    print("| preset | method | PLAN | CYL | SPH | CONE | OTH (torus) | overall | Brier "
          "| CPU ms/patch (median, p90) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    biases = {}
    for preset in args.presets.split(","):
        res = run_preset(preset, args.n, args.seed)
        biases[preset] = res["radius_bias"]
        for method in ("select", "paper"):
            r = res[method]
            a = r["acc"]
            print(f"| {preset} | {method} | {a['plane']:.2f} | {a['cylinder']:.2f} | {a['sphere']:.2f} | "
                  f"{a['cone']:.2f} | {a['torus']:.2f} | {r['overall']:.3f} | {r['brier']:.3f} | "
                  f"{r['time_ms']:.1f}, {r['time_p90_ms']:.1f} |", flush=True)
    print("\n## Radius bias (fitted / true - 1, %): median, mean, p10, p90\n")
    print("| preset | cylinder | sphere |")
    print("|---|---|---|")
    for preset, b in biases.items():
        cells = [", ".join(f"{100 * v:+.3f}" for v in b[k]) for k in ("cylinder", "sphere")]
        print(f"| {preset} | {cells[0]} | {cells[1]} |")
    if args.frames > 0:
        print("\n## Frame-like batches (40 patches of 200-20000 points, ~220k points in all)\n")
        for preset in args.presets.split(","):
            for method in ("select", "paper"):
                ts = [frame_batch_time(args.seed + k, method, preset=preset) for k in range(args.frames)]
                print(f"- {preset}, {method}: " + ", ".join(
                    f"{w:.3f} s wall / {c:.3f} s CPU ({npts} points)" for w, c, npts in ts))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
