"""``harness compare BASE CANDIDATE``: a verdict on a candidate run against a base run, for a person and for CI.

The headline metrics of the core (pooled and per group) with base, candidate, delta, the 95 % interval of the
paired per-trial delta (scenes resampled) and a verdict word; the other methods (counted only with
``--methods``); the trials that moved most; every numeric leaf with ``--all``. The rules are
:mod:`evaluation.verdicts`'s.

Exit codes: 0 no regression, 1 a regression (a counted headline metric ``regression`` or ``missing``),
2 unreadable input, an unknown ``--methods`` name, or runs of different suites, seeds or trials without
``--force``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from harness.compare import (
    TOLERANCES_DIR,
    CompareError,
    Tolerances,
    compare,
    compare_dirs,
    format_comparison,
    load_run,
    parse_methods,
)

NAME = "compare"
HELP = ("judge a candidate run against a base run on the headline metrics; exit 0 pass, 1 regression, 2 unreadable "
        "input or runs of different suites, seeds or trials")


EPILOG = ("Verdicts: pass (within tolerance); improved; within noise (beyond tolerance, but the 95 % interval of "
          "the paired per-trial delta, scenes resampled, reaches 0: passes); regression (beyond tolerance and the "
          "interval excludes 0, or no interval: fails); missing (the candidate lost the stage: fails); not scored "
          "(nothing left to score, e.g. no such patch: passes). A metric counts once over its scopes (pooled and "
          "per group). Rules: evaluation/verdicts.py.")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EPILOG
    parser.add_argument("base", type=Path, help="base run directory (or its summary.json)")
    parser.add_argument("candidate", type=Path, help="candidate run directory (or its summary.json)")
    parser.add_argument("--tolerances", type=Path, default=TOLERANCES_DIR / "default.yaml",
                        help="regression rules YAML, the 'beyond its tolerance' part (default: the shipped rules)")
    parser.add_argument("--format", choices=("text", "md"), default="text",
                        help="text: aligned columns for a terminal or a CI log (default); md: Markdown tables, "
                             "e.g. for a pull-request comment")
    parser.add_argument("--methods", metavar="NAME[,NAME...]|all",
                        help="methods besides the core whose regressions fail the comparison (e.g. paper,diff_change; "
                             "all: every method); the others are reported only")
    parser.add_argument("--force", action="store_true",
                        help="compare runs of different suites, seeds or trial sets (default: exit 2 saying what "
                             "differs)")
    parser.add_argument("--all", action="store_true", dest="all_leaves",
                        help="also list every numeric leaf of summary.json (informative)")
    parser.add_argument("--changes-only", action="store_true", help="with --all: list only the leaves that changed")
    parser.add_argument("--top", type=int, default=10, metavar="N",
                        help="how many trials 'what changed most' lists (default 10)")
    parser.add_argument("--check-time", action="store_true",
                        help="also judge the median time per trial (relative rule; off by default, shared machines "
                             "are noisy)")


def run(args: argparse.Namespace) -> int:
    if args.top < 0:
        raise ValueError(f"--top must be >= 0, got {args.top}")
    tol = Tolerances.load(args.tolerances)
    if args.check_time:
        tol = dataclasses.replace(tol, check_time=True)
    try:
        base, cand = load_run(args.base), load_run(args.candidate)
        methods = parse_methods(args.methods, base.summary, cand.summary)
        comparison = compare_dirs(base, cand, tol, methods, args.force, args.top)
    except CompareError as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 2
    leaves = compare(base.summary, cand.summary, tol) if args.all_leaves else None
    print(format_comparison(comparison, str(args.base), str(args.candidate), args.format, leaves, args.changes_only,
                            (base.code, cand.code)))
    return 0 if comparison.passed else 1
