"""``harness report RUN_DIR [--baseline OTHER_RUN_DIR] [--trials SELECTION]``: write RUN_DIR/report.html and
RUN_DIR/report.md, and the pages of the selected trials into RUN_DIR/trials_html/.

The gallery's trials (worst first) are re-run from their records to draw their pictures (DESIGN 10.14);
with ``--baseline`` the regression section carries ``harness compare``'s verdicts (the same
:class:`evaluation.verdicts.Comparison`; runs that differ in suite, seeds or trials are compared anyway, with a
warning in the section). ``--trials`` writes a page per selected trial (``trials_html/<id>.html``, pictures
embedded: :mod:`reports.trial_page`): ``gallery`` (the default: the gallery's trials, already drawn), ``all``,
``worst:N``, ``none`` or trial ids. The report's trial index links to every trial page that exists.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

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
    parser.add_argument("--trials", nargs="+", default=["gallery"], metavar="SELECTION",
                        help="write a page per trial into RUN_DIR/trials_html/: gallery (default: the gallery's "
                             "trials), all, worst:N, none, or trial ids")
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


def select_trials(records: Sequence[Mapping[str, Any]], selection: Sequence[str], gallery_ids: Sequence[str]
                  ) -> list[str]:
    """The trial ids that ``--trials`` names, in the run's order (``worst:N``: worst first): ``gallery``,
    ``all``, ``none``, ``worst:N`` or trial ids (an unknown id names the closest ones)."""
    from reports.render import worst_trials

    ids = [str(r.get("trial_id")) for r in records]
    out: list[str] = []
    for word in selection:
        if word == "none":
            continue
        if word == "gallery":
            out += list(gallery_ids)
        elif word == "all":
            out += ids
        elif word.startswith("worst:"):
            try:
                n = int(word.split(":", 1)[1])
            except ValueError:
                raise ValueError(f"--trials {word}: expected worst:N with N a number") from None
            out += [str(r["trial_id"]) for r, _, _ in worst_trials(records, n)]
        elif word in ids:
            out.append(word)
        else:
            from harness.suite import closest_hint

            raise ValueError(f"--trials {word}: no such trial in this run"
                             + closest_hint(word, ids, f" ({len(ids)} trials)"))
    return list(dict.fromkeys(out))


def write_trial_pages(run, trial_ids: Sequence[str], drawn: Mapping[str, Any], methods: Mapping[str, Any],
                      cache_dir: Path, log: Callable[[str], None] | None = None) -> list[Path]:
    """Write ``RUN/trials_html/<id>.html`` for each trial id: the gallery's pictures when ``drawn`` has them, else
    the trial re-run and drawn here (a trial that cannot be re-run gets a page without pictures, and a note)."""
    from harness.gallery import draw, rerun
    from reports.document import GalleryTrial
    from reports.render import TRIAL_PAGES_DIR, trial_page_name, trial_score
    from reports.trial_page import write_trial_page

    by_id = {str(r.get("trial_id")): r for r in run.records}
    out = []
    for i, tid in enumerate(trial_ids, start=1):
        record = by_id[tid]
        entry = drawn.get(tid)
        if entry is None and record.get("status") == "ok":
            if log is not None:
                log(f"trial pages: re-running {tid} ({i}/{len(trial_ids)})")
            why = trial_score(record)[1]
            try:
                entry = draw(record, rerun(record, methods, cache_dir), why)
            except Exception as exc:  # noqa: BLE001 - one trial's pictures must not cost the others
                entry = GalleryTrial(tid, str((record.get("spec") or {}).get("group", "")), why, (),
                                     (f"Could not re-run this trial to draw it: {type(exc).__name__}: {exc}",))
        out.append(write_trial_page(run.root / TRIAL_PAGES_DIR / trial_page_name(tid), run, record, entry,
                                    link_report=True))
    return out


def write_report(run_dir: Path, baseline: Path | None = None, gallery: int = DEFAULT_GALLERY,
                 tolerances: Path | None = None, check_time: bool = False,
                 log: Callable[[str], None] | None = None, trials: Sequence[str] = ("gallery",)
                 ) -> tuple[Path, Path]:
    """Select and re-run the gallery trials, write the pages of the ``trials`` selected (see
    :func:`select_trials`), compare with ``baseline`` if given, and render the report."""
    from harness.gallery import build_gallery
    from reports.render import load_run, render_report

    if gallery < 0:
        raise ValueError(f"--gallery must be >= 0, got {gallery}")
    run = load_run(run_dir)  # fails early on a directory that is not a run
    methods = (run.run.get("suite_config") or {}).get("methods") or {"core": {}}
    verdict = comparison(baseline, run_dir, tolerances, check_time) if baseline is not None else None
    pictures = build_gallery(run.records, methods, run_dir / "cache", gallery, log) if gallery else None
    drawn = {g.trial_id: g for g in pictures or ()}
    page_ids = select_trials(run.records, trials, list(drawn))
    if page_ids:
        write_trial_pages(run, page_ids, drawn, methods, run_dir / "cache", log)
    return render_report(run_dir, baseline, pictures, verdict)


def run(args: argparse.Namespace) -> int:
    from harness.compare import CompareError

    def log(msg: str) -> None:
        print(msg, file=sys.stderr, flush=True)

    try:
        html, md = write_report(args.run_dir, args.baseline, args.gallery, args.tolerances, args.check_time, log,
                                args.trials)
    except (CompareError, ValueError) as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 2
    print(f"report: {html}\n        {md}")
    return 0
