"""Reliability of the classifier's confidence per decision path, from a run's trials.

``python -m harness.bench.confidence RUN_DIR [--method core] [--min-pixels 200] [--group kinect]`` reads the
classification records of a ``harness run`` / ``harness bench`` results directory and prints, per decision path
of the model-selection classifier (:data:`recognition.classification.params.DECISION_PATHS`: how the label was
reached) and over all patches of ``--min-pixels`` or more: the count, the accuracy, the mean probability of the
label, the Brier score and the floor that minimises it, fitted on the probabilities before the floor the run
applied (:func:`evaluation.classification.decision_path_table`; the report shows the same table). The floors of
``SelectParams`` (``prob_floor``, ``rescue_floor``, ``unexplained_floor``) are fitted with it on the
``calibration`` suite, never on ``default`` (DESIGN 10.8).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from evaluation.classification import decision_path_table
from evaluation.metrics import MIN_SCORED_PIXELS
from harness.store import RunDirectory

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--method", default="core")
    ap.add_argument("--min-pixels", type=int, default=MIN_SCORED_PIXELS)
    ap.add_argument("--group", default="", help="only trials whose id contains this (e.g. kinect_like)")
    args = ap.parse_args(argv)
    records = RunDirectory(args.run_dir).read_trials()
    if not records:
        print(f"{args.run_dir}: no trials/*.json: not a results directory", file=sys.stderr)
        return 2
    rows = []
    for record in records:
        if args.group not in record["trial_id"]:
            continue
        section = record.get("methods", {}).get(args.method, {}).get("classification")
        if section is None:
            continue
        rows += [r for r in section["patches"] if r["n_pixels"] >= args.min_pixels]
    if not rows:
        print(f"{args.run_dir}: no classified patches of method {args.method!r}", file=sys.stderr)
        return 2
    print(f"{'path':<12} {'count':>6} {'accuracy':>9} {'confidence':>11} {'brier':>7} {'floor':>6} {'optimal':>8}")
    for t in decision_path_table(rows):
        fl = "" if t["floor"] is None else f"{t['floor']:.3f}"
        opt = "" if t["optimal_floor"] is None else f"{t['optimal_floor']:.3f}"
        print(f"{t['path']:<12} {t['count']:>6} {t['accuracy']:>9.3f} {t['confidence']:>11.3f} {t['brier']:>7.3f} "
              f"{fl:>6} {opt:>8}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
