"""Compare a candidate run with a base run (DESIGN 10.9, 11.3): the inputs, whether they are comparable, the
verdict and its text.

The verdict itself (which figures are judged, the paired intervals, the rules) is
:mod:`evaluation.verdicts`, shared with the report's regression section; this module reads the two run
directories (``summary.json``, ``run.json``, ``trials/*.json``), checks that they ran the same trials
(:func:`run_differences`), pairs their trials by trial id and writes the result as text or Markdown
(:func:`format_comparison`).

Two runs are comparable when they ran the same suite (name), the same trial-defining configuration (the
suite's seed and groups: scenes, perturbation and noise seeds, viewpoints, sensors, sweeps; and the files the
suite refers to, through the configuration hash) and the same trial ids. The methods' parameters may differ
(that is what a candidate often changes): it is noted, not refused.

Every numeric leaf (:func:`compare`, :func:`flatten`) is still available, listed by ``harness compare --all``:
each leaf becomes a dotted metric path (``classification.per_class.CYL.recall``,
``groups.mockup/mockup_laser.segmentation.over_rate``...) with the direction and tolerance rule of the
declaration of :mod:`evaluation.metrics` that covers it (never guessed from its name) and a per-leaf tolerance
word. Those words are informative: only the headline verdict decides. A leaf declared informative (a count, a
setting) has no direction; a leaf that no declaration covers is ``undeclared`` (and the comparison's notes
say how many there are), never silently skipped. A leaf that went from a value to null inside a section that
is still there (a per-class precision with no patch of that label any more) is ``undefined``, not a loss. The
95 % intervals (``*_ci95`` keys, ``ci95_bootstrap``) are not metrics, and the subtrees declared informative
as a whole (``provenance``, ``view``, the sweep...) are tables, not figures: they are not listed.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from evaluation import metrics
from evaluation.metrics import SECTIONS, Metric
from evaluation.verdicts import (
    DEFAULT_TOLERANCES,
    Comparison,
    Tolerances,
    TrialPair,
    compare_runs,
    methods_of,
    tolerance_side,
)
from harness.provenance import describe_code
from harness.summary import scene_of
from reports.regression import HEADLINE_HEADER, MOVES_HEADER, figure_cells, move_cells, shown_figures
from scenes.config import show

__all__ = ["Tolerances", "Comparison", "CompareError", "RunResults", "load_run", "run_differences",
           "pair_trials", "compare_dirs", "format_comparison", "compare", "regressions", "flatten", "format_rows",
           "direction", "undeclared_note"]

TOLERANCES_DIR = Path(__file__).parent / "tolerances"


@dataclass(frozen=True)
class Row:
    metric: str
    base: float | None
    candidate: float | None
    direction: str  # "higher" or "lower" (its declaration's), or "" (informative or undeclared)
    # "ok", "regression", "improved", "missing" (section lost), "undefined", "new", "undeclared" (no declaration
    # covers the leaf), "" (not judged: informative, or a time without --check-time)
    verdict: str

    @property
    def delta(self) -> float | None:
        if self.base is None or self.candidate is None:
            return None
        return self.candidate - self.base


class CompareError(ValueError):
    """An input that cannot be compared (unreadable, not a summary)."""


def load_summary(path: str | Path) -> dict[str, Any]:
    """A run directory's ``summary.json``, or a summary file itself."""
    p = Path(path)
    if p.is_dir():
        p = p / "summary.json"
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CompareError(f"{p}: no such file") from None
    except (OSError, ValueError) as exc:
        raise CompareError(f"{p}: unreadable summary ({exc})") from None
    if not isinstance(data, dict) or data.get("schema") != "harness.summary/1":
        raise CompareError(f"{p}: not a harness summary (schema harness.summary/1)")
    return data


def _leaves(summary: dict[str, Any]) -> dict[str, tuple[tuple[str, ...], float | None]]:
    """Dotted path -> (key path, value) of :func:`evaluation.metrics.leaves`."""
    return {".".join(path): (path, v) for path, v in metrics.leaves(summary)}


def flatten(node: dict[str, Any]) -> dict[str, float | None]:
    """Numeric leaves (and null sections) of a summary as dotted paths (intervals and the subtrees declared
    informative as a whole left out)."""
    return {k: v for k, (_, v) in _leaves(node).items()}


def direction(path: tuple[str, ...] | str) -> str:
    """The better direction of the summary leaf at ``path`` (a key tuple, or a dotted path whose group names hold
    no dot), from its declaration: ``higher``, ``lower``, or ``""`` (informative or undeclared)."""
    d = metrics.declaration(tuple(path.split(".")) if isinstance(path, str) else path)
    return d.direction if isinstance(d, Metric) else ""


def compare(base: dict[str, Any], candidate: dict[str, Any], tol: Tolerances = DEFAULT_TOLERANCES) -> list[Row]:
    """Every numeric leaf of both summaries with its per-leaf tolerance word (informative, for ``--all``; the
    verdict of a comparison is :func:`compare_dirs`'s), by the declarations of :mod:`evaluation.metrics`."""
    fb, fc = _leaves(base), _leaves(candidate)
    paths = {k: p for k, (p, _) in (*fc.items(), *fb.items())}
    rows = []
    lost = sorted(k for k, (p, v) in fc.items() if v is None and p[-1] in SECTIONS
                  and any(m.startswith(k + ".") for m in fb))
    rows += [Row(k, None, None, "", "regression") for k in lost]  # present in base, null in candidate
    for key in sorted(paths):
        path = paths[key]
        b, c = (fb.get(key) or (None, None))[1], (fc.get(key) or (None, None))[1]
        if path[-1] in SECTIONS and b is None and c is None:
            continue
        if any(key.startswith(k + ".") for k in lost):
            continue
        decl = metrics.declaration(path)
        if isinstance(decl, Metric):
            rest = ".".join(metrics.split_scope(path)[1])
            rows.append(Row(key, b, c, decl.direction, _verdict(decl, key, rest, b, c, tol)))
        elif decl is None and not (b is None and c is None and metrics.covers_node(path)):
            rows.append(Row(key, b, c, "", "undeclared"))
        else:
            rows.append(Row(key, b, c, "", ""))
    return rows


def _verdict(m: Metric, path: str, key: str, b: float | None, c: float | None, tol: Tolerances) -> str:
    if b is None and c is None:
        return ""
    if c is None:
        return "undefined"  # a value became null inside a section that is there: nothing to score
    if b is None:
        return "new"
    if m.rule == "time" and not tol.check_time:
        return ""
    side = tolerance_side(m, b, c, tol, tol.allowance(path, key))
    return "regression" if side < 0 else ("improved" if side > 0 else "ok")


def undeclared_note(*summaries: dict[str, Any], limit: int = 3) -> str:
    """One line naming the numeric leaves of the summaries that no declaration of :mod:`evaluation.metrics`
    covers (empty when there are none)."""
    found = sorted({p for s in summaries for p in metrics.undeclared(s)})
    if not found:
        return ""
    more = f" and {len(found) - limit} more" if len(found) > limit else ""
    return (f"{len(found)} numeric leaf(s) of summary.json are declared by no metric of evaluation/metrics.py "
            f"(listed as undeclared by --all, judged by nothing): {', '.join(found[:limit])}{more}")


def regressions(rows: list[Row]) -> list[Row]:
    """Leaves beyond their tolerance in the bad direction, or whose section was lost (informative: the verdict
    of a comparison is :class:`evaluation.verdicts.Comparison`'s)."""
    return [r for r in rows if r.verdict in ("regression", "missing")]


#: the per-leaf words of ``--all`` (informative, so not the verdict's words)
LEAF_WORDS = {"regression": "worse", "improved": "better", "missing": "lost", "undefined": "undefined",
              "new": "new", "undeclared": "undeclared", "ok": "", "": ""}


def format_rows(rows: list[Row], fmt: str = "text", only_changes: bool = False) -> str:
    """Every leaf as a table, ``text`` (aligned columns) or ``md`` (Markdown): base, candidate, delta, which way
    is better, and whether it moved beyond its tolerance (``worse``/``better``), lost its section (``lost``),
    became null within it (``undefined``) or has no declaration (``undeclared``). ``only_changes``: the leaves
    that moved or changed state only (and the undeclared ones)."""
    shown = [r for r in rows if not only_changes or r.verdict in ("regression", "missing", "improved", "new",
                                                                   "undefined", "undeclared")
             or (r.delta not in (None, 0.0))]

    def num(x: float | None) -> str:
        return "null" if x is None else f"{x:.6g}"

    body = [(r.metric, num(r.base), num(r.candidate), "" if r.delta is None else f"{r.delta:+.4g}", r.direction,
             LEAF_WORDS.get(r.verdict, r.verdict)) for r in shown]
    return _table(("metric", "base", "candidate", "delta", "better", "beyond tolerance"), body, fmt)


def _table(header: Sequence[str], body: Sequence[Sequence[str]], fmt: str) -> str:
    """Rows as aligned text columns or a Markdown table."""
    if fmt == "md":
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |" for cells in body]
        return "\n".join(lines)
    widths = [max(len(h), *(len(c[i]) for c in body)) if body else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True)).rstrip()]
    lines += ["  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)).rstrip() for cells in body]
    return "\n".join(lines)


# -- the two runs -------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class RunResults:
    """What a comparison reads of one run: its summary, its manifest (``run.json``, empty when absent) and its
    trial records (empty when there is no ``trials/`` directory, e.g. a lone summary file)."""

    path: Path
    summary: dict[str, Any]
    manifest: dict[str, Any]
    records: tuple[dict[str, Any], ...]

    @property
    def code(self) -> Any:
        """The run's code identity entry (``run.json``, else the summary's provenance), None if unrecorded."""
        return self.manifest.get("code") or (self.summary.get("provenance") or {}).get("code")

    @property
    def trial_ids(self) -> tuple[str, ...] | None:
        """The trials the run holds: its records' ids, else run.json's list, else None (unknown)."""
        if self.records:
            return tuple(sorted(str(r.get("trial_id")) for r in self.records))
        trials = self.manifest.get("trials")
        return tuple(sorted(map(str, trials))) if isinstance(trials, list) else None


def _read(path: Path, what: str) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CompareError(f"{path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise CompareError(f"{path}: unreadable {what} ({exc})") from None


def load_run(path: str | Path) -> RunResults:
    """A run directory (or its ``summary.json``): the summary, ``run.json`` and ``trials/*.json`` beside it.

    Raises
    ------
    CompareError
        A missing or unreadable summary, run.json or trial record (one line naming the file).
    """
    p = Path(path)
    summary = load_summary(p)
    root = p if p.is_dir() else (p.parent if p.name == "summary.json" else None)
    if root is None:
        return RunResults(p, summary, {}, ())
    manifest = _read(root / "run.json", "run.json") if (root / "run.json").is_file() else {}
    if not isinstance(manifest, dict):
        raise CompareError(f"{root / 'run.json'}: not a run manifest (expected a mapping)")
    records = []
    for f in sorted((root / "trials").glob("*.json")) if (root / "trials").is_dir() else []:
        rec = _read(f, "trial record")
        if not isinstance(rec, dict) or "trial_id" not in rec:
            raise CompareError(f"{f}: not a trial record (no trial_id)")
        records.append(rec)
    return RunResults(root, summary, manifest, tuple(records))


TRIAL_KEYS_SKIPPED = ("name", "methods", "oracles", "timeout_s")  # suite keys that do not define the trials


def _trial_config(manifest: Mapping[str, Any]) -> dict[str, Any] | None:
    cfg = manifest.get("suite_config")
    return {k: v for k, v in cfg.items() if k not in TRIAL_KEYS_SKIPPED} if isinstance(cfg, dict) else None


def _rest_config(manifest: Mapping[str, Any]) -> dict[str, Any] | None:
    cfg = manifest.get("suite_config")
    return {k: cfg.get(k) for k in TRIAL_KEYS_SKIPPED if k != "name"} if isinstance(cfg, dict) else None


def run_differences(base: RunResults, candidate: RunResults) -> list[str]:
    """How two runs differ in what defines their trials (empty: comparable).

    Checked: the suite name; from ``run.json`` the suite's seed, its groups (and every other trial-defining
    key: all but name, methods, oracles, timeout_s) and, when those and the rest are equal, the configuration
    hash (it covers the scene and perturbation files the suite refers to); the trial ids (of the records, else
    of run.json). Without run.json or records: the number of trials and the group names of the summaries.
    """
    out = []
    bs, cs = base.summary, candidate.summary
    if bs.get("suite") != cs.get("suite"):
        out.append(f"suite {bs.get('suite')!r} vs {cs.get('suite')!r}")
    bt, ct = _trial_config(base.manifest), _trial_config(candidate.manifest)
    if bt is not None and ct is not None:
        for key in sorted(set(bt) | set(ct)):
            if key == "groups":
                continue
            if bt.get(key) != ct.get(key):
                out.append(f"suite {key} {show(bt.get(key))} vs {show(ct.get(key))}")
        out += _group_differences(bt.get("groups") or [], ct.get("groups") or [])
        same_rest = _rest_config(base.manifest) == _rest_config(candidate.manifest)
        bh, ch = base.manifest.get("config_hash"), candidate.manifest.get("config_hash")
        if not out and same_rest and bh != ch:
            out.append(f"the suite's scene or perturbation files differ (configuration hash {bh} vs {ch} with the "
                       "same suite configuration)")
    bi, ci = base.trial_ids, candidate.trial_ids
    if bi is not None and ci is not None:
        only_b, only_c = sorted(set(bi) - set(ci)), sorted(set(ci) - set(bi))
        if only_b or only_c:
            parts = [f"{len(x)} only in {w} (e.g. {x[0]})" for x, w in ((only_b, "base"), (only_c, "candidate")) if x]
            out.append("trial ids: " + ", ".join(parts))
    elif bt is None or ct is None:
        if bs.get("n_trials") != cs.get("n_trials"):
            out.append(f"n_trials {bs.get('n_trials')} vs {cs.get('n_trials')}")
        if set(bs.get("groups") or {}) != set(cs.get("groups") or {}):
            out.append(f"groups {sorted(bs.get('groups') or {})} vs {sorted(cs.get('groups') or {})}")
    return out


def _group_differences(base: list[Any], candidate: list[Any], limit: int = 2) -> list[str]:
    if len(base) != len(candidate):
        return [f"{len(base)} group(s) vs {len(candidate)}"]
    out = []
    for i, (b, c) in enumerate(zip(base, candidate, strict=True)):
        if b == c:
            continue
        if not isinstance(b, dict) or not isinstance(c, dict):
            out.append(f"group {i + 1}: {show(b)} vs {show(c)}")
            continue
        keys = [k for k in sorted(set(b) | set(c)) if b.get(k) != c.get(k)]
        out += [f"group {i + 1} {k} {show(b.get(k))} vs {show(c.get(k))}" for k in keys]
    return out[:limit] + ([f"and {len(out) - limit} more group difference(s)"] if len(out) > limit else [])


def run_notes(base: RunResults, candidate: RunResults) -> list[str]:
    """What differs without making the runs incomparable: the methods' parameters; records that are not the
    summary's trials."""
    notes = []
    bm = (base.manifest.get("suite_config") or {}).get("methods")
    cm = (candidate.manifest.get("suite_config") or {}).get("methods")
    if bm is not None and cm is not None and bm != cm:
        notes.append(f"the methods' configuration differs: base {json.dumps(bm, sort_keys=True)}, candidate "
                     f"{json.dumps(cm, sort_keys=True)}")
    for run, name in ((base, "base"), (candidate, "candidate")):
        n = run.summary.get("n_trials")
        if run.records and isinstance(n, int) and n != len(run.records):
            notes.append(f"the {name} holds {len(run.records)} trial records but its summary {n} trials "
                         "(a run with --only?): intervals over the records")
    return notes


def pair_trials(base: Sequence[Mapping[str, Any]], candidate: Sequence[Mapping[str, Any]]) -> tuple[TrialPair, ...]:
    """The trials both runs recorded, paired by trial id (sorted by it); the scene and group are the base's."""
    cand = {str(r.get("trial_id")): r for r in candidate}
    pairs = []
    for b in sorted(base, key=lambda r: str(r.get("trial_id"))):
        tid = str(b.get("trial_id"))
        if tid in cand:
            pairs.append(TrialPair(tid, scene_of(b), str((b.get("spec") or {}).get("group", "")), b, cand[tid]))
    return tuple(pairs)


def parse_methods(value: str | None, base: Mapping[str, Any], candidate: Mapping[str, Any]) -> tuple[str, ...] | str:
    """``--methods``: ``all``, or comma-separated names of methods of either run (``core`` always counts)."""
    if not value:
        return ()
    if value.strip() == "all":
        return "all"
    known = methods_of(base, candidate)
    names = tuple(m.strip() for m in value.split(",") if m.strip())
    unknown = [m for m in names if m not in known]
    if unknown:
        raise CompareError(f"--methods: no method {unknown[0]!r} in either run (methods: {', '.join(known)})")
    return names


def compare_dirs(base: RunResults, candidate: RunResults, tol: Tolerances = DEFAULT_TOLERANCES,
                 methods: Sequence[str] | str = (), force: bool = False, top: int = 10) -> Comparison:
    """The verdict of ``candidate`` against ``base``.

    Raises
    ------
    CompareError
        When the runs ran different trials (:func:`run_differences`) and ``force`` is false.
    """
    differences = run_differences(base, candidate)
    if differences and not force:
        raise CompareError("the runs differ: " + "; ".join(differences) + " (compare runs of one suite, seeds "
                           "and trials, or pass --force)")
    notes = [f"compared with --force although the runs differ: {'; '.join(differences)}"] if differences else []
    notes += run_notes(base, candidate)
    if note := undeclared_note(base.summary, candidate.summary):
        notes.append(note)
    pairs = pair_trials(base.records, candidate.records)
    return compare_runs(base.summary, candidate.summary, pairs, tol, methods, top=top, notes=notes)


# -- the text -----------------------------------------------------------------------------------------------
def format_comparison(comparison: Comparison, base_name: str, candidate_name: str, fmt: str = "text",
                      leaves: list[Row] | None = None, only_changes: bool = False,
                      codes: tuple[Any, Any] | None = None) -> str:
    """The comparison as text (``text``) or Markdown (``md``): the headline table first, then the other
    methods, what changed most, every leaf (when ``leaves`` are given; ``only_changes``: those that moved),
    notes (with the runs' code identities, ``codes``: the base's and the candidate's ``code`` entries) and the
    verdict line."""
    c = comparison
    md = fmt == "md"

    def title(text: str) -> str:
        return f"**{text}**\n" if md else text

    parts = [title(f"Headline metrics: {candidate_name} (candidate) against {base_name} (base); delta = candidate - "
                   f"base; 95 % paired cluster-bootstrap interval over {c.n_scenes} scene(s), {c.n_pairs} trial(s) "
                   "paired by trial id"),
             _table(HEADLINE_HEADER, [figure_cells(f) for f in shown_figures(c, True)], fmt)]
    others = shown_figures(c, False)
    if c.reported_methods:
        parts += ["", title(f"Other methods ({', '.join(c.reported_methods)}): reported, counted only with "
                            "--methods NAME or --methods all (pooled; a group shown when not pass)"),
                  _table(HEADLINE_HEADER, [figure_cells(f) for f in others], fmt) if others else "(nothing to show)"]
    parts += ["", title("What changed most (core, per trial, paired by trial id)")]
    if c.moves:
        parts.append(_table(MOVES_HEADER, [move_cells(m) for m in c.moves], fmt))
    else:
        parts.append("no trial's figures moved" if c.n_pairs else "no paired trial records")
    if leaves is not None:
        parts += ["", title("Every numeric leaf of summary.json (informative: the verdict is on the headline "
                            "metrics)"), format_rows(leaves, fmt, only_changes)]
    notes = list(c.notes)
    if codes is not None:
        notes.insert(0, f"code: base {describe_code(codes[0])}; candidate {describe_code(codes[1])}")
    if notes:
        parts += ["", title("Notes")] + [f"- {n}" for n in notes]
    parts.append("")
    if c.uncounted_line():
        parts.append(c.uncounted_line())
    parts.append(f"**{c.verdict_line()}**" if md else c.verdict_line())  # last: what a CI log shows
    return "\n".join(parts)
