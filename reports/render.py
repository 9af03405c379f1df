"""The evaluation report of a run directory: ``report.html`` (self-contained, figures embedded) and ``report.md``.

Headline figures are shown with their 95 % interval from ``summary.json`` (``<key>_ci95``, DESIGN 11.3) as
``0.812 [0.76, 0.86]``, and plotted with error bars; a figure whose interval is null (fewer than two scenes)
is shown bare, never with an interval made up here.

:func:`render_report` reads ``summary.json``, ``run.json`` and ``trials/*.json`` (never logs), builds a
:class:`reports.document.Document` and writes it twice. A stage whose summary section is null is shown as
"no figure", never left out and never filled in. The gallery pictures and the regression verdicts come
from the caller (``harness report`` re-runs the gallery trials and hands in ``harness compare``'s
:class:`evaluation.verdicts.Comparison`), so this package never runs the simulator nor re-implements the
regression rules. Which figures the headline, per-group, per-method, oracle and regression tables show, with
what title, direction, unit and digits, are the declarations of :mod:`evaluation.metrics` (``headline`` and
``compact``).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation import metrics
from evaluation.attribution import attribute, largest_losses
from evaluation.classification import decision_path_table
from evaluation.metrics import HOOVER_RATES, MIN_SCORED_PIXELS, TIMING_STAGES, Metric
from evaluation.verdicts import Comparison
from reports import figures
from reports.colours import CHANGE_COLOURS, CHANGE_LABELS, CLASS_COLOURS, CLASSES
from reports.document import Cell, Code, Document, GalleryTrial, Grid, Image, Links, Note, Para, Section, Table
from reports.html import render_html
from reports.markdown import render_markdown
from reports.paper_table import paper_reproduction_section
from reports.regression import (
    MOVES_HEADER,
    Missing,
    figure_cells,
    headline_deltas,
    lookup,
    lookup_interval,
    move_cells,
    shown_figures,
)

HOOVER_HEAD = ("correct", "over", "under", "missed", "noise")  # column titles of HOOVER_RATES
STAGES = TIMING_STAGES
SWEEP_GROUP = re.compile(r"\[([A-Za-z_][A-Za-z0-9_]*)=([^\]]+)\]")
METHOD_NOTES = {"core": "the recognition core (its model-selection classifier)",
                "paper": "the core with the paper's literal classifier (plausibilities, 0.2 margin)"}
NOT_BUILT = "no figure"


# -- loading ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunData:
    """What a report reads from a run directory."""

    root: Path
    summary: dict[str, Any]
    run: dict[str, Any]
    records: list[dict[str, Any]]

    @property
    def methods(self) -> list[str]:
        """``core``, then ``paper``, then the other peers by name."""
        peers = sorted(self.summary.get("baselines") or {}, key=lambda m: (m != "paper", m))
        return ["core", *peers]

    def sections(self, method: str, scope: Mapping[str, Any] | None = None) -> Mapping[str, Any] | None:
        """A method's sections in the whole summary or in one group (``scope``)."""
        s = self.summary if scope is None else scope
        return s if method == "core" else (s.get("baselines") or {}).get(method)

    def ok_records(self) -> list[dict[str, Any]]:
        return [r for r in self.records if r.get("status") == "ok"]


def load_run(run_dir: str | Path) -> RunData:
    """Read a run directory; ``summary.json`` is required, ``run.json`` and the trial records are optional."""
    root = Path(run_dir)
    summary_path = root / "summary.json"
    if not summary_path.is_file():
        raise FileNotFoundError(f"{root}: no summary.json (is this a run directory?)")
    summary = _read_json(summary_path)
    if not isinstance(summary, dict) or summary.get("schema") != "harness.summary/1":
        raise ValueError(f"{summary_path}: not a harness summary (schema harness.summary/1)")
    run = _read_json(root / "run.json") if (root / "run.json").is_file() else {}
    records = []
    trials_dir = root / "trials"
    if trials_dir.is_dir():
        for p in sorted(trials_dir.glob("*.json")):
            try:
                records.append(_read_json(p))
            except (OSError, ValueError):
                continue  # a partial or foreign file: the summary is the reference, records only add detail
    order = {t: i for i, t in enumerate(run.get("trials", []))}
    records.sort(key=lambda r: (order.get(r.get("trial_id"), len(order)), str(r.get("trial_id"))))
    return RunData(root, summary, run, records)


def _read_json(path: Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def load_baseline_summary(baseline: str | Path) -> dict[str, Any]:
    """A baseline run directory's summary (or a summary.json file)."""
    p = Path(baseline)
    p = p / "summary.json" if p.is_dir() else p
    if not p.is_file():
        raise FileNotFoundError(f"baseline {baseline}: no summary.json")
    data = _read_json(p)
    if not isinstance(data, dict) or data.get("schema") != "harness.summary/1":
        raise ValueError(f"{p}: not a harness summary (schema harness.summary/1)")
    return data


# -- formatting ---------------------------------------------------------------------------------------------
def fmt(x: Any, digits: int = 3, unit: str = "") -> str:
    """A number for a table (``n/a`` for None, NaN or non-numbers)."""
    if isinstance(x, bool) or not isinstance(x, int | float) or x != x:
        return "n/a"
    s = f"{x:.{digits}f}" if isinstance(x, float) else str(x)
    return f"{s} {unit}".strip()


def fmt_ci(x: Any, ci: tuple[float, float] | None, digits: int = 3, unit: str = "") -> str:
    """A number with its interval, ``0.812 [0.76, 0.86]`` or ``9.0 [4.0, 14.0] mm`` (one digit fewer for the
    bounds, at least one); the bare number when there is no interval or no number."""
    text = fmt(x, digits)
    if ci is None or text == "n/a":
        return fmt(x, digits, unit)
    d = max(digits - 1, 1)
    return f"{text} [{ci[0]:.{d}f}, {ci[1]:.{d}f}] {unit}".strip()


def value_cell(v: float | Missing, digits: int = 3, unit: str = "", ci: tuple[float, float] | None = None) -> Cell:
    if isinstance(v, Missing):
        return Cell(v.why, "missing" if v.why == NOT_BUILT else "na")
    return Cell(fmt_ci(v, ci, digits, unit), "num")


def headline_rows() -> tuple[Metric, ...]:
    """The rows of the headline table: the headline metrics, the failed trials aside (the table's last row
    counts trials and failures)."""
    return tuple(m for m in metrics.headline() if m.rule != "count")


def rate_metrics() -> tuple[Metric, ...]:
    """The compact metrics that are rates in [0, 1], plotted per group and against swept values."""
    return tuple(m for m in metrics.compact() if m.rule == "rate")


def figure_cell(sections: Mapping[str, Any] | None, m: Metric) -> Cell:
    """The cell of headline metric ``m`` of a method's sections, with its interval when it has one."""
    return value_cell(lookup(sections, m.path), m.digits, m.unit, lookup_interval(sections, m.path))


def ci_cell(sec: Mapping[str, Any] | None, *path: str, digits: int = 3, unit: str = "") -> Cell:
    """A numeric cell of ``sec`` at ``path`` with the interval beside it (if any)."""
    return Cell(fmt_ci(_get(sec, *path), lookup_interval(sec, path), digits, unit), "num")


def _get(d: Mapping[str, Any] | None, *path: str) -> Any:
    node: Any = d
    for k in path:
        if not isinstance(node, Mapping):
            return None
        node = node.get(k)
    return node


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "x"


def why_no_figure(summary: Mapping[str, Any], section: str) -> str:
    """Why a stage of a summary has no figure: every trial failed (and the first reason), or nothing to score."""
    n_ok = summary.get("n_trials", 0) - summary.get("n_failed", 0)
    if not summary.get("n_trials"):
        return "no trial ran"
    if n_ok <= 0:
        first = (summary.get("failures") or [{}])[0].get("reason", "?")
        return f"every trial failed: {first}"
    sec = summary.get(section)
    if section == "pose":
        return "no trial constrained 6 DOF" if not (sec or {}).get("n_constrained") else "no pose was scored"
    if section == "change":
        return "no trial gave a pose (change detection needs one)"
    if section == "classification":
        return f"no patch of >= {(sec or {}).get('min_patch_pixels', MIN_SCORED_PIXELS)} pixels was described"
    return "no trial scored it"


def _not_built(stage: str, methods: Sequence[str], summary: Mapping[str, Any] | None = None) -> Note:
    who = "any method" if len(methods) > 1 else methods[0]
    why = f" ({why_no_figure(summary, stage)})" if summary is not None else ""
    return Note(f"{stage.capitalize()} has no figure: summary.json has {stage}: null for {who}{why}, so there are "
                "no numbers to show.", "missing")


# -- trial ranking (used by ``harness report`` to choose the gallery) -----------------------------------------
def trial_score(record: Mapping[str, Any], method: str = "core") -> tuple[float, str]:
    """A trial's score in [0, 1] (lower is worse) and a sentence saying why.

    The mean of the figures the trial has: Hoover correct-detection rate, classification accuracy over
    patches of 200 pixels or more, pose success (0 or 1) and the fraction of features whose change label is
    right. A failed trial scores -1 (it cannot be drawn; it is listed under failures).
    """
    if record.get("status") != "ok":
        return -1.0, f"failed: {record.get('reason', '')}"
    m = (record.get("methods") or {}).get(method) or {}
    parts: list[tuple[str, float]] = []
    seg = m.get("segmentation")
    if seg and seg.get("correct_detection_rate") is not None:
        parts.append(("correct detection", float(seg["correct_detection_rate"])))
    cls = m.get("classification")
    if cls:
        patches = [p for p in cls.get("patches", []) if p.get("n_pixels", 0) >= MIN_SCORED_PIXELS]
        if patches:
            parts.append((f"accuracy ({len(patches)} patches)",
                          sum(p["truth"] == p["label"] for p in patches) / len(patches)))
    pose = m.get("pose")
    if pose and pose.get("success") is not None:
        parts.append(("pose success", float(bool(pose["success"]))))
    chg = m.get("change")
    if chg and chg.get("features"):
        f = chg["features"]
        parts.append(("change labels right", sum(x["truth"] == x["predicted"] for x in f) / len(f)))
    if not parts:
        return 1.0, "no scored stage"
    score = sum(v for _, v in parts) / len(parts)
    return score, f"score {score:.2f}: " + ", ".join(f"{k} {v:.2f}" for k, v in parts)


def worst_trials(records: Sequence[Mapping[str, Any]], n: int, method: str = "core"
                 ) -> list[tuple[Mapping[str, Any], float, str]]:
    """The ``n`` worst successful trials, worst first (ties broken by trial id): ``(record, score, why)``."""
    scored = [(r, *trial_score(r, method)) for r in records if r.get("status") == "ok"]
    scored.sort(key=lambda t: (t[1], str(t[0].get("trial_id"))))
    return scored[:max(n, 0)]


# -- sections -----------------------------------------------------------------------------------------------
def overview_section(run: RunData) -> Section:
    s, prov = run.summary, run.summary.get("provenance") or run.run.get("provenance") or {}
    rinfo = s.get("run") or {}
    codes = run.run.get("mixed_codes") or prov.get("mixed_codes")
    mixed = [("mixed code", "resumed with --resume-any-code over records of: " + "; ".join(map(code_text, codes)))
             ] if codes else []
    rows = [
        ("suite", str(s.get("suite", "?"))),
        ("suite file", str(run.run.get("source", "n/a"))),
        ("configuration hash", str(s.get("config_hash", "n/a"))),
        ("trials", f"{s.get('n_trials', 0)} run of {s.get('n_planned', s.get('n_trials', 0))} planned, "
                   f"{s.get('n_failed', 0)} failed" + ("" if s.get("complete", True) else " (incomplete run)")),
        ("methods", ", ".join(f"{m} ({METHOD_NOTES.get(m, 'peer method')})" for m in run.methods)),
        ("package version", str(s.get("version", prov.get("version", "n/a")))),
        ("git commit", str(prov.get("git_commit") or "n/a")),
        ("code identity", code_text(run.run.get("code") or prov.get("code"))),
        *mixed,
        ("python", str(prov.get("python", "n/a"))),
        ("libraries", ", ".join(f"{k} {v}" for k, v in (prov.get("libraries") or {}).items()) or "n/a"),
        ("machine", ", ".join(f"{k} {v}" for k, v in (prov.get("machine") or {}).items()) or "n/a"),
        ("wall time", fmt(rinfo.get("wall_s"), 1, "s") + (f" on {rinfo['workers']} worker(s)"
                                                           if rinfo.get("workers") else "")),
        ("throughput", fmt(rinfo.get("trials_per_minute"), 2, "trials/min")),
    ]
    blocks: list[Any] = [Table(("item", "value"), tuple((Cell(k), Cell(v)) for k, v in rows), id="provenance")]
    command = prov.get("command")
    blocks.append(Para("Reproduce the run (same suite, seeds and code give the same summary apart from times and "
                       "provenance), then this report:"))
    suite_ref = run.run.get("source") or s.get("suite", "SUITE")
    recorded = bool(command and command.startswith("harness "))
    bench = command if recorded else f"harness bench --suite {suite_ref} --out {run.root}"
    blocks.append(Code(f"{bench}\nharness report {run.root}"))
    if command and not recorded:
        blocks.append(Para(f"(The run was started from Python; its recorded command line: {command})"))
    cfg = run.run.get("suite_config")
    if cfg:
        import yaml

        blocks.append(Para("Suite configuration as run:"))
        blocks.append(Code(yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None, width=110).rstrip()))
    if not s.get("complete", True):
        blocks.insert(0, Note(f"Incomplete run: {s.get('n_trials')} of {s.get('n_planned')} trials finished; "
                              "figures cover the finished trials only.", "warn"))
    return Section("run", "Run and reproduction", blocks)


def code_text(code: Any) -> str:
    """A run's code identity (``run.json`` ``code``, DESIGN 11.4) in one line: the commit and the hash of the
    uncommitted diff of the packages (or of their files outside git), and the plug-ins' versions."""
    if not isinstance(code, Mapping) or not (code.get("commit") or code.get("source_sha256")):
        return "n/a (not recorded)"
    if code.get("commit"):
        diff = code.get("diff_sha256")
        text = f"commit {str(code['commit'])[:12]}, " + (f"uncommitted diff sha256 {str(diff)[:12]}" if diff
                                                          else "no uncommitted change")
    else:
        text = f"no git checkout, source sha256 {str(code['source_sha256'])[:12]}"
    plugins = code.get("plugins") or {}
    return text + "; plug-ins: " + (", ".join(f"{k} {v}" for k, v in sorted(plugins.items())) or "none")


def headline_section(run: RunData) -> Section:
    s = run.summary
    methods = run.methods
    rows = []
    for m in headline_rows():
        cells = [Cell(m.title), Cell(m.direction)]
        cells += [figure_cell(run.sections(meth), m) for meth in methods]
        rows.append(tuple(cells))
    rows.append((Cell("trials (failed)"), Cell(""),
                 *[Cell(f"{s.get('n_trials', 0)} ({s.get('n_failed', 0)})", "num") for _ in methods]))
    blocks: list[Any] = [
        Table(("metric", "better", *methods), tuple(rows), id="headline",
              caption="All trials pooled. " + "; ".join(f"{m}: {METHOD_NOTES.get(m, 'peer method')}"
                                                        for m in methods) + "."),
        Para(intervals_note(s)),
    ]
    groups = s.get("groups") or {}
    if groups:
        gm = metrics.compact()
        grows = [(Cell(name), Cell(str(g.get("n_trials", "")), "num"),
                  Cell(str(g.get("n_failed", 0)), "bad" if g.get("n_failed") else "num"),
                  *[figure_cell(g, m) for m in gm]) for name, g in groups.items()]
        blocks.append(Table(("group (scene/sensor)", "trials", "failed", *[m.compact for m in gm]), tuple(grows),
                            caption="Per group, core method (DESIGN 10.5: the per-preset figures)."))
        points = group_points(groups)
        if len(groups) > 1 and points:
            blocks.append(Image(figures.group_headline_figure(points), "Headline rates per group, core method "
                                "(dots; bars: 95 % interval over the group's scenes, where it has two or more).",
                                alt="headline rates per group"))
    return Section("headline", "Headline", blocks)


def intervals_note(summary: Mapping[str, Any]) -> str:
    """What the bracketed intervals of the tables are, and how many scenes they rest on."""
    boot = summary.get("ci95_bootstrap")
    if not isinstance(boot, Mapping):
        return "No intervals: this summary.json carries none (written before DESIGN 11.3)."
    n = boot.get("n_clusters", 0)
    scenes = ", ".join(str(c) for c in (boot.get("clusters") or [])[:8])
    more = "" if n <= 8 else f" and {n - 8} more"
    text = (f"In brackets: {100 * float(boot.get('level', 0.95)):.0f} % intervals ({boot.get('method')}: whole "
            f"scenes resampled with replacement, {boot.get('n_boot')} resamples, seed {boot.get('seed')}; trials of "
            "one scene are correlated, so the scene is the unit). ")
    if n < 2:
        return text + (f"This run has {n} scene ({scenes or 'none'}): one scene gives no interval over scenes, so "
                       "none is shown.")
    return text + (f"Pooled over {n} scenes ({scenes}{more}); a group of one scene, or a figure that only one scene "
                   "defines, has none." + (" With so few scenes an interval only shows the spread between them."
                                           if n <= 3 else ""))


def group_points(groups: Mapping[str, Mapping[str, Any]]
                 ) -> dict[str, dict[str, tuple[float, tuple[float, float] | None]]]:
    """metric -> group -> (value, interval or None), for the core's compact rates (:func:`rate_metrics`) that
    some group has."""
    out: dict[str, dict[str, tuple[float, tuple[float, float] | None]]] = {}
    for m in rate_metrics():
        for name, g in groups.items():
            v = lookup(g, m.path)
            if not isinstance(v, Missing):
                out.setdefault(m.compact, {})[name] = (v, lookup_interval(g, m.path))
    return out


def segmentation_section(run: RunData) -> Section:
    methods = run.methods
    secs = {m: _get(run.sections(m), "segmentation") for m in methods}
    if all(v is None for v in secs.values()):
        return Section("segmentation", "Segmentation", [_not_built("segmentation", methods, run.summary)])
    core = next(v for v in secs.values() if v is not None)
    blocks: list[Any] = [Para(
        f"Hoover et al. (1996) region metrics at overlap tolerance T = {core.get('tolerance')}, over truth regions "
        f"of {core.get('min_truth_pixels', 0)} pixels or more ({core.get('n_truth_regions', 'n/a')} regions in "
        f"{core.get('n_images', 'n/a')} images). Correct, over, under and missed are per truth region; noise is "
        "per machine region; rates are averaged over images.")]
    rows = []
    for m, sec in secs.items():
        if sec is None:
            rows.append((Cell(m), *[Cell(NOT_BUILT, "missing") for _ in HOOVER_RATES]))
        else:
            rows.append((Cell(m), *[ci_cell(sec, k) for k in HOOVER_RATES]))
    blocks.append(Table(("method", *HOOVER_HEAD), tuple(rows), caption="Hoover rates (fraction of regions)"))
    sweeps, same_as = distinct_sweeps(secs)
    if sweeps:
        shared = "; ".join(f"{', '.join(others)} score(s) exactly as {m} (the same regions), drawn once with it"
                           for m, others in same_as.items() if others)
        blocks.append(Image(figures.hoover_sweep_figure(sweeps, core.get("tolerance"), same_as),
                            "Hoover rates against the overlap tolerance T: one panel per rate, one line per distinct "
                            "segmentation (grey line: the headline T). Look at how fast correct detection falls "
                            "as T tightens, and what it turns into" + (f"; {shared}" if shared else "") + ".",
                            alt="Hoover metrics vs tolerance"))
    groups = run.summary.get("groups") or {}
    grows = [(Cell(g), *[ci_cell(sec, "segmentation", k) if _get(sec, "segmentation") else
                         Cell(NOT_BUILT, "missing") for k in HOOVER_RATES]) for g, sec in groups.items()]
    if len(grows) > 1:
        blocks.append(Table(("group", *HOOVER_HEAD), tuple(grows), caption="Per group, core method"))
    causes = {name: _get(sec, "segmentation", "missed_causes") for name, sec in
              [("all", run.summary), *groups.items()]}
    causes = {k: v for k, v in causes.items() if v}
    if causes:
        keys = list(next(iter(causes.values())))
        blocks.append(Table(("core method", *keys), tuple((Cell(g), *[Cell(fmt(c.get(k)), "num") for k in keys])
                                                          for g, c in causes.items()),
                            caption="Missed truth regions by cause (fraction of regions; they sum to the missed "
                                    "rate): merged, the largest machine region on it also covers other surfaces; "
                                    "unlabelled, labelling its unlabelled pixels would have been enough; split, "
                                    "the rest"))
    sizes = {name: _get(sec, "segmentation", "by_size") for name, sec in [("all", run.summary), *groups.items()]}
    sizes = {k: v for k, v in sizes.items() if v}
    if sizes:
        bins = next(iter(sizes.values()))
        head = tuple(f"{b['min_pixels']}+ px" if b["max_pixels"] is None else
                     f"{b['min_pixels']}-{b['max_pixels'] - 1} px" for b in bins)
        blocks.append(Table(("core method", *head),
                            tuple((Cell(g), *[Cell(f"{fmt(b.get('correct_detection_rate'))} ({b['n_truth']})", "num")
                                              for b in v]) for g, v in sizes.items()),
                            caption="Correct detection by truth region size (regions of all images counted "
                                    "together; in brackets, how many)"))
    return Section("segmentation", "Segmentation", blocks)


def distinct_sweeps(secs: Mapping[str, Mapping[str, Any] | None]
                    ) -> tuple[dict[str, Any], dict[str, list[str]]]:
    """The Hoover sweeps of the methods, each distinct one once: ``(method -> sweep rows, method drawn -> the
    other methods with exactly the same rows)`` (a peer that reuses the core's segmentation scores as it)."""
    sweeps: dict[str, Any] = {}
    same_as: dict[str, list[str]] = {}
    for m, sec in secs.items():
        rows = (sec or {}).get("sweep")
        if not rows:
            continue
        first = next((d for d, other in sweeps.items() if other == rows), None)
        if first is None:
            sweeps[m], same_as[m] = rows, []
        else:
            same_as[first].append(m)
    return sweeps, same_as


def classification_section(run: RunData, table_trial: str | None) -> Section:
    methods = run.methods
    secs = {m: _get(run.sections(m), "classification") for m in methods}
    if all(v is None for v in secs.values()):
        return Section("classification", "Classification", [_not_built("classification", methods, run.summary)])
    present = {m: v for m, v in secs.items() if v is not None}
    first = next(iter(present.values()))
    blocks: list[Any] = [Para(
        f"Each patch of {first.get('min_patch_pixels', MIN_SCORED_PIXELS)} pixels or more takes the truth class of "
        f"the surface it mostly covers ({first.get('n_patches', 0)} such patches of "
        f"{first.get('n_patches_all', 'n/a')}). Brier score: multi-class over {', '.join(CLASSES)}; ECE: "
        "expected calibration error of the winning label's probability.")]
    rows = [(Cell(m), *([ci_cell(sec, "accuracy"), ci_cell(sec, "brier"),
                         ci_cell(sec, "ece"), Cell(str(sec.get("n_patches", "")), "num")]
                        if sec else [Cell(NOT_BUILT, "missing")] * 4)) for m, sec in secs.items()]
    blocks.append(Table(("method", "accuracy", "Brier", "ECE", "patches"), tuple(rows)))
    head = ["class", "support"]
    for m in present:
        head += [f"precision ({m})", f"recall ({m})"]
    crow = []
    for c in CLASSES:
        support = _get(first, "per_class", c, "support")
        cells = [Cell(c, colour=CLASS_COLOURS[c]), Cell(fmt(support), "num")]
        for sec in present.values():
            cells += [Cell(fmt(_get(sec, "per_class", c, "precision")), "num"),
                      Cell(fmt(_get(sec, "per_class", c, "recall")), "num")]
        crow.append(tuple(cells))
    blocks.append(Table(tuple(head), tuple(crow), caption="Per class (support: truth patches of that class)"))
    rrows = [(Cell(m), Cell(c), Cell(str(r["n"]), "num"), Cell(fmt(100 * r["median_abs_rel_error"]), "num"),
              Cell(fmt(100 * r["median_rel_error"]), "num"), Cell(fmt(r["within_2_sigma"]), "num"))
             for m, sec in present.items() for c, r in (sec.get("radius") or {}).items() if r]
    if rrows:
        blocks.append(Table(("method", "class", "patches", "median |error| (%)", "bias (median error, %)",
                             "within 2 sigma"), tuple(rrows),
                            caption="Fitted radius against the truth, on the patches labelled with their true class"))
    per_class = {m: sec["per_class"] for m, sec in present.items() if sec.get("per_class")}
    if per_class:
        blocks.append(Image(figures.per_class_figure(per_class), "Recall (bars, class colours) and precision "
                            "(diamonds) per truth class.", alt="per-class recall and precision"))
    conf = {m: sec["confusion"] for m, sec in present.items() if sec.get("confusion")}
    if conf:
        blocks.append(Image(figures.confusion_figure(conf), "Confusion matrices: rows are truth classes, columns "
                            "labels; counts of patches, shade = fraction of the row.", alt="confusion matrix"))
    rel = {m: sec["reliability"] for m, sec in present.items() if sec.get("reliability")}
    if rel:
        blocks.append(Image(figures.reliability_figure(rel), "Reliability diagram: how often the winning label is "
                            "right against the probability the method gave it (below: patches per bin).",
                            alt="reliability diagram"))
    paths = decision_path_rows(run, present, first.get("min_patch_pixels", MIN_SCORED_PIXELS))
    if paths:
        blocks.append(Table(("method", "decision path", "patches", "accuracy", "stated confidence", "Brier",
                             "floor", "Brier-optimal floor"), tuple(paths),
                            caption="How sure each decision path of the classifier is (how it reached the label: "
                                    "plane_gate, criterion, elbow, rescue of a merged patch's majority, unexplained "
                                    "OTH); a path whose accuracy falls below its stated confidence overclaims. "
                                    "`python -m harness.bench.confidence RUN` prints the same."))
    subs = [paper_table_section(run, table_trial)]
    reproduction = paper_reproduction_section(run.ok_records(), str(run.summary.get("suite") or ""))
    if reproduction is not None:  # the paper's table against every condition of the run (issue 37)
        subs.append(reproduction)
    return Section("classification", "Classification", blocks, subs)


def decision_path_rows(run: RunData, methods: Mapping[str, Any], min_pixels: int) -> list[tuple[Cell, ...]]:
    """The report's rows of :func:`evaluation.classification.decision_path_table` for every method whose patch
    records say how their labels were reached (``path``), over the successful trials' patches of ``min_pixels``
    pixels or more."""
    out = []
    for m in methods:
        rows = [p for r in run.ok_records() for p in (_get(r, "methods", m, "classification", "patches") or ())
                if p.get("n_pixels", 0) >= min_pixels]
        if not any("path" in p for p in rows):
            continue
        for t in decision_path_table(rows):
            out.append((Cell(m), Cell(t["path"]), Cell(str(t["count"]), "num"), Cell(fmt(t["accuracy"]), "num"),
                        Cell(fmt(t["confidence"]), "num"), Cell(fmt(t["brier"]), "num"), Cell(fmt(t["floor"]), "num"),
                        Cell(fmt(t["optimal_floor"]), "num")))
    return out


def choose_table_trial(run: RunData, gallery: Sequence[GalleryTrial] | None, method: str = "paper") -> str | None:
    """The trial of the paper's classification table: the first gallery trial (so its region numbers can be
    read on the region image), else the first successful trial with ``method``, preferring the mock-up scene."""
    with_method = [r for r in run.ok_records() if method in (r.get("methods") or {})]
    ids = {r["trial_id"] for r in with_method}
    for g in gallery or ():
        if g.trial_id in ids:
            return g.trial_id
    mockup = [r for r in with_method if str(_get(r, "spec", "scene")).startswith("mockup")]
    pick = (mockup or with_method or [None])[0]
    return pick["trial_id"] if pick else None


def paper_table_rows(patches: Sequence[Mapping[str, Any]], core_labels: Mapping[int, str] | None = None,
                     min_pixels: int = MIN_SCORED_PIXELS) -> list[tuple[Cell, ...]]:
    """The paper's table (region, P(cyl), P(sphere), P(cone), class) for the quadric patches: those of
    ``min_pixels`` or more that the method did not label PLAN or whose truth is not PLAN; plus truth and the
    core's label of the same patch when known."""
    rows = []
    for p in sorted(patches, key=lambda q: q["patch"]):
        if p.get("n_pixels", 0) < min_pixels or (p["label"] == "PLAN" and p["truth"] == "PLAN"):
            continue
        pl = p.get("plausibilities") or {}
        ok = p["label"] == p["truth"]
        cells = [Cell(str(p["patch"]), "num"), Cell(str(p["n_pixels"]), "num"),
                 *[Cell(fmt(pl.get(k), 2), "num") for k in ("CYL", "SPH", "CONE")],
                 Cell(p["label"], "good" if ok else "bad", CLASS_COLOURS.get(p["label"], "")),
                 Cell(p["truth"], colour=CLASS_COLOURS.get(p["truth"], "")),
                 Cell(str(p.get("truth_feature") or "none"))]
        if core_labels is not None:
            cl = core_labels.get(int(p["patch"]), "n/a")
            cells.append(Cell(cl, "good" if cl == p["truth"] else "bad", CLASS_COLOURS.get(cl, "")))
        rows.append(tuple(cells))
    return rows


def paper_table_section(run: RunData, trial_id: str | None, method: str = "paper") -> Section:
    sid, title = "paper-table", "The paper's classification table"
    rec = next((r for r in run.ok_records() if r.get("trial_id") == trial_id), None)
    patches = _get(rec, "methods", method, "classification", "patches") if rec else None
    if not patches:
        why = (f"no trial of this run has {method} classification records" if rec is None
               else f"trial {trial_id} has no {method} classification records")
        return Section(sid, title, [Note(f"Not available: {why}.", "missing")])
    core = _get(rec, "methods", "core", "classification", "patches") or []
    core_labels = {int(p["patch"]): p["label"] for p in core}
    rows = paper_table_rows(patches, core_labels if core else None)
    blocks: list[Any] = [Para(
        f"As the table of the paper's section 6, for trial {trial_id} ({_get(rec, 'spec', 'group')}): the "
        f"plausibilities that each quadric region is a cylinder, a sphere or a cone, and the label the paper's "
        f"classifier ({method}) gave it (CYL, SPH or CONE when that plausibility is highest by more than 0.2, "
        "OTH otherwise). Region numbers are the patch ids of the region image in the gallery. Added columns: the "
        "truth class and feature, and the core's label of the same patch. Patches under "
        f"{MIN_SCORED_PIXELS} pixels and planar patches labelled PLAN are not listed.")]
    head = ("region", "pixels", "P(cyl)", "P(sphere)", "P(cone)", "class", "truth", "truth feature")
    if core:
        head = (*head, "core label")
    if rows:
        blocks.append(Table(head, tuple(rows), id="paper-table"))
    else:
        blocks.append(Note(f"No quadric region of {MIN_SCORED_PIXELS} pixels or more in this trial.", "info"))
    agg = paper_plausibility_summary(run.ok_records(), method)
    if agg:
        blocks.append(Table(("truth class", "patches", "mean P(cyl)", "mean P(sphere)", "mean P(cone)",
                             "labelled right"), tuple(agg),
                            caption=f"Over all trials: mean plausibilities of {method} per truth class "
                                    f"(patches of {MIN_SCORED_PIXELS} pixels or more)"))
    return Section(sid, title, blocks)


def paper_plausibility_summary(records: Sequence[Mapping[str, Any]], method: str = "paper"
                               ) -> list[tuple[Cell, ...]]:
    """Per truth class: number of patches, mean plausibilities and the fraction labelled right."""
    by: dict[str, list[Mapping[str, Any]]] = {}
    for r in records:
        for p in _get(r, "methods", method, "classification", "patches") or []:
            if p.get("n_pixels", 0) >= MIN_SCORED_PIXELS:
                by.setdefault(p["truth"], []).append(p)
    rows = []
    for c in CLASSES:
        ps = by.get(c)
        if not ps:
            continue
        mean = {k: sum((p.get("plausibilities") or {}).get(k, 0.0) for p in ps) / len(ps)
                for k in ("CYL", "SPH", "CONE")}
        right = sum(p["label"] == c for p in ps) / len(ps)
        rows.append((Cell(c, colour=CLASS_COLOURS[c]), Cell(str(len(ps)), "num"),
                     *[Cell(fmt(mean[k], 2), "num") for k in ("CYL", "SPH", "CONE")], Cell(fmt(right, 2), "num")))
    return rows


def pose_errors(records: Sequence[Mapping[str, Any]], method: str) -> dict[str, dict[str, list[float]]]:
    """Per-trial pose errors of ``method``: ``{rotation_error_deg: {"after ICP": [...], "initial": [...]}, ...}``."""
    out: dict[str, dict[str, list[float]]] = {"rotation_error_deg": {}, "translation_error_mm": {}}
    for r in records:
        pose = _get(r, "methods", method, "pose")
        if not pose:
            continue
        for key in out:
            if pose.get(key) is not None:
                out[key].setdefault("after ICP", []).append(float(pose[key]))
            if _get(pose, "initial", key) is not None:
                out[key].setdefault("initial", []).append(float(pose["initial"][key]))
    return out


def viewing_angle_deg(T_world_sensor: Any) -> float | None:
    """How far the optical axis (the sensor's z) points below the horizontal, degrees (world z up)."""
    try:
        z = float(T_world_sensor[2][2])
    except (TypeError, IndexError, ValueError):
        return None
    return math.degrees(math.asin(max(-1.0, min(1.0, -z))))


def pose_points(records: Sequence[Mapping[str, Any]], method: str = "core") -> list[dict[str, Any]]:
    """Per trial with a pose of ``method``: its group, median range (m), viewing angle (deg), pose errors after
    ICP and whether the pose was stated ok (for :func:`reports.figures.pose_scatter_figure`)."""
    out = []
    for r in records:
        pose = _get(r, "methods", method, "pose")
        if not pose or pose.get("rotation_error_deg") is None:
            continue
        view = r.get("view") or {}
        out.append({"trial_id": r.get("trial_id"), "group": str(_get(r, "spec", "group")),
                    "range_m": view.get("median_range_m"), "angle_deg": viewing_angle_deg(view.get("T_world_sensor")),
                    "rotation_error_deg": pose.get("rotation_error_deg"),
                    "translation_error_mm": pose.get("translation_error_mm"), "ok": bool(pose.get("ok"))})
    return out


def pose_section(run: RunData) -> Section:
    methods = run.methods
    secs = {m: _get(run.sections(m), "pose") for m in methods}
    if all(v is None for v in secs.values()):
        return Section("pose", "Pose", [_not_built("pose", methods, run.summary)])
    blocks: list[Any] = [Para(
        "Error of the estimated T_world_sensor against the truth (bop_toolkit definitions): rotation "
        "arccos((tr(R_est R_gt') - 1) / 2) in degrees, translation in mm, before (initial, from the matched "
        "invariants) and after ICP. Success: rotation <= 1 deg and translation <= 1 % of the trial's median true "
        "range; 'constrained' counts only trials whose visible surfaces constrain all 6 DOF.")]
    head = ("method", "success", "success (constrained)", "rot. median (deg)", "rot. p90 (deg)", "rot. max (deg)",
            "trans. median (mm)", "trans. p90 (mm)", "trans. max (mm)", "ADD median (mm)")
    rows = []
    for m, p in secs.items():
        for stage, sec in (("after ICP", p), ("initial", _get(p, "initial"))):
            name = f"{m}, {stage}"
            if p is None:
                rows.append((Cell(name), *[Cell(NOT_BUILT, "missing")] * (len(head) - 1)))
                break
            if sec is None:
                continue
            rows.append((Cell(name), ci_cell(sec, "success_rate"), ci_cell(sec, "success_rate_constrained"),
                         *[ci_cell(sec, "rotation_error_deg", k) for k in ("median", "p90", "max")],
                         *[ci_cell(sec, "translation_error_mm", k, digits=1) for k in ("median", "p90", "max")],
                         ci_cell(sec, "add_mm", "median", digits=1)))
    blocks.append(Table(head, tuple(rows)))
    all_errors = {m: pose_errors(run.ok_records(), m) for m in methods}
    errors: dict[str, Any] = {}
    same: dict[str, list[str]] = {}
    for m, e in all_errors.items():
        if not any(e.values()):
            continue
        twin = next((d for d, other in errors.items() if other == e), None)
        if twin is None:
            errors[m], same[m] = e, []
        else:
            same[twin].append(m)
    if errors:
        shared = "; ".join(f"{', '.join(o)} has exactly the poses of {m} (drawn once)" for m, o in same.items() if o)
        blocks.append(Image(figures.pose_cdf_figure(errors, same_as=same), "Cumulative distribution of pose errors "
                            "over trials, before and after ICP (grey line: the 1 deg success threshold; symmetric-log "
                            "axes). Look for the step where the curves meet 1: the share of trials with gross "
                            "errors" + (f"; {shared}" if shared else "") + ".", alt="pose error CDF"))
    else:
        blocks.append(Note("No per-trial pose errors in the trial records: no CDF to draw.", "info"))
    vrows = [(Cell(m), Cell(fmt(p.get("n_ok")), "num"), ci_cell(p, "ok_precision"), Cell(fmt(p.get("ok_wrong")), "num"),
              ci_cell(p, "ok_wrong_rate"), Cell(fmt(p.get("n_conditional")), "num"),
              Cell(fmt(p.get("conditional_wrong")), "num"))
             for m, p in secs.items() if p is not None and p.get("n_ok") is not None]
    if vrows:
        blocks.append(Table(("method", "poses stated ok", "of them right", "ok but wrong", "ok but wrong, share of "
                             "trials", "conditional on one object", "of them wrong"), tuple(vrows),
                            caption="What an ok verdict is worth (right: a success). A conditional pose is not ok: it "
                            "rests on one object alone in some direction and holds only if that object has not moved; "
                            "change detection still judges the rest of the view against it"))
    rel = {m: p["reliability"] for m, p in secs.items() if p is not None and p.get("reliability")}
    if rel:
        blocks.append(Image(figures.reliability_figure(rel, "confidence stated with an ok pose", "ok poses"),
                            "Reliability of the pose verdicts: the fraction of ok poses that are right (a success) "
                            "against the confidence they state; at or above the diagonal the confidence means what "
                            "it says (below: ok poses per bin).", alt="pose reliability diagram"))
    points = pose_points(run.ok_records())
    if points:
        groups = list(dict.fromkeys([*(run.summary.get("groups") or {}), *(p["group"] for p in points)]))
        blocks.append(Image(figures.pose_scatter_figure(points, groups), "The core's pose error after ICP per "
                            "trial against the trial's median range (left) and its viewing angle (right: how far "
                            "the optical axis points below the horizontal); crosses: poses the core did not state "
                            "ok; grey: the success thresholds (1 deg; 1 % of the range). Look for errors that grow "
                            "with range or at grazing views, and for dots above the lines (confident and wrong).",
                            alt="pose error vs range and viewing angle"))
    grows = [(Cell(g), ci_cell(sec, "pose", "success_rate") if _get(sec, "pose") else Cell(NOT_BUILT, "missing"),
              ci_cell(sec, "pose", "rotation_error_deg", "median"),
              ci_cell(sec, "pose", "translation_error_mm", "median", digits=1))
             for g, sec in (run.summary.get("groups") or {}).items()]
    if len(grows) > 1:
        blocks.append(Table(("group", "success", "rot. median (deg)", "trans. median (mm)"), tuple(grows),
                            caption="Per group, core method"))
    return Section("pose", "Pose", blocks)


def change_section(run: RunData) -> Section:
    methods = run.methods
    secs = {m: _get(run.sections(m), "change") for m in methods}
    if all(v is None for v in secs.values()):
        return Section("change", "Change", [_not_built("change", methods, run.summary)])
    present = {m: v for m, v in secs.items() if v is not None}
    blocks: list[Any] = [Para(
        "Per label precision, recall and F1 over the features the truth says are observable from the viewpoint; "
        "macro-F1 over moved, missing, new and altered (unchanged is reported beside it).")]
    rows = [(Cell(m), ci_cell(sec, "macro_f1") if sec else Cell(NOT_BUILT, "missing"),
             ci_cell(sec, "objects", "macro_f1") if sec else Cell(NOT_BUILT, "missing"),
             ci_cell(sec, "displacement_error_mm", "median", digits=1) if sec else Cell(NOT_BUILT, "missing"))
            for m, sec in secs.items()]
    blocks.append(Table(("method", "macro-F1 (features)", "macro-F1 (objects)", "moved: displacement error median "
                                                                               "(mm)"), tuple(rows)))
    head = ["label", "support"]
    for m in present:
        head += [f"precision ({m})", f"recall ({m})", f"F1 ({m})"]
    first = next(iter(present.values()))
    lrows = []
    for lab in CHANGE_LABELS:
        cells = [Cell(lab, colour=CHANGE_COLOURS[lab]), Cell(fmt(_get(first, "per_label", lab, "support")), "num")]
        for sec in present.values():
            cells += [Cell(fmt(_get(sec, "per_label", lab, k)), "num") for k in ("precision", "recall")]
            cells.append(ci_cell(sec, "per_label", lab, "f1"))
        lrows.append(tuple(cells))
    blocks.append(Table(tuple(head), tuple(lrows), caption="Per change label, features"))
    per_label = {m: sec["per_label"] for m, sec in present.items() if sec.get("per_label")}
    if per_label:
        blocks.append(Image(figures.change_f1_figure(per_label), "F1 per change label (n: truth features with "
                            "that label).", alt="per-label change F1"))
    obj = {m: sec["objects"] for m, sec in present.items() if sec.get("objects")}
    if obj:
        orows = [(Cell(lab, colour=CHANGE_COLOURS[lab]),
                  *[ci_cell(o, "per_label", lab, "f1") for o in obj.values()]) for lab in CHANGE_LABELS]
        blocks.append(Table(("label", *[f"F1 ({m})" for m in obj]), tuple(orows), caption="Per change label, objects"))
    return Section("change", "Change", blocks)


def parse_sweep_group(name: str) -> tuple[str, dict[str, float]] | None:
    """``"factory_bay/factory_scanner[noise_scale=2]"`` -> ``("factory_bay/factory_scanner", {"noise_scale": 2.0})``
    (None for a group without swept values)."""
    found = SWEEP_GROUP.findall(name)
    if not found:
        return None
    try:
        values = {k: float(v) for k, v in found}
    except ValueError:
        return None
    return SWEEP_GROUP.sub("", name), values


def sweeps_section(run: RunData) -> Section | None:
    """Metric against each swept parameter (DESIGN 10.13); None when the suite sweeps nothing."""
    series: dict[tuple[str, str, tuple], list[tuple[float, Mapping[str, Any]]]] = {}
    for name, g in (run.summary.get("groups") or {}).items():
        parsed = parse_sweep_group(name)
        if parsed is None:
            continue
        base, values = parsed
        for key, v in values.items():
            others = tuple(sorted((k, x) for k, x in values.items() if k != key))
            series.setdefault((key, base, others), []).append((v, g))
    if not series:
        return None
    blocks: list[Any] = []
    shown = rate_metrics()
    for key in sorted({k for k, _, _ in series}):
        lines: dict[str, list[tuple[float, float | None, tuple[float, float] | None]]] = {}
        rows = []
        for (k, base, others), pts in sorted(series.items()):
            if k != key:
                continue
            suffix = "".join(f" [{a}={b:g}]" for a, b in others)
            for m in shown:
                vals = [(v, None if isinstance(x := lookup(g, m.path), Missing) else x, lookup_interval(g, m.path))
                        for v, g in pts]
                if any(x is not None for _, x, _ in vals):
                    lines[f"{m.compact}, {base}{suffix}"] = vals
            for v, g in sorted(pts, key=lambda t: t[0]):
                rows.append((Cell(base + suffix), Cell(f"{v:g}", "num"), Cell(str(g.get("n_trials", "")), "num"),
                             *[value_cell(lookup(g, m.path), m.digits, m.unit, lookup_interval(g, m.path))
                               for m in shown]))
        if lines:
            blocks.append(Image(figures.sweep_figure(key, lines), f"Metrics against {key} (core method, one point "
                                "per swept value; each value is a group of its own; bars: 95 % interval over the "
                                "group's scenes, where it has two or more).", alt=f"metrics vs {key}"))
        blocks.append(Table(("group", key, "trials", *[m.compact for m in shown]), tuple(rows),
                            caption=f"Swept parameter {key}"))
    return Section("sweeps", "Parameter sweeps", blocks)


REST = "evaluation + overhead"
METHOD_STAGES = tuple(st for st in STAGES if st not in ("sensor", "total"))


def trial_time_budget(record: Mapping[str, Any]) -> dict[str, Any] | None:
    """Where one trial's time went, in seconds: ``{sensor, methods: {method: {stage: s}}, oracles, rest, total}``.

    ``rest`` is the trial record's ``timing_s.total`` minus every timed stage (the sensor, each method's own
    stages, the oracles' re-runs): scoring against the truth (Hoover, classification, pose and change
    metrics, observability casts) and overhead. None for a record without a total.
    """
    t = record.get("timing_s") or {}
    total = t.get("total")
    if not isinstance(total, int | float):
        return None
    methods = {m: {st: float(v) for st in METHOD_STAGES if isinstance(v := (sec.get("timing_s") or {}).get(st),
                                                                       int | float)}
               for m, sec in (record.get("methods") or {}).items() if isinstance(sec, Mapping)}
    oracles = sum(float(v) for o in (record.get("oracles") or {}).values() if isinstance(o, Mapping)
                  for v in (o.get("timing_s") or {}).values() if isinstance(v, int | float))
    sensor = float(t.get("sensor") or 0.0)
    rest = float(total) - sensor - sum(sum(st.values()) for st in methods.values()) - oracles
    return {"sensor": sensor, "methods": methods, "oracles": oracles, "rest": rest, "total": float(total),
            "n_trials": 1}


def time_budget(records: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """The mean of :func:`trial_time_budget` over the trials that have one (means add up: the parts sum to the
    mean total); None when no trial has a total."""
    budgets = [b for r in records if (b := trial_time_budget(r)) is not None]
    if not budgets:
        return None
    n = len(budgets)
    methods: dict[str, dict[str, float]] = {}
    for b in budgets:
        for m, st in b["methods"].items():
            into = methods.setdefault(m, {})
            for k, v in st.items():
                into[k] = into.get(k, 0.0) + v / n
    return {"sensor": sum(b["sensor"] for b in budgets) / n, "methods": methods,
            "oracles": sum(b["oracles"] for b in budgets) / n, "rest": sum(b["rest"] for b in budgets) / n,
            "total": sum(b["total"] for b in budgets) / n, "n_trials": n}


def _quantiles(values: Sequence[float]) -> dict[str, float] | None:
    import numpy as np

    v = [x for x in values if isinstance(x, int | float)]
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90))} if v else None


def timing_section(run: RunData) -> Section:
    methods = run.methods
    timings = {m: _get(run.sections(m), "timing_s") for m in methods}
    timings = {m: t for m, t in timings.items() if t}
    if not timings:
        return Section("timing", "Timing", [Note("No timing in summary.json.", "missing")])
    ok = run.ok_records()
    rest = _quantiles([b["rest"] for r in ok if (b := trial_time_budget(r)) is not None])
    rows = []
    for stage in (*STAGES[:-1], REST, STAGES[-1]):
        cells = [Cell(stage)]
        for k in ("median", "p90"):
            for m, t in timings.items():
                v = rest if stage == REST else t.get(stage)
                if v:
                    cells.append(Cell(fmt(v.get(k), 3), "num"))
                elif m != "core" and stage in METHOD_STAGES:
                    cells.append(Cell("the core's", "na"))  # it reused the core's result: timed once, there
                else:
                    cells.append(Cell("n/a", "na"))
        rows.append(tuple(cells[:1] + _interleave(cells[1:], len(timings))))
    head = ["stage"] + [f"{m} {k} (s)" for m in timings for k in ("median", "p90")]
    blocks: list[Any] = [Para("Seconds per trial. sensor (viewpoint search and scan), evaluation + overhead and total "
                              "are per trial (shared by the methods); the other stages per method. A method that "
                              "reuses a stage of the core (its segmentation, its pose) shows 'the core's': that "
                              "time is counted once, in the core's column. evaluation + overhead is the trial's "
                              "total minus every timed stage: scoring each method against the truth, and the "
                              "runner's bookkeeping."),
                         Table(tuple(head), tuple(rows), id="timing")]
    budget = time_budget(ok)
    if budget is not None:
        blocks.append(Image(figures.time_budget_figure(budget), "The whole trial accounted for (means, so the parts "
                            "add up to the mean total): sensor, each method's own stages, the oracles and "
                            "evaluation + overhead (total minus the timed stages); below, each method by stage. "
                            "Look for the part that dominates.", alt="time budget of a trial"))
    blocks.append(Image(figures.timing_figure(timings), "Median time per stage and method (bars) with the 90th "
                        "percentile (whiskers); the total is in the budget beside it.", alt="stage times"))
    times = [r.get("timing_s") or {} for r in ok]
    isolation = [t["isolated"] - t["total"] for t in times
                 if isinstance(t.get("isolated"), int | float) and isinstance(t.get("total"), int | float)]
    outside = [(name, q) for name, q in (
        ("scene preparation (before the trial, cached per scene)", _quantiles([t.get("prepare") for t in times])),
        ("process isolation (fork and transfer, around the trial)", _quantiles(isolation))) if q]
    if outside:
        blocks.append(Para("Outside the trial's total: " + "; ".join(
            f"{name}: median {q['median']:.3f} s, p90 {q['p90']:.3f} s" for name, q in outside) + "."))
    rinfo = run.summary.get("run") or {}
    if rinfo:
        blocks.append(Para(f"Whole run: {fmt(rinfo.get('wall_s'), 1, 's')} wall time on "
                           f"{rinfo.get('workers', '?')} worker(s), {fmt(rinfo.get('trials_per_minute'), 2)} trials "
                           "per minute."))
    return Section("timing", "Timing", blocks)


def _interleave(cells: list[Cell], n_methods: int) -> list[Cell]:
    """[med_m1, med_m2, p90_m1, p90_m2] -> [med_m1, p90_m1, med_m2, p90_m2]."""
    med, p90 = cells[:n_methods], cells[n_methods:]
    return [c for pair in zip(med, p90, strict=True) for c in pair]


def methods_section(run: RunData) -> Section | None:
    """Peer methods side by side, pooled and per group; None when the run has only the core."""
    if len(run.methods) < 2:
        return None
    shown = [m for m in metrics.compact() if m.rule != "time"]
    scopes: list[tuple[str, Mapping[str, Any]]] = [("all trials", run.summary)]
    scopes += list((run.summary.get("groups") or {}).items())
    rows = []
    for scope_name, scope in scopes:
        for meth in run.methods:
            rows.append((Cell(scope_name), Cell(meth), *[figure_cell(run.sections(meth, scope), m)
                                                         for m in shown]))
    blocks: list[Any] = [
        Para("Every method runs on the same trials and images. " + "; ".join(
            f"{m}: {METHOD_NOTES.get(m, 'peer method')}" for m in run.methods) + "."),
        Table(("scope", "method", *[m.compact for m in shown]), tuple(rows), id="methods"),
    ]
    return Section("methods", "Methods side by side", blocks)


ORACLE_NOTES = {"segmentation": "truth regions fed to the classifier", "classification": "truth classes",
                "pairing": "truth pairings fed to the pose stage", "pose": "true pose fed to change detection"}


def oracles_section(run: RunData) -> Section | None:
    """Stage-isolating oracles beside the end-to-end core (DESIGN 10.10); None when the suite ran none."""
    oracles = run.summary.get("oracles") or {}
    if not oracles:
        return None
    rows = [(Cell(m.title), Cell(m.direction), figure_cell(run.summary, m),
             *[figure_cell(sec, m) for sec in oracles.values()]) for m in metrics.judged()]
    blocks: list[Any] = [
        Para("Each oracle replaces one stage of the core by the truth, so the figures after it show how much of "
             "the end-to-end error that stage causes. " + "; ".join(
                 f"{name}: {ORACLE_NOTES.get(name, 'oracle')}" for name in oracles) + "."),
        Table(("metric", "better", "core (end to end)", *[f"oracle: {o}" for o in oracles]), tuple(rows),
              id="oracles"),
    ]
    attribution = attribute(run.summary)
    if attribution:
        names = list(oracles)
        att_rows = [(Cell(r.figure), value_cell(r.end_to_end, 3, ""),
                     *[Cell("-" if r.cost.get(o) is None else
                            f"{r.cost[o]:+.3g}" + ("" if r.share.get(o) is None else f" ({100 * r.share[o]:.0f} %)"))
                       for o in names]) for r in attribution]
        blocks += [
            Para("Error attribution: what each stage costs each downstream figure (the figure with that stage's "
                 "truth minus end to end, in the better direction), and its share of the end-to-end gap to the "
                 "ideal value."),
            Table(("figure", "end to end", *[f"cost of {o}" for o in names]), tuple(att_rows), id="attribution"),
            *[Para(sentence) for sentence in largest_losses(attribution).values()],
        ]
    return Section("oracles", "Stage oracles", blocks)


TRIAL_PAGES_DIR = "trials_html"  # the per-trial pages of ``harness report --trials``, beside report.html


def trial_page_name(trial_id: str) -> str:
    """The file name of a trial's page in :data:`TRIAL_PAGES_DIR` (the id itself: ids are file-name safe)."""
    return f"{trial_id}.html"


def find_trial_pages(root: Path, trial_ids: Sequence[str]) -> dict[str, str]:
    """trial id -> the href (relative to ``report.html``) of the trial's page, for the pages that exist:
    ``trials_html/<id>.html`` (``harness report --trials``), else ``show/<id>/trial.html`` (``harness show``)."""
    out = {}
    for tid in trial_ids:
        for rel in (f"{TRIAL_PAGES_DIR}/{trial_page_name(tid)}", f"show/{tid}/trial.html"):
            if (root / rel).is_file():
                out[tid] = rel
                break
    return out


def pose_verdict(pose: Mapping[str, Any] | None) -> tuple[str, str]:
    """A pose record in words and a cell style: ``right`` (stated ok and within the success thresholds),
    ``WRONG, stated ok`` (a confident wrong answer), or ``not ok: <why>`` (with ``, was right`` when the
    withheld pose was within the thresholds)."""
    if not pose:
        return "no pose", "na"
    if pose.get("ok"):
        return ("right", "good") if pose.get("success") else ("WRONG, stated ok", "bad")
    why = str(pose.get("reason") or "no reason given")
    short = why.split(";")[0].split(":")[0].split("(")[0].strip() or why
    return f"not ok: {short}" + (", was right" if pose.get("success") else ""), ""


def trial_accuracy(record: Mapping[str, Any], method: str = "core") -> tuple[float | None, int]:
    """The fraction of a trial's scored patches (:data:`MIN_SCORED_PIXELS` or more) labelled with their truth
    class, and how many there are (None, 0 without any)."""
    patches = [p for p in _get(record, "methods", method, "classification", "patches") or []
               if p.get("n_pixels", 0) >= MIN_SCORED_PIXELS]
    if not patches:
        return None, 0
    return sum(p["truth"] == p["label"] for p in patches) / len(patches), len(patches)


def trial_change_f1(record: Mapping[str, Any], method: str = "core") -> float | None:
    """The trial's change macro-F1 over its features (:func:`evaluation.aggregate.aggregate_change`)."""
    from evaluation.aggregate import aggregate_change

    chg = _get(record, "methods", method, "change")
    if not chg or not chg.get("features"):
        return None
    return aggregate_change([chg]).get("macro_f1")


def _num_cell(x: Any, digits: int = 3) -> Cell:
    """A number of the trial index (``n/a`` right-aligned and sorted last)."""
    number = isinstance(x, int | float) and not isinstance(x, bool)
    return Cell(fmt(x, digits), "num" if number else "num na", sort="" if number else "~")


def trial_index_rows(records: Sequence[Mapping[str, Any]], pages: Mapping[str, str], method: str = "core"
                     ) -> tuple[tuple[Cell, ...], ...]:
    """One row per trial: id (linked to its page when it exists), group, scene, the trial's score, correct
    detection, accuracy, pose verdict and errors, change macro-F1, time."""
    rows = []
    for r in records:
        tid = str(r.get("trial_id"))
        link = Cell(tid, "id", href=pages.get(tid, ""))
        spec = r.get("spec") or {}
        head = (link, Cell(str(spec.get("group", ""))), Cell(str(spec.get("scene", ""))))
        total = (r.get("timing_s") or {}).get("total")
        if r.get("status") != "ok":
            rows.append((*head, Cell("failed", "bad", sort="-1"), *[Cell("", "na")] * 6,
                         Cell(f"failed: {r.get('reason', '')}", "bad"), _num_cell(total, 2)))
            continue
        score, _ = trial_score(r, method)
        acc, n = trial_accuracy(r, method)
        pose = _get(r, "methods", method, "pose")
        verdict, style = pose_verdict(pose)
        rows.append((*head, _num_cell(score, 2),
                     _num_cell(_get(r, "methods", method, "segmentation", "correct_detection_rate")),
                     Cell(f"{fmt(acc)} ({n})" if acc is not None else "n/a", "num" if acc is not None else "num na",
                          sort=f"{acc:.6f}" if acc is not None else "~"),
                     Cell(verdict, style),
                     _num_cell((pose or {}).get("rotation_error_deg"), 2),
                     _num_cell((pose or {}).get("translation_error_mm"), 1),
                     _num_cell(trial_change_f1(r, method)), Cell("", "na"), _num_cell(total, 2)))
    return tuple(rows)


TRIAL_INDEX_HEADER = ("trial", "group", "scene", "score", "correct detection", "accuracy (patches)", "pose",
                      "rot. error (deg)", "trans. error (mm)", "change macro-F1", "note", "time (s)")


def trials_section(run: RunData, pages: Mapping[str, str]) -> Section:
    """Every trial of the run in one sortable table, linked to the trial pages that exist."""
    records = run.records
    n_linked = sum(1 for r in records if str(r.get("trial_id")) in pages)
    rows = trial_index_rows(records, pages)
    # the note column only says something for failed trials: leave it out when none failed
    keep = [i for i, h in enumerate(TRIAL_INDEX_HEADER) if h != "note" or any(r[i].text for r in rows)]
    header = tuple(TRIAL_INDEX_HEADER[i] for i in keep)
    rows = tuple(tuple(r[i] for i in keep) for r in rows)
    root = str(run.root)
    blocks: list[Any] = [
        Para(f"All {len(records)} trials, in the run's order; click a column title to sort by it (score: the "
             "gallery's ranking, the mean of the core's correct detection, accuracy, pose success and change "
             "labels right; lower is worse). The figures are the core's. A trial links to its page (every "
             "picture, its patches, pose and changes per method) when the page has been written: "
             f"{n_linked} of {len(records)} here. To write the others:"),
        Code(f"harness show {root} TRIAL_ID              # one trial: {root}/show/TRIAL_ID/trial.html\n"
             f"harness report {root} --trials all        # every trial: {root}/{TRIAL_PAGES_DIR}/TRIAL_ID.html\n"
             f"harness report {root} --trials worst:10   # the 10 worst"),
        Table(header, rows, id="trial-index", sortable=True, markdown=False,
              caption=f"Trials ({len(records)}), core method"),
    ]
    return Section("trials", "Trials", blocks)


def gallery_section(gallery: Sequence[GalleryTrial] | None, pages: Mapping[str, str] | None = None) -> Section:
    if gallery is None:
        return Section("gallery", "Gallery", [Note(
            "No gallery in this rendering: 'harness report RUN_DIR' re-runs the worst trials (deterministically) "
            "to draw their pictures.", "info")])
    if not gallery:
        return Section("gallery", "Gallery", [Note("No successful trial to show.", "info")])
    blocks: list[Any] = [Para(
        "Selected trials, worst first (the mean of the trial's correct-detection rate, classification accuracy, "
        "pose success and change accuracy). Each was re-run from its record (same seeds, same image) to draw: the "
        "range image and its shading, the H-K curvature classes, the truth surfaces and the core's regions in "
        "the truth's colours (numbered as in the paper's table), its classification (red stripes: wrong label), "
        "the truth and predicted change maps, the registration before and after ICP and the scene in 3D. Every "
        "other trial is in the trial index above.")]
    subs = []
    for g in gallery:
        sb: list[Any] = [Para(f"Group {g.group}. {g.why}")]
        if pages and g.trial_id in pages:
            sb.append(Links(((f"the page of {g.trial_id}: its patches, pose and changes per method",
                              pages[g.trial_id]),)))
        if g.panels:
            sb.append(Grid(tuple(g.panels)))
        sb += [Note(n, "missing" if NOT_BUILT in n else "info") for n in g.notes]
        subs.append(Section(f"trial-{_slug(g.trial_id)}", g.trial_id, sb))
    return Section("gallery", "Gallery (worst trials first)", blocks, subs)


def regression_section(run: RunData, base: Mapping[str, Any], base_name: str,
                       comparison: Comparison | None) -> Section:
    """What moved against the baseline run, by how much, and (with the ``comparison`` of ``harness compare``,
    :mod:`evaluation.verdicts`) the verdict: the same headline table, verdict line and trials that moved most."""
    blocks: list[Any] = []
    if comparison is not None:
        text = comparison.verdict_text()
        if comparison.passed:
            blocks.append(Note(f"No regression against {base_name}{text.removeprefix('no regression')} (the rules "
                               "of harness compare).", "pass"))
        else:
            blocks.append(Note(f"Against {base_name}: {text} (the rules of harness compare).", "fail"))
        if comparison.uncounted_line():
            blocks.append(Note(comparison.uncounted_line(), "info"))
        blocks += [Note(n, "warn" if n.startswith("compared with --force") else "info") for n in comparison.notes]
    else:
        blocks.append(Note("Deltas only: no pass/fail verdicts were supplied (run 'harness report RUN_DIR "
                           "--baseline BASE' or 'harness compare BASE RUN_DIR' for them).", "info"))
    if base.get("config_hash") != run.summary.get("config_hash"):
        blocks.append(Note(f"The runs used different suite configurations (hash {base.get('config_hash')} vs "
                           f"{run.summary.get('config_hash')}): differences need not come from the code.", "warn"))
    bprov, cprov = base.get("provenance") or {}, run.summary.get("provenance") or {}
    blocks.append(Table(("", "baseline", "this run"), (
        (Cell("run"), Cell(base_name), Cell(str(run.root))),
        (Cell("suite"), Cell(str(base.get("suite"))), Cell(str(run.summary.get("suite")))),
        (Cell("git commit"), Cell(str(bprov.get("git_commit") or "n/a")), Cell(str(cprov.get("git_commit") or "n/a"))),
        (Cell("code identity"), Cell(code_text(bprov.get("code"))),
         Cell(code_text(run.run.get("code") or cprov.get("code")))),
        (Cell("trials (failed)"), Cell(f"{base.get('n_trials')} ({base.get('n_failed')})"),
         Cell(f"{run.summary.get('n_trials')} ({run.summary.get('n_failed')})")))))
    if comparison is not None:
        return Section("regression", "Regression against the baseline", blocks + _verdict_blocks(comparison))
    rows = []
    for meth in run.methods:
        if meth != "core" and meth not in (base.get("baselines") or {}):
            continue
        for d in headline_deltas(base, run.summary, meth):
            if meth != "core" and not d["delta"] and (d["base"] is None) == (d["candidate"] is None):
                continue  # peers: only what moved
            style = "" if d["better"] is None else ("good" if d["better"] else "bad")
            m = metrics.metric(d["key"])
            rows.append((Cell(meth), Cell(d["label"]), _delta_value(d["base"], base, m, meth),
                         _delta_value(d["candidate"], run.summary, m, meth),
                         Cell("" if d["delta"] is None else f"{d['delta']:+.{m.digits}f}", style or "num"),
                         Cell(d["direction"])))
    blocks.append(Table(("method", "metric", "baseline", "this run", "change", "better"), tuple(rows),
                        caption="Headline metrics: all of the core's, the peers' where they moved "
                                "(green: better, red: worse)"))
    return Section("regression", "Regression against the baseline", blocks)


_VERDICT_STYLE = {"regression": "bad", "missing": "bad", "improved": "good"}


def _verdict_blocks(comparison: Comparison) -> list[Any]:
    """The headline verdict table, the other methods' and the trials that moved most, as ``harness compare``
    prints them (:func:`reports.regression.figure_cells`)."""
    def rows(figs: Sequence[Any]) -> tuple[tuple[Cell, ...], ...]:
        out = []
        for f in figs:
            cells = figure_cells(f)
            style = _VERDICT_STYLE.get(f.verdict, "") if f.counted else ""
            out.append((*(Cell(c) for c in cells[:3]), *(Cell(c, "num") for c in cells[3:7]), Cell(cells[7], style)))
        return tuple(out)

    header = ("method", "metric", "scope", "baseline", "this run", "change", "95 % interval of change", "verdict")
    blocks: list[Any] = [Table(header, rows(shown_figures(comparison, True)), caption=(
        f"Headline metrics of {', '.join(comparison.counted_methods)}, pooled and per group; the interval is of the "
        f"paired per-trial change, {comparison.n_scenes} scene(s) resampled, {comparison.n_pairs} trial(s) paired "
        "by id. A change beyond its tolerance whose interval excludes 0 is a regression; one whose interval "
        "reaches 0 is within noise."))]
    others = shown_figures(comparison, False)
    if others:
        blocks.append(Table(header, rows(others), caption=f"Other methods ({', '.join(comparison.reported_methods)}),"
                            " reported only: pooled, and a group where it is not pass"))
    if comparison.moves:
        blocks.append(Table(MOVES_HEADER, tuple(tuple(Cell(c) for c in move_cells(m)) for m in comparison.moves),
                            caption="What changed most: the core's figures per trial, paired by trial id"))
    return blocks


def _delta_value(v: float | None, summary: Mapping[str, Any], m: Metric, method: str) -> Cell:
    sections = summary if method == "core" else (summary.get("baselines") or {}).get(method)
    if v is not None:
        return Cell(fmt_ci(v, lookup_interval(sections, m.path), m.digits, m.unit), "num")
    return value_cell(lookup(sections, m.path), m.digits, m.unit)


def failures_section(run: RunData) -> Section:
    fails = run.summary.get("failures") or []
    if not fails:
        return Section("failures", "Failures", [Para("No trial failed.")])
    rows = tuple((Cell(str(f.get("trial_id"))), Cell(str(f.get("reason", "")))) for f in fails)
    return Section("failures", "Failures", [Note(f"{len(fails)} trial(s) failed; they are left out of every "
                                                 "figure above.", "warn"), Table(("trial", "reason"), rows)])


# -- the document and the files -----------------------------------------------------------------------------
def build_document(run: RunData, baseline: Mapping[str, Any] | None = None, baseline_name: str = "",
                   gallery: Sequence[GalleryTrial] | None = None,
                   comparison: Comparison | None = None, pages: Mapping[str, str] | None = None) -> Document:
    """The report of ``run`` as a document tree (see :mod:`reports.document`); ``pages``: trial id -> href of
    the trial pages that exist (:func:`find_trial_pages`), linked from the trial index and the gallery."""
    pages = pages or {}
    s = run.summary
    when = _dt.datetime.fromtimestamp((run.root / "summary.json").stat().st_mtime, _dt.UTC)
    subtitle = (f"suite {s.get('suite')} - {s.get('n_trials', 0)} trials, {s.get('n_failed', 0)} failed - "
                f"{when:%Y-%m-%d %H:%M} UTC - {run.root}")
    sections = [headline_section(run), overview_section(run), segmentation_section(run),
                classification_section(run, choose_table_trial(run, gallery)), pose_section(run), change_section(run)]
    sweeps = sweeps_section(run)
    if sweeps is not None:
        sections.append(sweeps)
    sections.append(timing_section(run))
    for extra in (methods_section(run), oracles_section(run)):
        if extra is not None:
            sections.append(extra)
    sections.append(trials_section(run, pages))
    sections.append(gallery_section(gallery, pages))
    if baseline is not None:
        sections.append(regression_section(run, baseline, baseline_name, comparison))
    sections.append(failures_section(run))
    return Document(f"Evaluation report: {s.get('suite', 'run')}", subtitle, sections)


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.chmod(tmp, 0o644)  # a report is for reading (mkstemp creates 0600)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def render_report(run_dir: str | Path, baseline_dir: str | Path | None = None,
                  gallery: Sequence[GalleryTrial] | None = None,
                  comparison: Comparison | None = None) -> tuple[Path, Path]:
    """Write ``report.html`` and ``report.md`` into ``run_dir``.

    Parameters
    ----------
    run_dir : a run directory (``summary.json``, ``run.json``, ``trials/``).
    baseline_dir : another run directory (or its summary.json) to compare against: adds the regression section.
    gallery : pictures of selected trials (``harness report`` re-runs them); None: no gallery.
    comparison : ``harness compare``'s verdict (:class:`evaluation.verdicts.Comparison`) for the regression
        section's pass/fail; without it the section shows deltas only.

    Returns
    -------
    (html_path, md_path)
    """
    run = load_run(run_dir)
    base = load_baseline_summary(baseline_dir) if baseline_dir is not None else None
    pages = find_trial_pages(run.root, [str(r.get("trial_id")) for r in run.records])
    doc = build_document(run, base, str(baseline_dir or ""), gallery, comparison, pages)
    html_path, md_path = run.root / "report.html", run.root / "report.md"
    _write_atomic(html_path, render_html(doc))
    _write_atomic(md_path, render_markdown(doc))
    return html_path, md_path


def image(png: bytes, caption: str, alt: str = "", width_px: int = 660, span: int = 1) -> Image:
    """A gallery panel (convenience for callers building :class:`GalleryTrial` s); ``span`` 2: a wide picture
    that takes a whole row."""
    return Image(png, caption, alt or caption, width_px, span)
