"""``harness show RUN TRIAL_ID``: one trial of a run - its figures, and its gallery pictures drawn again.

Prints the trial's figures per method (from its record in ``RUN/trials/``) and writes the report's gallery
pictures of it (the scan simulated again from the record, deterministic: DESIGN 10.14) as PNG files with an
``index.md`` of their captions, and ``trial.html``: the trial's page in the report's look (its figures, pictures,
patches, pose and changes per method, timing; :mod:`reports.trial_page`), referencing the PNGs beside it, into
``--out`` (default ``RUN/show/TRIAL_ID/``). The report's trial index links to that page once it exists.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any

NAME = "show"
HELP = "print one trial's figures and draw its pictures (re-simulated from the run's record)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, help="results directory of a run")
    parser.add_argument("trial_id", help="a trial id of that run (`harness bench --suite S --list` lists them)")
    parser.add_argument("--out", type=Path, help="where the pictures go (default: RUN/show/TRIAL_ID/)")
    parser.add_argument("--no-pictures", action="store_true", help="print the figures only")


def load_record(run_dir: Path, trial_id: str) -> dict[str, Any]:
    path = run_dir / "trials" / f"{trial_id}.json"
    if not path.is_file():
        from harness.suite import closest_hint

        ids = sorted(p.stem for p in (run_dir / "trials").glob("*.json"))
        if not ids:
            raise FileNotFoundError(f"{run_dir}: no trial records (not a results directory?)")
        raise FileNotFoundError(f"{path}: no such trial in this run" + closest_hint(trial_id, ids,
                                                                                     f" ({len(ids)} trials)"))
    return json.loads(path.read_text(encoding="utf-8"))


def trial_figures(record: dict[str, Any]) -> list[str]:
    """Lines describing a trial: what it is, then each method's figures on it."""
    from evaluation.aggregate import aggregate_change, aggregate_classification

    spec = record.get("spec", {})
    view = record.get("view") or {}
    lines = [f"{record['trial_id']}: group {spec.get('group')}, scene {spec.get('scene')}, perturbation seed "
             f"{spec.get('perturbation_seed')}, viewpoint {spec.get('viewpoint')}, sensor "
             f"{Path(str(spec.get('sensor'))).stem}, noise seed {spec.get('noise_seed')}"]
    if record.get("status") != "ok":
        return [*lines, f"  FAILED: {record.get('reason', '')}"]
    lines.append(f"  view: median range {view.get('median_range_m', float('nan')):.2f} m, "
                 f"{100 * view.get('valid_fraction', 0):.0f} % valid, {view.get('surfaces_seen')} surfaces of "
                 f">= {spec.get('min_view_pixels', 200)} px, constrains 6 DOF: {view.get('constrains_pose')}"
                 f"{' (a twin pose explains it as well)' if view.get('twin_ambiguous') else ''}; "
                 f"time {(record.get('timing_s') or {}).get('total') or 0:.2f} s")
    for name, m in (record.get("methods") or {}).items():
        seg, cls, pose, chg = (m.get(k) for k in ("segmentation", "classification", "pose", "change"))
        parts = []
        if seg:
            parts.append(f"correct detection {_f(seg.get('correct_detection_rate'))}")
        if cls:
            c = aggregate_classification([cls])
            parts.append(f"accuracy {_f(c['accuracy'])} ({c['n_patches']} patches)")
        if pose:
            ok = "ok" if pose.get("ok") else (f"conditional on {pose['conditional_on']}" if pose.get("conditional_on")
                                              else "not ok")
            right = "right" if pose.get("success") else "wrong"
            parts.append(f"pose {ok}, {right}: {_f(pose.get('rotation_error_deg'), 2)} deg, "
                         f"{_f(pose.get('translation_error_mm'), 1)} mm")
        if chg:
            parts.append(f"change macro-F1 {_f(aggregate_change([chg])['macro_f1'])}")
        lines.append(f"  {name}: " + ("; ".join(parts) or "no stage scored"))
    return lines


def _f(x: Any, digits: int = 3) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def run(args: argparse.Namespace) -> int:
    record = load_record(args.run_dir, args.trial_id)
    print("\n".join(trial_figures(record)))
    from reports.render import load_run, trial_score
    from reports.trial_page import write_trial_page

    run = load_run(args.run_dir)
    out = args.out or args.run_dir / "show" / args.trial_id
    if args.no_pictures or record.get("status") != "ok":
        page = write_trial_page(out / "trial.html", run, record, None)
        print(f"page -> {page}")
        return 0
    from harness.gallery import draw, rerun

    methods = (run.run.get("suite_config") or {}).get("methods") or {"core": {}}
    out.mkdir(parents=True, exist_ok=True)
    entry = draw(record, rerun(record, methods, args.run_dir / "cache"), trial_score(record)[1])
    index = [f"# {entry.trial_id} ({entry.group})", "", "The same pictures with the trial's tables: trial.html.", ""]
    names = []
    for i, panel in enumerate(entry.panels):
        name = f"{i:02d}-{re.sub(r'[^a-z0-9]+', '-', panel.caption.lower()).strip('-')[:40]}.png"
        (out / name).write_bytes(panel.png)
        names.append(name)
        index += [f"![{panel.alt or panel.caption}]({name})", "", panel.caption, ""]
    index += [f"- {n}" for n in entry.notes]
    (out / "index.md").write_text("\n".join(index) + "\n", encoding="utf-8")
    page = write_trial_page(out / "trial.html", run, record, entry, image_files=names)
    print(f"{len(entry.panels)} pictures -> {out}\npage -> {page}")
    return 0
