"""Compare two runs' summaries metric by metric and apply regression rules (DESIGN 10.9).

Every numeric leaf of ``summary.json`` becomes a dotted metric path (``classification.per_class.CYL.recall``,
``groups.mockup/mockup_laser.segmentation.over_rate``...). Its direction comes from its name: rates of
correct detection, accuracy, precision, recall, F1 and success are better higher; over, under, missed and
noise rates, the Brier score, errors, times and ``n_failed`` are better lower; counts and settings have no
direction and are only reported. A section present in the base and null in the candidate is a regression.
Time rules are relative and off unless asked for (shared machines are noisy). The 95 % intervals beside the
figures (``*_ci95`` keys, and ``ci95_bootstrap``, how they were drawn) are not metrics: they are skipped.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scenes.config import Fields, load_yaml

TOLERANCES_DIR = Path(__file__).parent / "tolerances"
HIGHER = ("correct_detection_rate", "accuracy", "precision", "recall", "f1", "macro_f1", "success_rate",
          "success_rate_constrained")
LOWER_RATES = ("over_rate", "under_rate", "missed_rate", "noise_rate")
LOWER_ERRORS = ("brier", "ece")
ERROR_PARENTS = ("rotation_error_deg", "translation_error_mm", "add_mm", "displacement_error_mm")
STAT_KEYS = ("median", "p90", "max", "mean")
SECTIONS = ("segmentation", "classification", "pose", "change")
SKIPPED_TREES = ("provenance", "run", "failures", "view", "reliability", "confusion", "sweep")


@dataclass(frozen=True)
class Tolerances:
    """Regression rules. Rates: absolute change allowed in the bad direction; errors and times: relative
    growth allowed, with an absolute floor so that tiny values do not trip on rounding."""

    rate_drop: float = 0.02
    error_growth: float = 0.10
    error_floor: float = 1e-3
    time_growth: float = 0.5
    time_floor_s: float = 0.05
    n_failed_increase: int = 0
    check_time: bool = False
    per_metric: dict[str, float] = field(default_factory=dict)

    @staticmethod
    def load(path: str | Path) -> Tolerances:
        f = Fields(load_yaml(path), str(path))
        schema = f.string("schema", "tolerances/1")
        if schema != "tolerances/1":
            raise f.error("schema", f"unsupported schema {schema!r} (expected 'tolerances/1')")
        per = f.sub("per_metric", {})
        t = Tolerances(
            rate_drop=f.number("rate_drop", 0.02, nonnegative=True),
            error_growth=f.number("error_growth", 0.10, nonnegative=True),
            error_floor=f.number("error_floor", 1e-3, nonnegative=True),
            time_growth=f.number("time_growth", 0.5, nonnegative=True),
            time_floor_s=f.number("time_floor_s", 0.05, nonnegative=True),
            n_failed_increase=f.integer("n_failed_increase", 0, min=0),
            check_time=f.boolean("check_time", False),
            per_metric={str(k): per.number(str(k), nonnegative=True) for k in per.data},
        )
        f.check_unknown()
        return t


@dataclass(frozen=True)
class Row:
    metric: str
    base: float | None
    candidate: float | None
    direction: str  # "higher", "lower", "time", or "" (reported only)
    verdict: str  # "ok", "regression", "improved", "missing", "new", ""

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


def flatten(node: Any, prefix: str = "") -> dict[str, float | None]:
    """Numeric leaves (and null sections) of a summary as dotted paths."""
    out: dict[str, float | None] = {}
    if isinstance(node, dict):
        for k, v in node.items():
            if k in SKIPPED_TREES or is_interval_key(str(k)):
                continue
            path = f"{prefix}.{k}" if prefix else str(k)
            if v is None:
                out[path] = None
            elif isinstance(v, dict | list):
                out.update(flatten(v, path) if isinstance(v, dict) else {})
            elif isinstance(v, bool):
                continue
            elif isinstance(v, int | float) and math.isfinite(v):
                out[path] = float(v)
    return out


def is_interval_key(key: str) -> bool:
    """Whether a summary key holds an interval (``accuracy_ci95``) or how intervals were made (``ci95_bootstrap``)."""
    return key.endswith("_ci95") or key.startswith("ci95")


def direction(metric: str) -> str:
    parts = metric.split(".")
    leaf = parts[-1]
    if "timing_s" in parts:
        return "time"
    if leaf in HIGHER:
        return "higher"
    if leaf in LOWER_RATES or leaf in LOWER_ERRORS or leaf == "n_failed":
        return "lower"
    if leaf in STAT_KEYS and len(parts) >= 2 and parts[-2] in ERROR_PARENTS:
        return "lower"
    return ""


def _is_section(metric: str) -> bool:
    return metric.split(".")[-1] in SECTIONS


def compare(base: dict[str, Any], candidate: dict[str, Any], tol: Tolerances = Tolerances()) -> list[Row]:
    """Every metric of both summaries with its verdict."""
    fb, fc = flatten(base), flatten(candidate)
    rows = []
    lost = sorted(k for k, v in fc.items() if v is None and _is_section(k)
                  and any(m.startswith(k + ".") for m in fb))
    rows += [Row(k, None, None, "", "regression") for k in lost]  # present in base, null in candidate
    for metric in sorted(set(fb) | set(fc)):
        if _is_section(metric) and fb.get(metric) is None and fc.get(metric) is None:
            continue
        if any(metric.startswith(k + ".") for k in lost):
            continue
        b, c = fb.get(metric), fc.get(metric)
        d = direction(metric)
        rows.append(Row(metric, b, c, d, _verdict(metric, b, c, d, tol)))
    return rows


def _verdict(metric: str, b: float | None, c: float | None, d: str, tol: Tolerances) -> str:
    if b is None and c is None:
        return ""
    if c is None:
        return "missing" if d else ""
    if b is None:
        return "new" if d else ""
    if not d:
        return ""
    if metric.split(".")[-1] == "n_failed":
        return "regression" if c - b > tol.n_failed_increase else ("improved" if c < b else "ok")
    allowed = tol.per_metric.get(metric)
    if d == "higher":
        allowed = tol.rate_drop if allowed is None else allowed
        return "regression" if b - c > allowed + 1e-12 else ("improved" if c - b > allowed else "ok")
    if d == "lower":
        leaf = metric.split(".")[-1]
        if leaf in LOWER_RATES:
            allowed = tol.rate_drop if allowed is None else allowed
            return "regression" if c - b > allowed + 1e-12 else ("improved" if b - c > allowed else "ok")
        growth = tol.error_growth if allowed is None else allowed
        limit = b * (1 + growth) + tol.error_floor
        return "regression" if c > limit else ("improved" if c < b * (1 - growth) - tol.error_floor else "ok")
    if d == "time":
        if not tol.check_time:
            return ""
        limit = b * (1 + tol.time_growth) + tol.time_floor_s
        return "regression" if c > limit else "ok"
    return ""


def regressions(rows: list[Row]) -> list[Row]:
    return [r for r in rows if r.verdict in ("regression", "missing")]


def format_rows(rows: list[Row], fmt: str = "text", only_changes: bool = False) -> str:
    """A table of the comparison: ``text`` (aligned columns) or ``md`` (Markdown)."""
    shown = [r for r in rows if not only_changes or r.verdict in ("regression", "missing", "improved", "new")
             or (r.delta not in (None, 0.0))]

    def num(x: float | None) -> str:
        return "null" if x is None else f"{x:.6g}"

    def delta(r: Row) -> str:
        return "" if r.delta is None else f"{r.delta:+.4g}"

    header = ("metric", "base", "candidate", "delta", "better", "verdict")
    body = [(r.metric, num(r.base), num(r.candidate), delta(r), r.direction, r.verdict.upper()
             if r.verdict == "regression" else r.verdict) for r in shown]
    if fmt == "md":
        lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        lines += ["| " + " | ".join(cells) + " |" for cells in body]
        return "\n".join(lines)
    widths = [max(len(h), *(len(c[i]) for c in body)) if body else len(h) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(cells, widths, strict=True)) for cells in body]
    return "\n".join(lines)
