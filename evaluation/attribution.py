"""Error attribution from stage-isolating oracles (DESIGN 10.10): how much of each downstream figure's gap
each stage explains.

An oracle replaces one stage's output by the truth; the difference between a figure under that oracle and
end to end is what that stage costs the figure (e.g. classification accuracy 0.91 end to end and 0.97 with
the truth segmentation: 0.06 comes from segmentation). Shares are of the end-to-end gap to the ideal value
(1 for rates, 0 for errors). The figures and their directions are the headline metrics of
:mod:`evaluation.metrics`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from evaluation import metrics
from evaluation.metrics import Metric


def figures() -> tuple[Metric, ...]:
    """The figures attributed: the headline metrics of a method that have an ideal value
    (:mod:`evaluation.metrics`)."""
    return tuple(m for m in metrics.judged() if m.ideal is not None)


def _name(m: Metric) -> str:
    return f"{m.title} ({m.unit})" if m.unit else m.title
#: the summary sections downstream of the stage each oracle replaces
AFFECTS = {"segmentation": ("classification", "pose", "change"), "classification": ("pose", "change"),
           "pairing": ("pose", "change"), "pose": ("change",)}
STAGE_NAMES = {"segmentation": "Segmentation", "classification": "Classification", "pairing": "Matching",
               "pose": "Pose estimation"}


@dataclass(frozen=True)
class Attribution:
    """One downstream figure end to end, under each oracle, and what each stage costs it."""

    figure: str
    direction: str
    ideal: float
    end_to_end: float | None
    with_oracle: dict[str, float | None]
    cost: dict[str, float | None]  # in the figure's units, positive = the stage makes it worse
    share: dict[str, float | None]  # cost / end-to-end gap to the ideal


def _lookup(node: Any, path: tuple[str, ...]) -> float | None:
    for key in path:
        if not isinstance(node, dict) or node.get(key) is None:
            return None
        node = node[key]
    return float(node) if isinstance(node, int | float) else None


def attribute(summary: dict[str, Any]) -> list[Attribution]:
    """Attribution rows for every figure that some oracle can explain (oracles upstream of the figure)."""
    oracles = summary.get("oracles") or {}
    rows = []
    for m in figures():
        path, label, direction, ideal = m.path, _name(m), m.direction, m.ideal
        upstream = [o for o in oracles if path[0] in AFFECTS.get(o, ())]
        if not upstream:
            continue
        e2e = _lookup(summary, path)
        values = {o: _lookup(oracles[o], path) for o in upstream}
        sign = 1.0 if direction == "higher" else -1.0
        gap = None if e2e is None else sign * (ideal - e2e)
        cost = {o: (None if e2e is None or v is None else sign * (v - e2e)) for o, v in values.items()}
        share = {o: (None if c is None or not gap else c / gap) for o, c in cost.items()}
        rows.append(Attribution(label, direction, ideal, e2e, values, cost, share))
    return rows


def largest_losses(rows: list[Attribution]) -> dict[str, str]:
    """One sentence per oracle's stage naming the figure whose gap it explains most (by share)."""
    out = {}
    stages = [o for o in AFFECTS if any(o in r.cost for r in rows)]
    for o in stages:
        cands = [(r.share[o], r) for r in rows if r.share.get(o) is not None]
        if not cands:
            continue
        share, r = max(cands, key=lambda x: x[0])
        what = STAGE_NAMES[o]
        if share <= 0:
            out[o] = f"{what} costs no downstream figure measurably on this suite."
        else:
            out[o] = (f"{what} costs most on {r.figure}: {r.end_to_end:.3g} end to end, {r.with_oracle[o]:.3g} with "
                      f"its truth ({100 * share:.0f} % of the gap to {r.ideal:g}).")
    return out
