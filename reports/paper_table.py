"""The paper's own classification table beside the plausibilities of the ``paper`` classifier (issue 37).

The reference is the table of section 6 of Fillatreau & Fisher (:data:`PAPER_ROWS`, typed from the paper: its
published values, not a result): 14 quadric regions of a real range image of the factory mock-up, 7 cylinder
patches labelled CYL at P(cyl) 0.21-0.55, and 7 patches labelled OTH (an elbow, a junction between a pipe and
an elbow, and five small noisy planar patches). The paper's claim, tested here in every condition of a run:

- (a) every cylinder patch is labelled CYL, at a plausibility P(cyl) within 0.2-0.55;
- (b) the non-cylindrical quadric patches (elbows, junctions: truth OTH) are labelled OTH;
- (c) planar patches that reach the quadric classifier (small noisy ones the segmentation did not call planar:
  truth PLAN, label not PLAN) are labelled OTH.

A *condition* is a group of the run (a sensor, a noise scale, a viewing distance...), a method with the paper's
classifier (today's reading ``paper`` or one of the unstated choices of :class:`recognition.PaperParams`) and a
patch-size class (patches of >= 200 pixels, or one size bin: a filter at evaluation time). Per condition:
cylinder recall and the P(cyl) quartiles of the method and of the core's ``select`` on the same patches' truth
class, whether the claim holds (one sentence), and a distance to the paper's table (:func:`distance`).

Two entry points share one computation: :func:`paper_reproduction_section` (the report, from a run's trial
records) and ``python -m reports.paper_table`` (Markdown; from a run directory, or from the compact JSON that
``--json`` writes, so a committed JSON regenerates the block of ``docs/paper_reproduction.md``).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.metrics import MIN_SCORED_PIXELS
from recognition.describe import DescribeParams
from reports import generated_blocks as blocks
from reports.document import Cell, Note, Para, Section, Table

__all__ = ["CITATION", "PAPER_ROWS", "PaperRow", "CLAIM_BAND", "SIZE_CLASSES", "Stats", "compact", "conditions",
           "distance", "verdict", "pooled", "markdown", "paper_reproduction_section", "BEGIN", "END", "main"]

CITATION = ("P. Fillatreau and R. B. Fisher, \"Non-polyhedral landmark recognition using 3D depth images and "
            "partially correct models\", Department of Artificial Intelligence, University of Edinburgh: section 6 "
            "(experimental results), the table of quadric patch classification on a real range image of the "
            "factory mock-up (regions numbered as in its figure 3)")


@dataclass(frozen=True)
class PaperRow:
    """One row of the paper's table: region number, plausibilities, the paper's label, and what the region is
    (the text around the table) with its truth class in this project's vocabulary."""

    region: int
    p_cyl: float
    p_sph: float
    p_cone: float
    label: str
    truth: str
    what: str


#: The paper's table, as published (section 6); truth classes from the text around it.
PAPER_ROWS: tuple[PaperRow, ...] = (
    PaperRow(5, 0.05, 0.0, 0.0, "OTH", "OTH", "junction between a horizontal pipe and an elbow"),
    PaperRow(6, 0.48, 0.0, 0.09, "CYL", "CYL", "cylinder"),
    PaperRow(7, 0.54, 0.0, 0.0, "CYL", "CYL", "cylinder"),
    PaperRow(9, 0.47, 0.03, 0.05, "CYL", "CYL", "cylinder"),
    PaperRow(11, 0.55, 0.0, 0.24, "CYL", "CYL", "cylinder"),
    PaperRow(12, 0.33, 0.0, 0.11, "CYL", "CYL", "cylinder"),
    PaperRow(13, 0.21, 0.0, 0.0, "CYL", "CYL", "cylinder"),
    PaperRow(15, 0.34, 0.09, 0.06, "CYL", "CYL", "cylinder"),
    PaperRow(16, 0.0, 0.0, 0.04, "OTH", "PLAN", "small noisy planar patch"),
    PaperRow(18, 0.0, 0.0, 0.01, "OTH", "PLAN", "small noisy planar patch"),
    PaperRow(19, 0.0, 0.0, 0.0, "OTH", "OTH", "elbow between two horizontal pipes"),
    PaperRow(21, 0.32, 0.02, 0.15, "OTH", "PLAN", "small noisy planar patch"),
    PaperRow(22, 0.0, 0.0, 0.05, "OTH", "PLAN", "small noisy planar patch"),
    PaperRow(23, 0.0, 0.0, 0.14, "OTH", "PLAN", "small noisy planar patch"),
)

#: The plausibility band of claim (a): the paper's 7 cylinders lie at P(cyl) 0.21-0.55.
CLAIM_BAND = (0.2, 0.55)
#: A part of the claim holds in a condition when at least this share of its patches satisfy it (the paper's
#: 7 of 7, with room for one patch in ten).
HOLDS_SHARE = 0.9
#: Fewer cylinder patches than this in a condition: too few to tell.
MIN_CYLINDERS = 5
#: The smallest patch the classifier fits (``DescribeParams.min_classify_pixels``): smaller ones are OTH unfitted.
MIN_CLASSIFIED = DescribeParams().min_classify_pixels
#: Patch-size classes (pixels, ``[lo, hi)``, None: no upper bound): all scored patches, then four bins, the first
#: below the scored size (the paper's "small patches containing a small number of noisy measure points").
SIZE_CLASSES: tuple[tuple[int, int | None], ...] = ((MIN_SCORED_PIXELS, None), (MIN_CLASSIFIED, MIN_SCORED_PIXELS),
                                                   (MIN_SCORED_PIXELS, 1000), (1000, 5000), (5000, None))
SCHEMA = "reports.paper_table/1"
CORE = "core"
BEGIN = "<!-- paper-table:begin (generated by `python -m reports.paper_table`, do not edit by hand) -->"
END = "<!-- paper-table:end -->"
_SWEEP = re.compile(r"\[([a-z_]+)=([^\]]+)\]")


def paper_cylinder_values() -> list[float]:
    """P(cyl) of the paper's 7 cylinder patches."""
    return [r.p_cyl for r in PAPER_ROWS if r.truth == "CYL"]


# -- the compact data: what the figures are computed from ---------------------------------------------------------
def _keep(p: Mapping[str, Any]) -> bool:
    """The patches the claim speaks of: true cylinders, true OTH, planar patches labelled other than PLAN; of
    at least ``MIN_CLASSIFIED`` pixels and classified (not OTH for being too small to fit)."""
    if int(p.get("n_pixels", 0)) < MIN_CLASSIFIED or str(p.get("reason", "")).startswith("too small"):
        return False
    return p.get("truth") in ("CYL", "OTH") or (p.get("truth") == "PLAN" and p.get("label") != "PLAN")


def compact(records: Sequence[Mapping[str, Any]], suite: str = "", commit: str = "", dirty: bool = False
            ) -> dict[str, Any]:
    """The per-patch rows the section needs, from a run's trial records: per group and method with a
    classification, ``[n_pixels, truth, label, P(cyl)]`` of the patches that :func:`_keep` keeps (P(cyl)
    rounded to 4 decimals). Plain JSON (``--json``)."""
    groups: dict[str, dict[str, Any]] = {}
    for r in records:
        if r.get("status") != "ok":
            continue
        group = str((r.get("spec") or {}).get("group", ""))
        g = groups.setdefault(group, {"n_trials": 0, "methods": {}})
        g["n_trials"] += 1
        for m, rec in (r.get("methods") or {}).items():
            patches = ((rec or {}).get("classification") or {}).get("patches")
            if patches is None:
                continue
            rows = g["methods"].setdefault(m, [])
            for p in patches:
                if _keep(p):
                    rows.append([int(p["n_pixels"]), str(p["truth"]), str(p["label"]),
                                 round(float((p.get("plausibilities") or {}).get("CYL", 0.0)), 4)])
    for g in groups.values():
        for rows in g["methods"].values():
            rows.sort()
    return {"schema": SCHEMA, "suite": suite, "commit": commit, "uncommitted_changes": dirty,
            "n_trials": sum(g["n_trials"] for g in groups.values()),
            "groups": {k: groups[k] for k in sorted(groups, key=_group_key)}}


def _group_key(name: str) -> tuple:
    values = [(k, float(v)) for k, v in _SWEEP.findall(name) if _is_number(v)]
    return (_SWEEP.sub("", name), tuple(values))


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def group_label(name: str) -> str:
    """``mockup/mockup_laser[noise_scale=0.25][view_distance=0.6]`` -> ``noise x0.25, 0.6 m``, or the group
    with its swept values when it sweeps other things."""
    base, swept = _SWEEP.sub("", name), dict(_SWEEP.findall(name))
    parts = []
    if "noise_scale" in swept:
        parts.append(f"noise x{swept.pop('noise_scale')}")
    if "view_distance" in swept:
        parts.append(f"{swept.pop('view_distance')} m")
    parts += [f"{k}={v}" for k, v in swept.items()]
    return ", ".join(parts) if parts else base


# -- per condition ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Stats:
    """One method's figures over one set of patches."""

    n_cyl: int
    cyl_labelled: int          # true cylinders labelled CYL
    cyl_in_band: int           # true cylinders labelled CYL at P(cyl) within CLAIM_BAND
    cyl_plan: int              # true cylinders labelled PLAN (the segmenter's planar class, or a plane within noise)
    quartiles: tuple[float, float, float] | None   # P(cyl) of the true cylinders
    n_oth: int                 # true OTH (elbows, junctions, ...)
    oth_labelled: int
    n_planar: int              # true PLAN labelled other than PLAN (reached the quadric classifier)
    planar_oth: int
    ks: float | None           # KS distance of the true cylinders' P(cyl) to the paper's 7 values

    @property
    def recall(self) -> float | None:
        return self.cyl_labelled / self.n_cyl if self.n_cyl else None


def _quartiles(values: Sequence[float]) -> tuple[float, float, float] | None:
    if not len(values):
        return None
    q = np.percentile(np.asarray(values, float), [25, 50, 75])
    return float(q[0]), float(q[1]), float(q[2])


def ks_distance(a: Sequence[float], b: Sequence[float]) -> float | None:
    """Two-sample Kolmogorov-Smirnov statistic ``sup |F_a - F_b|`` (None when one is empty)."""
    if not len(a) or not len(b):
        return None
    xa, xb = np.sort(np.asarray(a, float)), np.sort(np.asarray(b, float))
    grid = np.concatenate([xa, xb])
    fa = np.searchsorted(xa, grid, side="right") / len(xa)
    fb = np.searchsorted(xb, grid, side="right") / len(xb)
    return float(np.max(np.abs(fa - fb)))


def stats(rows: Sequence[Sequence[Any]], size: tuple[int, int | None]) -> Stats:
    """The figures of one method's compact rows over the patches of one size class."""
    lo, hi = size
    sel = [r for r in rows if r[0] >= lo and (hi is None or r[0] < hi)]
    cyl = [r for r in sel if r[1] == "CYL"]
    oth = [r for r in sel if r[1] == "OTH"]
    planar = [r for r in sel if r[1] == "PLAN" and r[2] != "PLAN"]
    pc = [float(r[3]) for r in cyl]
    band = sum(1 for r in cyl if r[2] == "CYL" and CLAIM_BAND[0] <= float(r[3]) <= CLAIM_BAND[1])
    return Stats(len(cyl), sum(1 for r in cyl if r[2] == "CYL"), band, sum(1 for r in cyl if r[2] == "PLAN"),
                 _quartiles(pc), len(oth),
                 sum(1 for r in oth if r[2] == "OTH"), len(planar), sum(1 for r in planar if r[2] == "OTH"),
                 ks_distance(pc, paper_cylinder_values()))


def distance(s: Stats) -> float | None:
    """How far a condition is from the paper's table, 0 for the table itself: the KS distance of its cylinders'
    P(cyl) to the paper's 7 values, plus the share of cylinders not labelled CYL, plus the share of the other
    quadric patches (true OTH, and planar patches that reached the quadric classifier) not labelled OTH (0 when
    there are none). In [0, 3]; None without cylinder patches."""
    if not s.n_cyl or s.ks is None:
        return None
    n_other = s.n_oth + s.n_planar
    other_miss = 1.0 - (s.oth_labelled + s.planar_oth) / n_other if n_other else 0.0
    return s.ks + (1.0 - s.cyl_labelled / s.n_cyl) + other_miss


def _share(k: int, n: int) -> bool:
    return k / n >= HOLDS_SHARE


def verdict(s: Stats) -> str:
    """One sentence: whether the paper's claim holds in a condition, with the counts that decide it."""
    if s.n_cyl < MIN_CYLINDERS:
        return f"Too few cylinder patches to tell ({s.n_cyl})."
    # the parts with patches to judge (a condition without elbows or planar quadric patches is silent on them)
    parts = {k: _share(hit, n) for k, hit, n in (("a", s.cyl_in_band, s.n_cyl), ("b", s.oth_labelled, s.n_oth),
                                                 ("c", s.planar_oth, s.n_planar)) if n}
    head = ("Holds" if all(parts.values()) else "Does not hold" if not any(parts.values()) else
            "Holds only for " + " and ".join(_PART_NAMES[k] for k, v in parts.items() if v))
    planar = (f"{s.planar_oth} of {s.n_planar} planar patches that reached the quadric test OTH" if s.n_planar
              else "no planar patch reached the quadric test")
    oth = f"{s.oth_labelled} of {s.n_oth} elbows/junctions OTH" if s.n_oth else "no elbow or junction patch"
    return (f"{head}: {s.cyl_labelled} of {s.n_cyl} cylinders CYL, {s.cyl_in_band} of them at P(cyl) "
            f"{CLAIM_BAND[0]:g}-{CLAIM_BAND[1]:g}; {oth}; {planar}.")


_PART_NAMES = {"a": "the cylinders", "b": "the elbows/junctions", "c": "the planar patches"}


@dataclass(frozen=True)
class Condition:
    group: str
    method: str
    size: tuple[int, int | None]
    stats: Stats
    core: Stats | None

    @property
    def size_label(self) -> str:
        return size_label(self.size)

    @property
    def distance(self) -> float | None:
        return distance(self.stats)


def size_label(size: tuple[int, int | None]) -> str:
    lo, hi = size
    return f">= {lo} px" if hi is None else f"{lo}-{hi - 1} px"


def paper_methods(data: Mapping[str, Any]) -> list[str]:
    """The methods of the compact data with the paper's classifier: ``paper`` first, then the others whose
    name starts with ``paper``, in name order."""
    names = {m for g in data["groups"].values() for m in g["methods"]}
    return sorted((m for m in names if m.startswith("paper")), key=lambda m: (m != "paper", m))


def conditions(data: Mapping[str, Any]) -> list[Condition]:
    """Every condition of the compact data: group x paper method x size class."""
    out = []
    for group, g in data["groups"].items():
        core_rows = g["methods"].get(CORE)
        for m in paper_methods(data):
            rows = g["methods"].get(m)
            if rows is None:
                continue
            for size in SIZE_CLASSES:
                out.append(Condition(group, m, size, stats(rows, size),
                                     stats(core_rows, size) if core_rows is not None else None))
    return out


POOLED = "all groups"


def pooled(data: Mapping[str, Any]) -> list[Condition]:
    """Every method with the paper's classifier over the patches of >= 200 pixels of all groups together (not a
    condition: what each option does on average)."""
    def rows(m: str) -> list | None:
        found = [g["methods"][m] for g in data["groups"].values() if m in g["methods"]]
        return [r for rs in found for r in rs] if found else None

    core = rows(CORE)
    size = SIZE_CLASSES[0]
    return [Condition(POOLED, m, size, stats(rows(m) or [], size), stats(core, size) if core is not None else None)
            for m in paper_methods(data)]


def closest(conds: Sequence[Condition], n: int = 3) -> list[Condition]:
    """The ``n`` conditions nearest the paper's table (:func:`distance`), with enough cylinders to tell."""
    ok = [c for c in conds if c.distance is not None and c.stats.n_cyl >= MIN_CYLINDERS]
    return sorted(ok, key=lambda c: (c.distance, c.group, c.method, c.size[0], math.inf if c.size[1] is None
                                     else c.size[1]))[:n]


# -- rendering ----------------------------------------------------------------------------------------------------
def _f(x: float | None, digits: int = 2) -> str:
    return "n/a" if x is None else f"{x:.{digits}f}"


def _q(q: tuple[float, float, float] | None) -> str:
    return "n/a" if q is None else f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f}"


def _rec(s: Stats | None) -> str:
    if s is None or not s.n_cyl:
        return "n/a"
    return f"{s.recall:.2f} ({s.cyl_labelled}/{s.n_cyl})"


CONDITION_HEAD = ("condition", "method", "patches", "cyl recall", "P(cyl) q1 / median / q3", "in band",
                  "cyl as PLAN", "OTH: elbow etc.", "OTH: planar", "select recall", "select P(cyl) q1 / median / q3",
                  "distance", "the paper's claim")


def condition_cells(c: Condition) -> tuple[str, ...]:
    s = c.stats
    return (group_label(c.group), c.method, c.size_label, _rec(s), _q(s.quartiles),
            f"{s.cyl_in_band}/{s.n_cyl}", str(s.cyl_plan), f"{s.oth_labelled}/{s.n_oth}",
            f"{s.planar_oth}/{s.n_planar}",
            _rec(c.core), _q(c.core.quartiles if c.core else None), _f(c.distance), verdict(s))


def paper_rows_cells() -> list[tuple[str, ...]]:
    return [(str(r.region), f"{r.p_cyl:.2f}", f"{r.p_sph:.2f}", f"{r.p_cone:.2f}", r.label, r.truth, r.what)
            for r in PAPER_ROWS]


PAPER_HEAD = ("region", "P(cyl)", "P(sphere)", "P(cone)", "class", "truth", "what it is")


def _md_table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(x).replace("|", "/") for x in r) + " |" for r in rows]
    return lines


def tables(data: Mapping[str, Any]) -> tuple[list[Condition], list[Condition], list[Condition]]:
    """``(by method, by size, closest)``: every method on the patches of >= 200 pixels; ``paper`` per size bin;
    the three conditions nearest the paper's table."""
    conds = conditions(data)
    by_method = [c for c in conds if c.size == SIZE_CLASSES[0]]
    by_size = [c for c in conds if c.method == "paper" and c.size != SIZE_CLASSES[0]]
    return by_method, by_size, closest(conds)


def summary_sentences(data: Mapping[str, Any]) -> list[str]:
    """What the figures say, generated: whether any condition reproduces the table, and the nearest ones."""
    conds = [c for c in conditions(data) if c.stats.n_cyl >= MIN_CYLINDERS]
    holds = [c for c in conds if verdict(c.stats).startswith("Holds:")]
    near = closest(conds)
    out = []
    if holds:
        out.append("The paper's claim holds in " + "; ".join(
            f"{group_label(c.group)}, {c.method}, {c.size_label}" for c in holds) + ".")
    else:
        out.append(f"No condition of this run reproduces the paper's table: in none of the {len(conds)} conditions "
                   f"with at least {MIN_CYLINDERS} cylinder patches are {HOLDS_SHARE:.0%} of them CYL at P(cyl) "
                   f"{CLAIM_BAND[0]:g}-{CLAIM_BAND[1]:g} with the other quadric patches OTH.")
    best = max(conds, key=lambda c: (c.stats.cyl_in_band / c.stats.n_cyl, c.stats.n_cyl), default=None)
    if best is not None:
        share = best.stats.cyl_in_band / best.stats.n_cyl
        k = len(paper_cylinder_values())
        out.append(f"The largest share of cylinders CYL at P(cyl) {CLAIM_BAND[0]:g}-{CLAIM_BAND[1]:g} is "
                   f"{best.stats.cyl_in_band}/{best.stats.n_cyl} ({group_label(best.group)}, {best.method}, "
                   f"{best.size_label}): {k} cylinders drawn from that condition would all be so with probability "
                   f"{share:.2f}^{k} = {share ** k:.2g}, where the paper has {k} of {k}.")
    if near:
        out.append("Closest to it (distance 0 is the paper's table): " + "; ".join(
            f"{group_label(c.group)}, {c.method}, {c.size_label} ({_f(c.distance)}: recall "
            f"{_f(c.stats.recall)}, median P(cyl) {_f(c.stats.quartiles[1] if c.stats.quartiles else None)}, "
            f"{c.stats.cyl_in_band}/{c.stats.n_cyl} in band)" for c in near) + ".")
    return out


def markdown(data: Mapping[str, Any]) -> str:
    """The generated block of ``docs/paper_reproduction.md``."""
    by_method, by_size, near = tables(data)
    paper_cyl = paper_cylinder_values()
    dirty = " with uncommitted changes" if data.get("uncommitted_changes") else ""
    lines = [f"Suite `{data.get('suite') or 'n/a'}`, {data.get('n_trials', 0)} trials, commit "
             f"`{(data.get('commit') or 'n/a')[:12]}`{dirty}.", "",
             f"**The paper's table** (the reference, typed from the paper: {CITATION}). Its 7 cylinders: recall "
             f"1.00 (7/7), P(cyl) quartiles {_q(_quartiles(paper_cyl))}; its 7 other patches all OTH.", ""]
    lines += _md_table(PAPER_HEAD, paper_rows_cells())
    lines += ["", "**Every method with the paper's classifier, patches of >= 200 pixels** (counts are patches: "
              "cylinders CYL / all true cylinders; in band: CYL at P(cyl) 0.2-0.55; cyl as PLAN: true cylinders "
              "labelled PLAN; OTH: elbows and junctions "
              "(truth OTH) labelled OTH, and planar patches that reached the quadric test labelled OTH; select: the "
              "core's classifier on the same scans):", ""]
    lines += _md_table(CONDITION_HEAD, [condition_cells(c) for c in by_method])
    lines += ["", "**Each method over all groups together** (patches of >= 200 pixels):", ""]
    lines += _md_table(CONDITION_HEAD, [condition_cells(c) for c in pooled(data)])
    lines += ["", "**`paper` by patch size**:", ""]
    lines += _md_table(CONDITION_HEAD, [condition_cells(c) for c in by_size])
    lines += ["", "**The conditions closest to the paper's table** (any method and patch size):", ""]
    lines += _md_table(CONDITION_HEAD, [condition_cells(c) for c in near])
    lines += [""] + summary_sentences(data)
    return "\n".join(lines) + "\n"


def paper_reproduction_section(records: Sequence[Mapping[str, Any]], suite: str = "") -> Section | None:
    """The report's section (a subsection of the classification); None when no trial has a method with the
    paper's classifier."""
    data = compact(records, suite)
    if not paper_methods(data):
        return None
    by_method, by_size, near = tables(data)
    sid, title = "paper-reproduction", "The paper's table against this run's conditions"
    blocks: list[Any] = [
        Para("The table of the paper's section 6 (the reference, typed from the paper: " + CITATION + "), then, "
             "per condition of this run (group, method with the paper's classifier, patch size), the cylinder "
             "recall and the P(cyl) quartiles of the true cylinder patches beside the core's select on the same "
             "scans, and whether the paper's claim holds there: all cylinders CYL at P(cyl) 0.2-0.55, elbows, "
             "junctions and the small noisy planar patches that reach the quadric test OTH (at least 90 % of "
             "each). Distance: KS distance of the cylinders' P(cyl) to the paper's 7 values + share of cylinders "
             "not CYL + share of other quadric patches not OTH (0 is the paper's table)."),
        Table(PAPER_HEAD, tuple(paper_rows_cells()), caption="The paper's table (its published values)"),
    ]
    if by_method:
        blocks.append(Table(CONDITION_HEAD, tuple(tuple(Cell(x) for x in condition_cells(c)) for c in by_method),
                            caption="Every method with the paper's classifier, patches of >= 200 pixels",
                            sortable=True))
    blocks.append(Table(CONDITION_HEAD, tuple(tuple(Cell(x) for x in condition_cells(c)) for c in pooled(data)),
                        caption="Each method over all groups together, patches of >= 200 pixels"))
    if by_size:
        blocks.append(Table(CONDITION_HEAD, tuple(tuple(Cell(x) for x in condition_cells(c)) for c in by_size),
                            caption="paper by patch size", sortable=True))
    if near:
        blocks.append(Table(CONDITION_HEAD, tuple(tuple(Cell(x) for x in condition_cells(c)) for c in near),
                            caption="The conditions closest to the paper's table (any method and patch size)"))
    blocks += [Note(s, "info") for s in summary_sentences(data)]
    return Section(sid, title, blocks)


# -- the command --------------------------------------------------------------------------------------------------
def _records(run_dir: Path) -> list[dict[str, Any]]:
    out = []
    for p in sorted((run_dir / "trials").glob("*.json")):
        try:
            out.append(json.loads(p.read_text(encoding="utf-8")))
        except (OSError, ValueError):
            continue
    return out


def load_compact(source: str | Path) -> dict[str, Any]:
    """The compact data of a run directory (its trial records) or of a JSON written by ``--json``."""
    path = Path(source)
    if path.is_dir():
        run = json.loads((path / "run.json").read_text(encoding="utf-8")) if (path / "run.json").is_file() else {}
        code = run.get("code") or {}
        commit = str(code.get("commit") or (run.get("provenance") or {}).get("git_commit") or "")
        return compact(_records(path), str(run.get("suite", "") or ""), commit, bool(code.get("diff_sha256")))
    data = json.loads(path.read_text(encoding="utf-8"))
    if not isinstance(data, dict) or data.get("schema") != SCHEMA:
        raise ValueError(f"{path}: not a {SCHEMA} file (write one with --json)")
    return data


def replace_block(text: str, block: str, source: str = "<text>") -> str:
    """``text`` with its generated block (between :data:`BEGIN` and :data:`END`) replaced by ``block``."""
    return blocks.replace_block(text, block, BEGIN, END, source)


def generated_block(text: str) -> str:
    """What lies between the markers of ``text`` (the part :func:`replace_block` writes)."""
    return blocks.generated_block(text, BEGIN, END)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m reports.paper_table", description=(
        "The paper's classification table beside the paper classifier's plausibilities per condition (issue 37)."))
    ap.add_argument("source", help="a run directory (its trials/) or a JSON written by --json")
    ap.add_argument("--json", type=Path, help="also write the compact per-patch data (what the figures come from)")
    ap.add_argument("--into", type=Path, help="replace the generated block of this Markdown file instead of printing")
    args = ap.parse_args(argv)
    try:
        data = load_compact(args.source)
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json is not None:
        args.json.write_text(json.dumps(data, indent=None, separators=(",", ":")) + "\n", encoding="utf-8")
    block = markdown(data)
    if args.into is None:
        sys.stdout.write(block)
        return 0
    try:
        args.into.write_text(replace_block(args.into.read_text(encoding="utf-8"), block, str(args.into)),
                             encoding="utf-8")
    except (OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
