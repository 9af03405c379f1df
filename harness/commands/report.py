"""``harness report RUN_DIR [--baseline OTHER_RUN_DIR]``: write RUN_DIR/report.html and RUN_DIR/report.md.

The gallery's trials (worst first) are re-run from their records to draw their pictures (DESIGN 10.14);
with ``--baseline`` the regression section carries ``harness compare``'s verdicts (the same
:class:`evaluation.verdicts.Comparison`; runs that differ in suite, seeds or trials are compared anyway, with a
warning in the section).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from evaluation.verdicts import Comparison

NAME = "report"
HELP = "render a run's evaluation report (report.html, report.md), optionally against a baseline run"
DEFAULT_GALLERY = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, help="results directory of a run (holds summary.json)")
    parser.add_argument("--baseline", type=Path, metavar="OTHER_RUN_DIR",
                        help="a base run to compare against (adds the regression section)")
    parser.add_argument("--gallery", type=int, default=DEFAULT_GALLERY, metavar="N",
                        help=f"re-run and draw the N worst trials (default {DEFAULT_GALLERY}; 0: no gallery)")
    parser.add_argument("--tolerances", type=Path, help="regression rules YAML for --baseline (default: shipped)")
    parser.add_argument("--check-time", action="store_true", help="also apply the (relative) time rules")


def comparison(base_dir: Path, run_dir: Path, tolerances: Path | None = None, check_time: bool = False
               ) -> Comparison:
    """``harness compare``'s verdict (base = ``base_dir``, candidate = ``run_dir``), with ``--force``: a report
    says how the runs differ rather than refusing."""
    from harness.compare import TOLERANCES_DIR, Tolerances, compare_dirs, load_run

    tol = Tolerances.load(tolerances or TOLERANCES_DIR / "default.yaml")
    if check_time:
        tol = dataclasses.replace(tol, check_time=True)
    return compare_dirs(load_run(base_dir), load_run(run_dir), tol, force=True)


def write_report(run_dir: Path, baseline: Path | None = None, gallery: int = DEFAULT_GALLERY,
                 tolerances: Path | None = None, check_time: bool = False,
                 log: Callable[[str], None] | None = None) -> tuple[Path, Path]:
    """Select and re-run the gallery trials, compare with ``baseline`` if given, and render the report."""
    from harness.gallery import build_gallery
    from reports.render import load_run, render_report

    if gallery < 0:
        raise ValueError(f"--gallery must be >= 0, got {gallery}")
    run = load_run(run_dir)  # fails early on a directory that is not a run
    methods = (run.run.get("suite_config") or {}).get("methods") or {"core": {}}
    verdict = comparison(baseline, run_dir, tolerances, check_time) if baseline is not None else None
    pictures = build_gallery(run.records, methods, run_dir / "cache", gallery, log) if gallery else None
    return render_report(run_dir, baseline, pictures, verdict)


def run(args: argparse.Namespace) -> int:
    from harness.compare import CompareError

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        html, md = write_report(args.run_dir, args.baseline, args.gallery, args.tolerances, args.check_time, log)
    except CompareError as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 2
    print(f"report: {html}\n        {md}")
    return 0
