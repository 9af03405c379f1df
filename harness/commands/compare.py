"""``harness compare``: every metric of two runs with its delta; exit 1 on a regression (for CI)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from harness.compare import TOLERANCES_DIR, CompareError, Tolerances, compare, format_rows, load_summary, regressions

NAME = "compare"
HELP = "compare a candidate run with a base run; exit 1 on a regression, 2 on unreadable input"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("base", type=Path, help="base run directory or summary.json")
    parser.add_argument("candidate", type=Path, help="candidate run directory or summary.json")
    parser.add_argument("--tolerances", type=Path, default=TOLERANCES_DIR / "default.yaml",
                        help="regression rules YAML (default: the shipped rules)")
    parser.add_argument("--format", choices=("text", "md"), default="text")
    parser.add_argument("--check-time", action="store_true", help="also apply the (relative) time rules")
    parser.add_argument("--changes-only", action="store_true", help="list only metrics that changed")


def run(args: argparse.Namespace) -> int:
    try:
        base, cand = load_summary(args.base), load_summary(args.candidate)
    except CompareError as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 2
    tol = Tolerances.load(args.tolerances)
    if args.check_time:
        tol = dataclasses.replace(tol, check_time=True)
    rows = compare(base, cand, tol)
    print(format_rows(rows, args.format, args.changes_only))
    bad = regressions(rows)
    verdict = f"{len(bad)} regression(s)" if bad else "no regression"
    print(f"\n{'FAIL' if bad else 'PASS'}: {verdict} ({len(rows)} metrics compared)")
    for r in bad[:20]:
        print(f"  {r.metric}: {r.base} -> {r.candidate}")
    return 1 if bad else 0
