"""``summary.json``: the aggregate of a run's trial records, with exactly the keys of DESIGN section 8.

A section whose stage did not run in any trial is ``null``: absent, never faked.
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

SCHEMA = "harness.summary/1"
TIMING_KEYS = ("sensor", "segmentation", "classification", "matching", "icp", "change", "total")
SECTIONS: dict[str, Callable[[list[dict]], dict | None]] = {
    "segmentation": aggregate_segmentation,
    "classification": aggregate_classification,
    "pose": aggregate_pose,
    "change": aggregate_change,
}


def method_sections(records: list[dict[str, Any]], method: str, kind: str = "methods") -> dict[str, Any]:
    """The DESIGN 8 sections (segmentation ... timing_s) of one method (or oracle) over ``records``."""
    ok = [r for r in records if r.get("status") == "ok" and method in r.get(kind, {})]
    out: dict[str, Any] = {}
    for name, agg in SECTIONS.items():
        per_trial = [r[kind][method].get(name) for r in ok]
        present = [p for p in per_trial if p is not None]
        out[name] = agg(present) if present else None
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
              methods: list[str], oracles: list[str] = (), extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Build the summary dict from trial records (one per trial of the run)."""
    summary: dict[str, Any] = {
        "schema": SCHEMA,
        "suite": suite,
        "n_trials": len(records),
        "n_failed": sum(1 for r in records if r.get("status") != "ok"),
        "config_hash": config_hash,
        "version": version,
    }
    summary.update(method_sections(records, "core"))
    summary["baselines"] = {m: method_sections(records, m) for m in methods if m != "core"}
    if oracles:
        summary["oracles"] = {o: method_sections(records, o, "oracles") for o in oracles}
    by_group: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        by_group[r["spec"]["group"]].append(r)
    summary["groups"] = {}
    for g in sorted(by_group):
        recs = by_group[g]
        sec = {"n_trials": len(recs), "n_failed": sum(1 for r in recs if r.get("status") != "ok")}
        sec.update(method_sections(recs, "core"))
        sec["baselines"] = {m: method_sections(recs, m) for m in methods if m != "core"}
        if oracles:
            sec["oracles"] = {o: method_sections(recs, o, "oracles") for o in oracles}
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
            "surfaces_seen": stats([v["surfaces_seen"] for v in views])}


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
