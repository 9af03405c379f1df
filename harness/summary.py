"""``summary.json``: the aggregate of a run's trial records, with the keys of DESIGN section 8 (and more beside).

A section whose stage did not run in any trial is ``null``: absent, never faked.

Intervals (DESIGN 11.3): every headline rate and median carries a 95 % interval beside it, in the same dict,
under its key with ``_ci95`` appended (``classification.accuracy_ci95: [lo, hi]``,
``pose.rotation_error_deg.median_ci95``, ``change.per_label.moved.f1_ci95``; the full list is in
:mod:`evaluation.aggregate`), for the core, every baseline and oracle, pooled and per group. They come from a
cluster bootstrap over the scenes (``spec.scene``) of the scope, seeded, so they are deterministic and belong
to the :func:`comparable` part. All methods of one scope share its resamples. Each scope (the top level and
every group) says how they were made in ``ci95_bootstrap``: ``{method, cluster_key, level, n_boot, seed,
n_clusters, clusters}``. An interval is null when fewer than two scenes contribute to its figure (a one-scene
group has none: resampling one scene says nothing about variation over scenes). A trial record that names no
scene is a cluster of its own. ``timing_s`` has no intervals (times are not comparable between runs).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np

from evaluation.aggregate import (
    aggregate_change,
    aggregate_classification,
    aggregate_pose,
    aggregate_segmentation,
    stats,
)
from evaluation.intervals import DEFAULT_BOOTSTRAP, BootstrapParams, Clusters, Resampling
from evaluation.metrics import TIMING_STAGES

SCHEMA = "harness.summary/1"
TIMING_KEYS = TIMING_STAGES
SECTIONS: dict[str, Callable[[list[dict], Resampling], dict | None]] = {
    "segmentation": aggregate_segmentation,
    "classification": lambda trials, rs: aggregate_classification(trials, resampling=rs),
    "pose": aggregate_pose,
    "change": aggregate_change,
}


def scene_of(record: dict[str, Any]) -> str:
    """The cluster of a trial for the intervals: its scene (``spec.scene``), else its trial id."""
    spec = record.get("spec") or {}
    return str(spec.get("scene") or record.get("trial_id"))


def scope_clusters(records: list[dict[str, Any]], params: BootstrapParams = DEFAULT_BOOTSTRAP) -> Clusters:
    """The scenes of the successful trials of ``records`` and their bootstrap weights."""
    return Clusters.of((scene_of(r) for r in records if r.get("status") == "ok"), params)


def method_sections(records: list[dict[str, Any]], method: str, kind: str = "methods",
                    clusters: Clusters | None = None) -> dict[str, Any]:
    """The DESIGN 8 sections (segmentation ... timing_s) of one method (or oracle) over ``records``, with the
    intervals over ``clusters`` (default: the scenes of ``records``)."""
    ok = [r for r in records if r.get("status") == "ok" and method in r.get(kind, {})]
    clusters = scope_clusters(records) if clusters is None else clusters
    out: dict[str, Any] = {}
    for name, agg in SECTIONS.items():
        present = [(r, r[kind][method].get(name)) for r in ok]
        present = [(r, p) for r, p in present if p is not None]
        rs = clusters.resampling([scene_of(r) for r, _ in present])
        out[name] = agg([p for _, p in present], rs) if present else None
    out["timing_s"] = timing(ok, method, kind)
    return out


def timing(records: list[dict[str, Any]], method: str, kind: str = "methods") -> dict[str, Any]:
    """Median and p90 seconds per stage; ``sensor`` and ``total`` are per trial, the others per method."""
    out: dict[str, Any] = {}
    for key in TIMING_KEYS:
        if key in ("sensor", "total"):
            vals = [r["timing_s"].get(key) for r in records]
        else:
            vals = [r[kind][method].get("timing_s", {}).get(key) for r in records]
        vals = [v for v in vals if v is not None]
        out[key] = {"median": float(np.median(vals)), "p90": float(np.percentile(vals, 90))} if vals else None
    return out


def summarise(records: list[dict[str, Any]], *, suite: str, config_hash: str, version: str,
              methods: list[str], oracles: list[str] = (), extra: dict[str, Any] | None = None,
              bootstrap: BootstrapParams = DEFAULT_BOOTSTRAP) -> dict[str, Any]:
    """Build the summary dict from trial records (one per trial of the run); ``bootstrap``: how the intervals
    are drawn (default: 2000 resamples, seed 0, 95 %)."""
    summary: dict[str, Any] = {
        "schema": SCHEMA,
        "suite": suite,
        "n_trials": len(records),
        "n_failed": sum(1 for r in records if r.get("status") != "ok"),
        "config_hash": config_hash,
        "version": version,
    }
    clusters = scope_clusters(records, bootstrap)
    summary.update(method_sections(records, "core", clusters=clusters))
    summary["baselines"] = {m: method_sections(records, m, clusters=clusters) for m in methods if m != "core"}
    if oracles:
        summary["oracles"] = {o: method_sections(records, o, "oracles", clusters) for o in oracles}
    summary["ci95_bootstrap"] = clusters.describe()
    by_group: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        by_group[r["spec"]["group"]].append(r)
    summary["groups"] = {}
    for g in sorted(by_group):
        recs = by_group[g]
        sec = {"n_trials": len(recs), "n_failed": sum(1 for r in recs if r.get("status") != "ok")}
        group_clusters = scope_clusters(recs, bootstrap)
        sec.update(method_sections(recs, "core", clusters=group_clusters))
        sec["baselines"] = {m: method_sections(recs, m, clusters=group_clusters) for m in methods if m != "core"}
        if oracles:
            sec["oracles"] = {o: method_sections(recs, o, "oracles", group_clusters) for o in oracles}
        sec["ci95_bootstrap"] = group_clusters.describe()
        views = [r["view"] for r in recs if r.get("status") == "ok"]
        sec["view"] = _view_stats(views)
        summary["groups"][g] = sec
    summary["failures"] = [{"trial_id": r["trial_id"], "reason": r.get("reason", "")}
                           for r in records if r.get("status") != "ok"]
    summary["view"] = _view_stats([r["view"] for r in records if r.get("status") == "ok"])
    if extra:
        summary.update(extra)
    return summary


def _view_stats(views: list[dict[str, Any]]) -> dict[str, Any] | None:
    if not views:
        return None
    return {"viewpoint_rejection_rate": stats([v["viewpoint_rejection_rate"] for v in views]),
            "valid_fraction": stats([v["valid_fraction"] for v in views]),
            "surfaces_seen": stats([v["surfaces_seen"] for v in views]),
            "n_twin_ambiguous": sum(bool(v.get("twin_ambiguous")) for v in views)}


VOLATILE = ("timing_s", "provenance", "run", "version")


def comparable(summary: dict[str, Any]) -> dict[str, Any]:
    """The summary without what legitimately differs between identical runs (times, provenance): equal
    configs and seeds must give equal ``comparable`` summaries (DESIGN 10.4)."""

    def strip(node: Any) -> Any:
        if isinstance(node, dict):
            return {k: strip(v) for k, v in node.items() if k not in VOLATILE}
        if isinstance(node, list):
            return [strip(v) for v in node]
        return node

    return strip(summary)
