"""``harness bench``: run a benchmark suite into a results directory and write its summary and report."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from harness.run import RunOptions, run_suite
from harness.suite import load_suite, shipped_suites
from reports.render import why_no_figure

NAME = "bench"
HELP = "run a benchmark suite (default: the shipped 'default' suite)"
EXIT_TRIALS_FAILED = 3  # the run completed and wrote everything, but at least one trial failed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--suite", default="default",
                        help=f"shipped suite name ({', '.join(shipped_suites())}) or a suite YAML file")
    parser.add_argument("--out", type=Path, help="results directory (default: runs/<suite>-<timestamp>)")
    parser.add_argument("--workers", type=int, help="local worker processes (default: all cores)")
    parser.add_argument("--resume", action="store_true",
                        help="complete an interrupted run, skipping finished trials; refused (exit 2) when its "
                             "run.json or records were made by other code (another commit or uncommitted diff)")
    parser.add_argument("--resume-any-code", action="store_true",
                        help="--resume even when other code made the run so far; run.json then lists the mixed "
                             "code identities (mixed_codes)")
    parser.add_argument("--overwrite", action="store_true", help="discard the trial records already in --out")
    parser.add_argument("--only", action="append", default=[], metavar="TRIAL_ID", help="run only this trial")
    parser.add_argument("--artifacts", action="store_true", help="write per-trial images and range data")
    parser.add_argument("--timeout", type=float, help="per-trial timeout in seconds (default: the suite's)")
    parser.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this Dask scheduler")
    parser.add_argument("--dask-local", type=int, metavar="N", help="start a Dask LocalCluster of N workers")
    parser.add_argument("--no-report", action="store_true", help="do not render report.html / report.md")
    parser.add_argument("--progress", choices=("auto", "bar", "log"), default="auto",
                        help="a progress bar (bar), one line per trial (log), or a bar on a terminal only (auto)")
    parser.add_argument("--list", action="store_true",
                        help="print the suite's trials (id, group, scene, seeds, sensor) without running anything")
    parser.add_argument("--allow-failures", action="store_true",
                        help=f"exit 0 even when trials failed (default: exit {EXIT_TRIALS_FAILED} after writing "
                             "every record, the summary and the report)")


def run(args: argparse.Namespace) -> int:
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    if args.dask_local is not None and args.dask_local < 1:
        raise ValueError(f"--dask-local must be >= 1, got {args.dask_local}")
    if args.timeout is not None and not args.timeout > 0:
        raise ValueError(f"--timeout must be > 0, got {args.timeout}")
    suite = load_suite(args.suite)
    if args.list:
        print(trial_list(suite))
        return 0
    out = args.out or Path("runs") / f"{suite.name}-{time.strftime('%Y%m%d-%H%M%S')}"
    options = RunOptions(workers=args.workers, resume=args.resume or args.resume_any_code, only=tuple(args.only),
                         artifacts=args.artifacts, scheduler=args.scheduler, dask_local=args.dask_local,
                         timeout_s=args.timeout, progress={"auto": None, "bar": True, "log": False}[args.progress],
                         overwrite=args.overwrite, resume_any_code=args.resume_any_code)
    summary = run_suite(suite, out, options)
    if not args.no_report:
        _report(out)
    print(headline(summary, out))
    if summary["n_failed"] and not args.allow_failures:
        print(f"{summary['n_failed']} trial(s) failed (see {out / 'summary.json'} failures); exit "
              f"{EXIT_TRIALS_FAILED} (--allow-failures to exit 0)", file=sys.stderr)
        return EXIT_TRIALS_FAILED
    return 0


def _report(out: Path) -> None:
    """report.html and report.md, with the gallery of the worst trials re-run (DESIGN 10.14)."""
    from harness.commands.report import write_report

    write_report(out, log=lambda msg: print(msg, file=sys.stderr, flush=True))


def headline(summary: dict, out: Path) -> str:
    """A few lines for the terminal: trials, failures, and each section's key figure."""
    lines = [f"{out}: {summary['n_trials']} trials, {summary['n_failed']} failed"
             + ("" if summary.get("complete", True) else " (incomplete)")]
    seg, cls, pose, chg = (summary.get(k) for k in ("segmentation", "classification", "pose", "change"))
    fmt = {"segmentation": seg and f"correct detection {seg['correct_detection_rate']:.3f} at T={seg['tolerance']}",
           "classification": cls and cls["accuracy"] is not None and f"accuracy {cls['accuracy']:.3f} "
           f"({cls['n_patches']} patches)",
           "pose": pose and pose["success_rate"] is not None and f"success {pose['success_rate']:.3f}",
           "change": chg and chg["macro_f1"] is not None and f"macro-F1 {chg['macro_f1']:.3f}"}
    for k, v in fmt.items():
        lines.append(f"  {k:15s} {v or why_no_figure(summary, k)}")
    t = summary.get("timing_s", {}).get("total")
    if t:
        lines.append(f"  {'time/trial':15s} median {t['median']:.2f} s, p90 {t['p90']:.2f} s")
    lines.append(f"  summary: {out / 'summary.json'}")
    return "\n".join(lines) + ("\n" + json.dumps(summary["failures"][:5]) if summary["failures"] else "")


def trial_list(suite) -> str:
    """One line per trial of ``suite``: its id and what it is, then the count per group."""
    rows = [("trial id", "group", "scene", "perturbation", "view", "sensor", "noise", "overrides")]
    for t in suite.trials:
        ov = ",".join(f"{k}={v:g}" for k, v in sorted(t.overrides.items()))
        rows.append((t.trial_id, t.group, t.scene, str(t.perturbation_seed), str(t.viewpoint), Path(t.sensor).stem,
                     str(t.noise_seed), ov or "-"))
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    groups: dict[str, int] = {}
    for t in suite.trials:
        groups[t.group] = groups.get(t.group, 0) + 1
    lines.append(f"suite {suite.name}: {len(suite.trials)} trials, {len({t.scene for t in suite.trials})} scenes; "
                 + "; ".join(f"{g}: {n}" for g, n in groups.items()))
    return "\n".join(lines)

