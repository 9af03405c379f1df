"""The page of one trial: what it is, every method's figures on it, its pictures (the gallery's, drawn again
from the record), its patches, pose and changes per method, and where its time went.

Written by ``harness show RUN TRIAL_ID`` (``RUN/show/TRIAL_ID/trial.html``, its pictures the PNG files beside
it) and by ``harness report RUN --trials ...`` (``RUN/trials_html/TRIAL_ID.html``, pictures embedded). The
look is the report's (:mod:`reports.html`); the pictures come from the caller (a
:class:`reports.document.GalleryTrial`), so this module never runs the simulator.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from evaluation.metrics import HOOVER_RATES, MIN_SCORED_PIXELS
from reports import figures
from reports.colours import CHANGE_COLOURS, CLASS_COLOURS, CLASSES
from reports.document import Cell, Code, Document, GalleryTrial, Grid, Image, Links, Note, Para, Section, Table
from reports.html import render_html
from reports.render import (
    HOOVER_HEAD,
    METHOD_NOTES,
    RunData,
    _write_atomic,
    fmt,
    pose_verdict,
    trial_accuracy,
    trial_change_f1,
    trial_score,
    trial_time_budget,
    viewing_angle_deg,
)


def _rel(target: Path, start: Path) -> str:
    return Path(os.path.relpath(target, start)).as_posix()


def overview_section(run: RunData, record: Mapping[str, Any]) -> Section:
    spec, view = record.get("spec") or {}, record.get("view") or {}
    score, why = trial_score(record)
    rows = [
        ("group (scene/sensor)", str(spec.get("group", "n/a"))),
        ("scene", f"{spec.get('scene', 'n/a')}" + (f" (family {spec['family']}, generator seed "
                                                    f"{spec.get('scene_seed')})" if spec.get("family") else "")),
        ("perturbation", f"{Path(str(spec.get('perturbation_file') or 'none')).name}, seed "
                         f"{spec.get('perturbation_seed', 'n/a')}"),
        ("viewpoint", f"{spec.get('viewpoint', 'n/a')}, aimed at {view.get('target_feature', 'n/a')}; "
                      f"{view.get('viewpoint_attempts', 'n/a')} attempt(s)"),
        ("sensor", f"{Path(str(spec.get('sensor', 'n/a'))).stem}, noise seed {spec.get('noise_seed', 'n/a')}"
         + (f", overrides {spec['overrides']}" if spec.get("overrides") else "")),
        ("median range", fmt(view.get("median_range_m"), 2, "m")),
        ("viewing angle (optical axis below horizontal)", fmt(viewing_angle_deg(view.get("T_world_sensor")), 1,
                                                              "deg")),
        ("pixels with a return", fmt(100 * view["valid_fraction"], 1, "%") if isinstance(
            view.get("valid_fraction"), int | float) else "n/a"),
        ("surfaces seen (of 200 px or more)", str(view.get("surfaces_seen", "n/a"))),
        ("surfaces constrain the 6 DOF", str(view.get("constrains_pose", "n/a"))),
        ("status", "ok" if record.get("status") == "ok" else f"failed: {record.get('reason', '')}"),
        ("score (the gallery's ranking)", why if score >= 0 else "n/a"),
        ("time", fmt((record.get("timing_s") or {}).get("total"), 2, "s")),
    ]
    suite = run.run.get("source") or run.summary.get("suite", "SUITE")
    blocks: list[Any] = [Table(("item", "value"), tuple((Cell(k), Cell(v)) for k, v in rows), id="trial"),
                         Para("Run this trial again (the same record, bit for bit), and draw this page again:"),
                         Code(f"harness bench --suite {suite} --only {record.get('trial_id')} --out /tmp/one\n"
                              f"harness show {run.root} {record.get('trial_id')}")]
    return Section("trial", "The trial", blocks)


def figures_section(record: Mapping[str, Any]) -> Section:
    head = ("method", *HOOVER_HEAD, "accuracy (patches)", "pose", "rot. error (deg)", "trans. error (mm)",
            "before ICP (deg, mm)", "change macro-F1")
    rows = []
    for m, sec in (record.get("methods") or {}).items():
        seg = sec.get("segmentation") or {}
        acc, n = trial_accuracy(record, m)
        pose = sec.get("pose")
        verdict, style = pose_verdict(pose)
        init = (pose or {}).get("initial") or {}
        rows.append((Cell(m), *[Cell(fmt(seg.get(k)), "num") for k in HOOVER_RATES],
                     Cell(f"{fmt(acc)} ({n})", "num"), Cell(verdict, style),
                     Cell(fmt((pose or {}).get("rotation_error_deg"), 2), "num"),
                     Cell(fmt((pose or {}).get("translation_error_mm"), 1), "num"),
                     Cell(f"{fmt(init.get('rotation_error_deg'), 2)}, {fmt(init.get('translation_error_mm'), 1)}",
                          "num"),
                     Cell(fmt(trial_change_f1(record, m)), "num")))
    notes = "; ".join(f"{m}: {METHOD_NOTES.get(m, 'peer method')}" for m in (record.get("methods") or {}))
    return Section("figures", "Figures per method", [Table(head, tuple(rows), id="trial-figures", caption=(
        f"Hoover rates (T = 0.8, truth regions of {MIN_SCORED_PIXELS} px or more), accuracy over the patches of "
        f"{MIN_SCORED_PIXELS} px or more, the pose after ICP (and before), change macro-F1. {notes}."))])


def pictures_section(entry: GalleryTrial | None, command: str) -> Section:
    if entry is None:
        return Section("pictures", "Pictures", [Note(f"No pictures on this page: '{command}' draws them.", "info")])
    blocks: list[Any] = []
    if entry.panels:
        blocks.append(Grid(tuple(entry.panels)))
    blocks += [Note(n, "info") for n in entry.notes]
    return Section("pictures", "Pictures", blocks)


def _same_patches(a: Sequence[Mapping[str, Any]], b: Sequence[Mapping[str, Any]]) -> bool:
    key = ("patch", "n_pixels", "label")
    return [tuple(p.get(k) for k in key) for p in a] == [tuple(p.get(k) for k in key) for p in b]


def patches_section(record: Mapping[str, Any]) -> Section:
    blocks: list[Any] = [Para(
        "Every patch of every method: its size, the truth surface it mostly covers, the label, the probability "
        f"vector over {', '.join(CLASSES)} (sums to 1) and the paper's plausibilities P(cyl), P(sphere), P(cone) "
        f"(each in [0, 1]). Patches under {MIN_SCORED_PIXELS} pixels are not scored (italic 'small'). Region "
        "numbers are those of the region picture.")]
    shown: dict[str, Sequence[Mapping[str, Any]]] = {}
    for m, sec in (record.get("methods") or {}).items():
        patches = (sec.get("classification") or {}).get("patches") or []
        if not patches:
            continue
        twin = next((o for o, ps in shown.items() if _same_patches(ps, patches)), None)
        if twin is not None:
            blocks.append(Para(f"{m}: the same patches and labels as {twin}."))
            continue
        shown[m] = patches
        rows = []
        for p in sorted(patches, key=lambda q: int(q["patch"])):
            probs, pl = p.get("probabilities") or {}, p.get("plausibilities") or {}
            small = p.get("n_pixels", 0) < MIN_SCORED_PIXELS
            right = p.get("label") == p.get("truth")
            rows.append((Cell(str(p["patch"]), "num"), Cell(str(p.get("n_pixels", "")), "num"),
                         Cell(str(p.get("truth", "")), colour=CLASS_COLOURS.get(str(p.get("truth")), "")),
                         Cell(str(p.get("truth_feature") or "none")),
                         Cell(str(p.get("label", "")), "na" if small else ("good" if right else "bad"),
                              CLASS_COLOURS.get(str(p.get("label")), "")),
                         *[Cell(fmt(probs.get(c), 2), "num") for c in CLASSES],
                         *[Cell(fmt(pl.get(c), 2), "num") for c in ("CYL", "SPH", "CONE")],
                         Cell("small" if small else str(p.get("reason") or ""), "na" if small else "")))
        head = ("region", "pixels", "truth", "truth feature", "label", *[f"P({c})" for c in CLASSES],
                "P(cyl)", "P(sphere)", "P(cone)", "note")
        blocks.append(Table(head, tuple(rows), id=f"patches-{m}", sortable=True,
                            caption=f"{m}: {len(patches)} patches"))
    return Section("patches", "Patches", blocks)


def pose_section(record: Mapping[str, Any]) -> Section:
    head = ("method", "verdict", "confidence", "free DOF", "hypotheses", "rot. error (deg)", "trans. error (mm)",
            "ADD (mm)", "before ICP: rot. (deg)", "before ICP: trans. (mm)", "reason")
    rows = []
    for m, sec in (record.get("methods") or {}).items():
        pose = sec.get("pose")
        if not pose:
            continue
        verdict, style = pose_verdict(pose)
        init = pose.get("initial") or {}
        rows.append((Cell(m), Cell(verdict, style), Cell(fmt(pose.get("confidence"), 2), "num"),
                     Cell(fmt(pose.get("free_dof")), "num"), Cell(fmt(pose.get("n_hypotheses")), "num"),
                     Cell(fmt(pose.get("rotation_error_deg"), 3), "num"),
                     Cell(fmt(pose.get("translation_error_mm"), 1), "num"), Cell(fmt(pose.get("add_mm"), 1), "num"),
                     Cell(fmt(init.get("rotation_error_deg"), 3), "num"),
                     Cell(fmt(init.get("translation_error_mm"), 1), "num"), Cell(str(pose.get("reason") or ""))))
    if not rows:
        return Section("pose", "Pose", [Note("No method has a pose section in this record.", "info")])
    return Section("pose", "Pose", [Table(head, tuple(rows), id="trial-pose", caption=(
        "The estimated T_world_sensor against the truth, after ICP and before (from the matched invariants); "
        "right: stated ok and within 1 deg and 1 % of the median range."))])


def change_section(record: Mapping[str, Any]) -> Section:
    methods = {m: sec.get("change") for m, sec in (record.get("methods") or {}).items() if sec.get("change")}
    if not methods:
        return Section("change", "Change", [Note("No method detected changes in this trial (no pose, or no change "
                                                 "stage).", "info")])
    blocks: list[Any] = []
    for kind, key in (("feature", "features"), ("object", "objects")):
        truth: dict[str, str] = {}
        pred: dict[str, dict[str, str]] = {}
        for m, chg in methods.items():
            for f in chg.get(key) or []:
                name = str(f.get(kind) or "?")
                truth.setdefault(name, str(f.get("truth")))
                pred.setdefault(m, {})[name] = str(f.get("predicted"))
        if not truth:
            continue
        rows = []
        for name in sorted(truth):
            cells = [Cell(name), Cell(truth[name], colour=CHANGE_COLOURS.get(truth[name], ""))]
            for m in methods:
                v = pred.get(m, {}).get(name)
                cells.append(Cell("n/a", "na") if v is None else
                             Cell(v, "good" if v == truth[name] else "bad", CHANGE_COLOURS.get(v, "")))
            rows.append(tuple(cells))
        blocks.append(Table((kind, "truth", *methods), tuple(rows), id=f"change-{key}", sortable=True,
                            caption=f"Change label of every observable {kind}: truth and each method's"))
    return Section("change", "Change", blocks)


def timing_section(record: Mapping[str, Any]) -> Section:
    budget = trial_time_budget(record)
    if budget is None:
        return Section("timing", "Timing", [Note("The record has no total time.", "info")])
    rows = [(Cell("sensor"), Cell(fmt(budget["sensor"], 3), "num"))]
    for m, st in budget["methods"].items():
        rows += [(Cell(f"{m}: {k}"), Cell(fmt(v, 3), "num")) for k, v in st.items()]
    if budget["oracles"]:
        rows.append((Cell("oracles"), Cell(fmt(budget["oracles"], 3), "num")))
    rows += [(Cell("evaluation + overhead (total minus the above)"), Cell(fmt(budget["rest"], 3), "num")),
             (Cell("total"), Cell(fmt(budget["total"], 3), "num"))]
    return Section("timing", "Timing", [
        Table(("part", "seconds"), tuple(rows), id="trial-timing"),
        Image(figures.time_budget_figure(budget), "This trial's time accounted for: sensor, each method's own "
              "stages (a method that reuses the core's shows only what it adds), evaluation + overhead.",
              alt="time budget of this trial")])


def trial_document(run: RunData, record: Mapping[str, Any], entry: GalleryTrial | None,
                   report_href: str | None = None, command: str = "") -> Document:
    """The page of trial ``record`` of ``run`` as a document tree; ``entry`` holds its pictures (None: none),
    ``report_href`` links back to the run's report (None: no report yet)."""
    tid = str(record.get("trial_id"))
    spec = record.get("spec") or {}
    header: tuple[Any, ...] = ()
    if report_href:
        header = (Links((("the run's report", report_href), ("all trials", report_href + "#trials"))),)
    command = command or f"harness show {run.root} {tid}"
    sections = [overview_section(run, record), figures_section(record), pictures_section(entry, command),
                patches_section(record), pose_section(record), change_section(record), timing_section(record)]
    if record.get("status") != "ok":
        sections = [overview_section(run, record)]
    subtitle = f"trial of run {run.root} (suite {run.summary.get('suite')}) - group {spec.get('group')}"
    return Document(f"Trial {tid}", subtitle, sections, header=header,
                    footer="Generated by harness show / harness report --trials from the trial's record "
                           "(pictures re-simulated from it).")


def write_trial_page(path: Path, run: RunData, record: Mapping[str, Any], entry: GalleryTrial | None,
                     image_files: Sequence[str] | None = None, link_report: bool | None = None) -> Path:
    """Write the page of ``record`` to ``path`` (atomically); ``image_files``: the file names (beside ``path``)
    of the entry's pictures, to reference instead of embedding them. Links back to ``RUN/report.html`` when
    ``link_report`` (default: when it exists; ``harness report`` writes the pages just before the report)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if entry is not None and image_files is not None:
        panels = tuple(replace(p, src=name) for p, name in zip(entry.panels, image_files, strict=True))
        entry = replace(entry, panels=panels)
    report = run.root / "report.html"
    href = _rel(report, path.parent) if (report.is_file() if link_report is None else link_report) else None
    _write_atomic(path, render_html(trial_document(run, record, entry, href)))
    return path


__all__ = ["trial_document", "write_trial_page"]
