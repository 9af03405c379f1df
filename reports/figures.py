"""Figures of the report, drawn with matplotlib's Agg canvas (no pyplot, no global state) and returned as PNG bytes.

Plots take plain summary data (the dicts of ``summary.json`` and trial records); pictures take image arrays.
Colours come from :mod:`reports.colours`; axes carry their units; every figure and picture carries its legend
(or colour bar). Figures are 660 px wide at 100 dpi (two to a row of the report's 1344 px column; a wide one,
1320 px, takes the row). Pictures of one scan share one layout (title band, image, legend band), so a row of
them lines up.
Headline values are drawn with error bars from their 95 % interval (``<key>_ci95`` of the summary) where they
have one; a value without an interval is drawn without a bar.
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from evaluation.metrics import MIN_SCORED_PIXELS
from reports.colours import (
    CHANGE_COLOURS,
    CHANGE_LABELS,
    CLASS_COLOURS,
    CLASSES,
    EDGE_COLOUR,
    HK_COLOURS,
    HK_NAMES,
    HOOVER_COLOURS,
    NO_RETURN,
    STAGE_COLOURS,
    group_colour,
    method_colour,
    region_colours,
    rgb,
)
from scenes.vocabulary import CHANGE_MAP_LABELS

DPI = 100
WIDTH_IN = 6.6  # 660 px: two figures to a row of the report
WIDE_IN = 13.2  # a figure that takes the row (``Image(span=2)``)
HOOVER_NAMES = {"correct_detection_rate": "correct detection", "over_rate": "over-segmentation",
                "under_rate": "under-segmentation", "missed_rate": "missed", "noise_rate": "noise"}
METHOD_STYLES = ("-", "--", ":", "-.")


def new_figure(width_in: float = WIDTH_IN, height_in: float = 3.6) -> Figure:
    """A figure on its own Agg canvas."""
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def to_png(fig: Figure) -> bytes:
    """The figure as PNG bytes: an 8-bit palette image of at most 256 colours (median cut, no dithering, so
    deterministic), about a third of the size of the RGBA image for the noisy range pictures."""
    from PIL import Image as PILImage

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, facecolor="white")
    buf.seek(0)
    with PILImage.open(buf) as img:
        pal = img.convert("RGB").quantize(colors=256, method=PILImage.Quantize.MEDIANCUT,
                                          dither=PILImage.Dither.NONE)
    out = io.BytesIO()
    pal.save(out, format="png")
    return out.getvalue()


def _style(i: int) -> str:
    return METHOD_STYLES[i % len(METHOD_STYLES)]


def error_bars(values: Sequence[float], intervals: Sequence[Sequence[float] | None]) -> np.ndarray:
    """Asymmetric error bars for ``errorbar``/``bar``.

    Parameters
    ----------
    values : the plotted values, N of them (NaN for a blank).
    intervals : N ``(lo, hi)`` or None.

    Returns
    -------
    ndarray of shape (2, N): distances below and above each value, never negative (a percentile interval
    need not contain the value); NaN without an interval, which matplotlib leaves undrawn (a zero-length
    bar with caps would look like a zero-width interval).
    """
    v = np.asarray(values, dtype=float)
    out = np.full((2, len(v)), np.nan)
    for i, (x, ci) in enumerate(zip(v, intervals, strict=True)):
        if ci is not None and np.isfinite(x):
            out[0, i] = max(x - float(ci[0]), 0.0)
            out[1, i] = max(float(ci[1]) - x, 0.0)
    return out


def _ci(d: Mapping[str, Any] | None, key: str) -> Sequence[float] | None:
    ci = (d or {}).get(key + "_ci95")
    return ci if isinstance(ci, list | tuple) and len(ci) == 2 and None not in ci else None


# -- segmentation -------------------------------------------------------------------------------------------
def hoover_sweep_figure(sweeps: Mapping[str, Sequence[Mapping[str, float]]], tolerance: float | None = None,
                        same_as: Mapping[str, Sequence[str]] | None = None) -> bytes:
    """Hoover rates against the overlap tolerance T: one panel per rate, one line per distinct segmentation.

    Parameters
    ----------
    sweeps : method name -> the ``segmentation.sweep`` rows ``[{tolerance, correct_detection_rate, ...}]``;
        one entry per distinct segmentation (methods with identical rows are passed once, see ``same_as``).
    tolerance : the headline tolerance, marked with a vertical line in every panel.
    same_as : method drawn -> the other methods whose sweep is identical (it shares the core's segmentation),
        named in its legend entry ("core (= diff_change)").
    """
    same_as = same_as or {}
    fig = new_figure(height_in=4.9)
    axes = fig.subplots(2, 3, sharex=True).ravel()
    methods = list(sweeps)
    for ax, key in zip(axes, HOOVER_COLOURS, strict=False):
        top = 0.0
        for i, (method, rows) in enumerate(sweeps.items()):
            t = [r["tolerance"] for r in rows]
            y = [r[key] for r in rows]
            top = max([top, *[v for v in y if v is not None]])
            others = list(same_as.get(method, ()))
            label = method + (f" (= {', '.join(others)})" if others else "")
            ax.plot(t, y, _style(i), color=method_colour(method, methods), marker="o", markersize=2.5, lw=1.4,
                    label=label)
        if tolerance is not None:
            ax.axvline(tolerance, color="#9ca3af", lw=1, zorder=0)
        ax.set_title(HOOVER_NAMES[key], fontsize=9.5, color=HOOVER_COLOURS[key], fontweight="bold")
        ax.set_ylim(0, 1.02 if key == "correct_detection_rate" else min(1.02, max(0.1, 1.15 * top)))
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=8)
    for ax in axes[3:5]:
        ax.set_xlabel("overlap tolerance T", fontsize=8.5)
    axes[0].set_ylabel("fraction of regions", fontsize=8.5)
    axes[3].set_ylabel("fraction of regions", fontsize=8.5)
    key_ax = axes[5]
    key_ax.axis("off")
    handles, labels = axes[0].get_legend_handles_labels()
    if tolerance is not None:
        from matplotlib.lines import Line2D

        handles.append(Line2D([], [], color="#9ca3af", lw=1))
        labels.append(f"headline T = {tolerance:g}")
    key_ax.legend(handles, labels, loc="center", fontsize=8.5, frameon=False, title="segmentation of",
                  title_fontsize=8.5)
    return to_png(fig)


# -- classification -----------------------------------------------------------------------------------------
def confusion_figure(confusions: Mapping[str, Mapping[str, Any]]) -> bytes:
    """Confusion matrices (rows: truth, columns: label), one panel per method, counts and row fractions.

    Parameters
    ----------
    confusions : method name -> ``{classes: [...], matrix: [[...]]}``.
    """
    n = max(len(confusions), 1)
    fig = new_figure(height_in=3.4 if n <= 2 else 2.6)
    axes = fig.subplots(1, n, squeeze=False)[0]
    for ax, (method, conf) in zip(axes, confusions.items(), strict=False):
        classes = list(conf["classes"])
        m = np.asarray(conf["matrix"], dtype=float).reshape(len(classes), len(classes))
        rows = m.sum(axis=1, keepdims=True)
        frac = np.divide(m, rows, out=np.zeros_like(m), where=rows > 0)
        ax.imshow(frac, cmap="Blues", vmin=0, vmax=1)
        for i in range(len(classes)):
            for j in range(len(classes)):
                if m[i, j]:
                    ax.text(j, i, f"{int(m[i, j])}", ha="center", va="center", fontsize=8,
                            color="white" if frac[i, j] > 0.55 else "#111827")
        ax.set_xticks(range(len(classes)), classes, fontsize=7)
        ax.set_yticks(range(len(classes)), classes, fontsize=7)
        for tick in (*ax.get_xticklabels(), *ax.get_yticklabels()):
            tick.set_color(CLASS_COLOURS.get(tick.get_text(), "#111827"))
            tick.set_fontweight("bold")
        ax.set_xlabel("predicted label")
        ax.set_ylabel("truth class")
        ax.set_title(f"{method} (patches)", fontsize=9)
    return to_png(fig)


def reliability_figure(tables: Mapping[str, Sequence[Mapping[str, float]]],
                       stated: str = "stated probability of the winning label", items: str = "patches") -> bytes:
    """Reliability diagram: accuracy against the stated probability of the winning label, per bin.

    Parameters
    ----------
    tables : method name -> ``classification.reliability`` (or ``pose.reliability``) rows
        ``[{low, high, confidence, accuracy, count}]``.
    stated, items : the x axis's title and what the bins count.
    """
    fig = new_figure(height_in=4.2)
    ax, axc = fig.subplots(2, 1, sharex=True, height_ratios=(3, 1))
    ax.plot([0, 1], [0, 1], color="#9ca3af", lw=1, label="perfect calibration")
    methods = list(tables)
    width = 0.8 / max(len(methods), 1)
    for i, (method, rows) in enumerate(tables.items()):
        colour = method_colour(method, methods)
        rows = [r for r in rows if r.get("count")]
        if not rows:
            continue
        conf = [r["confidence"] for r in rows]
        ax.plot(conf, [r["accuracy"] for r in rows], _style(i), color=colour, marker="o", label=method)
        centres = np.array([(r["low"] + r["high"]) / 2 for r in rows])
        bw = np.array([r["high"] - r["low"] for r in rows])
        axc.bar(centres - bw / 2 + (i + 0.5) * width * bw, [r["count"] for r in rows], width=width * bw,
                color=colour, alpha=0.8)
    ax.set_ylabel("accuracy (fraction correct)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    axc.set_xlabel(stated)
    axc.set_ylabel(items)
    axc.set_xlim(0, 1)
    return to_png(fig)


def per_class_figure(per_class: Mapping[str, Mapping[str, Mapping[str, float | None]]]) -> bytes:
    """Recall (bars, with their 95 % intervals) and precision (markers) per truth class, grouped by method.

    Parameters
    ----------
    per_class : method name -> ``classification.per_class`` ``{PLAN: {precision, recall, support}, ...}``.
    """
    fig = new_figure(height_in=3.2)
    ax = fig.add_subplot()
    methods = list(per_class)
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(CLASSES))
    for i, (method, pc) in enumerate(per_class.items()):
        rec = [np.nan if (pc.get(c) or {}).get("recall") is None else pc[c]["recall"] for c in CLASSES]
        prec = [np.nan if (pc.get(c) or {}).get("precision") is None else pc[c]["precision"] for c in CLASSES]
        pos = x - 0.4 + (i + 0.5) * width
        ax.bar(pos, rec, width=width * 0.95, color=[CLASS_COLOURS[c] for c in CLASSES],
               alpha=max(1.0 - 0.3 * i, 0.45), edgecolor=method_colour(method, methods), linewidth=1.2,
               hatch=None if i == 0 else "//", label=f"recall ({method})",
               yerr=error_bars(rec, [_ci(pc.get(c), "recall") for c in CLASSES]), ecolor="#374151", capsize=2)
        ax.plot(pos, prec, "D", color=method_colour(method, methods), markersize=5, label=f"precision ({method})")
    ax.set_xticks(x, [f"{c}\n(n={_support(per_class, c)})" for c in CLASSES], fontsize=8)
    ax.set_ylabel("fraction")
    ax.set_ylim(0, 1.05)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return to_png(fig)


def _support(per_class: Mapping[str, Mapping[str, Mapping[str, Any]]], cls: str) -> int:
    first = next(iter(per_class.values()), {})
    return int((first.get(cls) or {}).get("support") or 0)


# -- pose ---------------------------------------------------------------------------------------------------
def pose_cdf_figure(errors: Mapping[str, Mapping[str, Mapping[str, Sequence[float]]]],
                    rotation_threshold_deg: float = 1.0, same_as: Mapping[str, Sequence[str]] | None = None
                    ) -> bytes:
    """Cumulative distributions of the rotation and translation errors, before and after ICP.

    Parameters
    ----------
    errors : method -> ``{"rotation_error_deg": {"after ICP": [...], "initial": [...]},
        "translation_error_mm": {...}}``, one value per trial (non-finite values are dropped).
    rotation_threshold_deg : the success threshold on rotation, marked on its axis.
    same_as : method drawn -> the methods with exactly its errors, named in its legend entry.
    """
    same_as = same_as or {}
    fig = new_figure(height_in=3.4)
    axes = fig.subplots(1, 2)
    methods = list(errors)
    units = {"rotation_error_deg": "rotation error (deg)", "translation_error_mm": "translation error (mm)"}
    for ax, (key, xlabel) in zip(axes, units.items(), strict=True):
        for method, per in errors.items():
            for j, (stage, values) in enumerate(per.get(key, {}).items()):
                v = np.sort(np.asarray([x for x in values if x is not None], dtype=float))
                v = v[np.isfinite(v)]
                if not len(v):
                    continue
                y = np.arange(1, len(v) + 1) / len(v)
                ax.step(np.r_[0.0, v], np.r_[0.0, y], where="post", ls=_style(j),
                        color=method_colour(method, methods),
                        label=f"{method}" + (f" (= {', '.join(same_as[method])})" if same_as.get(method) else "")
                        + f", {stage}")
        if key == "rotation_error_deg":
            ax.axvline(rotation_threshold_deg, color="#9ca3af", lw=1, zorder=0)
        ax.set_xscale("symlog", linthresh=0.1 if key == "rotation_error_deg" else 1.0)
        ax.set_xlim(left=0)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("fraction of trials")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower right")
    return to_png(fig)


# -- change -------------------------------------------------------------------------------------------------
def change_f1_figure(per_label: Mapping[str, Mapping[str, Mapping[str, float | None]]]) -> bytes:
    """F1 per change label (bars in the label's colour, with their 95 % intervals), grouped by method; labels
    without support are blank.

    Parameters
    ----------
    per_label : method -> ``change.per_label`` ``{moved: {precision, recall, f1, support}, ...}``.
    """
    fig = new_figure(height_in=3.0)
    ax = fig.add_subplot()
    methods = list(per_label)
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(CHANGE_LABELS))
    for i, (method, pl) in enumerate(per_label.items()):
        f1 = [np.nan if (pl.get(lab) or {}).get("f1") is None else pl[lab]["f1"] for lab in CHANGE_LABELS]
        ax.bar(x - 0.4 + (i + 0.5) * width, f1, width=width * 0.95,
               color=[CHANGE_COLOURS[lab] for lab in CHANGE_LABELS], edgecolor=method_colour(method, methods),
               linewidth=1.2, hatch=None if i == 0 else "//", label=method,
               yerr=error_bars(f1, [_ci(pl.get(lab), "f1") for lab in CHANGE_LABELS]), ecolor="#374151", capsize=2)
    first = next(iter(per_label.values()), {})
    ax.set_xticks(x, [f"{lab}\n(n={int((first.get(lab) or {}).get('support') or 0)})" for lab in CHANGE_LABELS],
                  fontsize=8)
    ax.set_ylabel("F1 (features)")
    ax.set_ylim(0, 1.05)
    ax.grid(axis="y", alpha=0.3)
    if len(methods) > 1:
        ax.legend(fontsize=7)
    return to_png(fig)


# -- sweeps and timing --------------------------------------------------------------------------------------
def sweep_figure(parameter: str, series: Mapping[str, Sequence[tuple]], ylabel: str = "rate") -> bytes:
    """A metric against a swept parameter (DESIGN 10.13), one line per series, with error bars where a point
    has an interval.

    Parameters
    ----------
    parameter : the swept parameter's name (the x label).
    series : label -> ``[(value, metric or None), ...]`` or ``[(value, metric or None, (lo, hi) or None), ...]``.
    """
    fig = new_figure(height_in=3.2)
    ax = fig.add_subplot()
    for label, points in series.items():
        pts = sorted(((p[0], p[1], p[2] if len(p) > 2 else None) for p in points if p[1] is not None),
                     key=lambda p: p[0])
        if pts:
            ys = [p[1] for p in pts]
            ax.errorbar([p[0] for p in pts], ys, yerr=error_bars(ys, [p[2] for p in pts]), marker="o",
                        capsize=3, label=label)
    ax.set_xlabel(parameter + (" (m)" if parameter == "max_range" else " (x preset)" if parameter == "noise_scale"
                               else " (rays)" if parameter == "footprint_rays" else ""))
    ax.set_ylabel(ylabel)
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return to_png(fig)


def group_headline_figure(points: Mapping[str, Mapping[str, tuple[float, Sequence[float] | None]]]) -> bytes:
    """Headline rates per group: a dot per group and metric, with its 95 % interval as an error bar.

    Parameters
    ----------
    points : metric label -> group name -> ``(value, (lo, hi) or None)``; values are rates in [0, 1].
    """
    groups = list(dict.fromkeys(g for per in points.values() for g in per))
    fig = new_figure(height_in=1.4 + 0.32 * len(groups) * max(len(points), 1) ** 0.5)
    ax = fig.add_subplot()
    metrics = list(points)
    height = 0.8 / max(len(metrics), 1)
    y = np.arange(len(groups))
    for i, (label, per) in enumerate(points.items()):
        vals = [per[g][0] if g in per else np.nan for g in groups]
        cis = [per[g][1] if g in per else None for g in groups]
        ax.errorbar(vals, y - 0.4 + (i + 0.5) * height, xerr=error_bars(vals, cis), fmt="o", capsize=3,
                    color=method_colour(label, metrics), label=label)
    ax.set_yticks(y, groups, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(-0.02, 1.02)
    ax.set_xlabel("rate (core method); bars: 95 % interval over scenes")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return to_png(fig)


def timing_figure(timing: Mapping[str, Mapping[str, Mapping[str, float] | None]]) -> bytes:
    """Median seconds per stage (bars) with the 90th percentile (whisker), grouped by method; the trial's total
    is left to :func:`time_budget_figure` (beside the stages it would dwarf them).

    Parameters
    ----------
    timing : method -> ``timing_s`` ``{stage: {median, p90} or None}``.
    """
    stages = [s for s in STAGE_COLOURS if s != "total" and any((t or {}).get(s) for t in timing.values())]
    fig = new_figure(height_in=1.3 + 0.32 * max(len(stages), 1) * max(len(timing), 1) ** 0.5)
    ax = fig.add_subplot()
    methods = list(timing)
    height = 0.8 / max(len(methods), 1)
    y = np.arange(len(stages))
    for i, (method, t) in enumerate(timing.items()):
        med = [((t or {}).get(s) or {}).get("median", np.nan) for s in stages]
        p90 = [((t or {}).get(s) or {}).get("p90", np.nan) for s in stages]
        err = np.clip(np.array(p90, dtype=float) - np.array(med, dtype=float), 0, None)
        ax.barh(y - 0.4 + (i + 0.5) * height, med, height=height * 0.9, xerr=[np.zeros_like(err), err],
                color=[STAGE_COLOURS[s] for s in stages], alpha=max(1.0 - 0.3 * i, 0.45),
                edgecolor=method_colour(method, methods), linewidth=1.2,
                hatch=None if i == 0 else "//", label=method, capsize=2)
    ax.set_yticks(y, stages)
    ax.invert_yaxis()
    ax.set_xlabel("seconds per trial: median, whisker to p90")
    ax.grid(axis="x", alpha=0.3)
    if len(methods) > 1:
        ax.legend(fontsize=8, loc="lower right", title="method (bar edge)", title_fontsize=8)
    return to_png(fig)


def time_budget_figure(budget: Mapping[str, Any], title: str = "") -> bytes:
    """Where a trial's time goes, accounted for in full: the top bar is the mean total split into the sensor
    (viewpoint and scan), each method's own stages, the stage oracles and the rest (evaluation against the
    truth and overhead: the total minus every timed stage); below it, one bar per method split by stage.

    Parameters
    ----------
    budget : ``{"sensor": s, "methods": {method: {stage: s}}, "oracles": s, "rest": s, "total": s,
        "n_trials": n}``, mean seconds per trial (:func:`reports.render.time_budget`).
    title : an optional title (e.g. the trial of a trial page).
    """
    methods = [m for m, st in budget["methods"].items() if sum(v for v in st.values() if v) > 0]
    rows = ["whole trial", *methods]
    fig = new_figure(height_in=1.9 + 0.42 * len(rows))
    ax = fig.add_subplot()
    total = float(budget.get("total") or 0.0)
    parts: list[tuple[str, float, str, str]] = [("sensor", float(budget.get("sensor") or 0.0),
                                                  STAGE_COLOURS["sensor"], "")]
    all_methods = list(budget["methods"])
    for m in methods:
        parts.append((m, sum(v for v in budget["methods"][m].values() if v), method_colour(m, all_methods), ""))
    if budget.get("oracles"):
        parts.append(("oracles", float(budget["oracles"]), STAGE_COLOURS["oracles"], ""))
    parts.append(("evaluation + overhead", max(float(budget.get("rest") or 0.0), 0.0),
                  STAGE_COLOURS["evaluation + overhead"], "//"))

    def stacked(y: float, segments: Sequence[tuple[str, float, str, str]]) -> None:
        left = 0.0
        for _name, v, colour, hatch in segments:
            if v <= 0:
                continue
            ax.barh(y, v, left=left, height=0.62, color=colour, edgecolor="white", linewidth=1, hatch=hatch)
            if total > 0 and v / total >= 0.07:
                dark = np.mean(rgb(colour)) < 0.55
                ax.text(left + v / 2, y, f"{v:.2f} s", ha="center", va="center", fontsize=7.5,
                        color="white" if dark else "#111827")
            left += v

    stacked(0, parts)
    stages = [s for s in STAGE_COLOURS if s not in ("sensor", "total", "oracles", "evaluation + overhead")]
    for i, m in enumerate(methods, start=1):
        st = budget["methods"][m]
        stacked(i, [(s, float(st.get(s) or 0.0), STAGE_COLOURS[s], "") for s in stages])
    ax.set_yticks(range(len(rows)), [f"{r}\n{total:.2f} s" if r == "whole trial" else
                                     f"{r}\n{sum(v for v in budget['methods'][r].values() if v):.2f} s"
                                     for r in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, max(total, 1e-3) * 1.02)
    n = budget.get("n_trials")
    ax.set_xlabel("seconds per trial" + (f" (mean over {n} trials)" if n and n > 1 else ""))
    ax.grid(axis="x", alpha=0.3)
    if title:
        ax.set_title(title, fontsize=9.5)
    handles = [Patch(facecolor=c, edgecolor="#9ca3af", hatch=h, label=name) for name, _, c, h in parts]
    handles += [Patch(color=STAGE_COLOURS[s], label=s) for s in stages
                if any((budget["methods"][m].get(s) or 0) > 0 for m in methods)]
    fig.legend(handles=handles, loc="outside lower center", ncol=5, fontsize=7.5, frameon=False,
               handlelength=1.2, columnspacing=1.0)
    return to_png(fig)


def pose_scatter_figure(points: Sequence[Mapping[str, Any]], groups: Sequence[str],
                        rotation_threshold_deg: float = 1.0, translation_threshold: float = 0.01) -> bytes:
    """Pose error against the trial's range and against its viewing angle, one dot per trial.

    Parameters
    ----------
    points : ``{group, range_m, angle_deg, rotation_error_deg, translation_error_mm, ok}`` per trial (the
        core's pose after ICP); errors of None are left out.
    groups : the run's groups, in order (their colours).
    rotation_threshold_deg, translation_threshold : the success thresholds (rotation in degrees; translation
        as a fraction of the median range), drawn as grey lines.
    """
    fig = new_figure(height_in=5.6)
    axes = fig.subplots(2, 2, sharex="col", sharey="row")
    floor = {"rotation_error_deg": 1e-3, "translation_error_mm": 1e-2}
    for row, key in enumerate(("rotation_error_deg", "translation_error_mm")):
        for col, xkey in enumerate(("range_m", "angle_deg")):
            ax = axes[row, col]
            for gi, g in enumerate(groups):
                for ok, marker in ((True, "o"), (False, "x")):
                    pts = [p for p in points if p["group"] == g and bool(p.get("ok")) == ok
                           and p.get(key) is not None and p.get(xkey) is not None]
                    if pts:
                        ax.scatter([p[xkey] for p in pts], [max(float(p[key]), floor[key]) for p in pts],
                                   s=16, marker=marker, color=group_colour(gi), alpha=0.85, linewidths=1.1,
                                   facecolors=group_colour(gi) if ok else None)
            ax.set_yscale("log")
            ax.grid(alpha=0.3, which="both", lw=0.5)
            ax.tick_params(labelsize=8)
            if key == "rotation_error_deg":
                ax.axhline(rotation_threshold_deg, color="#9ca3af", lw=1, zorder=0)
            elif xkey == "range_m":
                xs = sorted(p[xkey] for p in points if p.get(xkey) is not None)
                if xs:
                    x = np.linspace(min(xs), max(xs), 20)
                    ax.plot(x, 1000 * translation_threshold * x, color="#9ca3af", lw=1, zorder=0)
    axes[0, 0].set_ylabel("rotation error (deg)", fontsize=8.5)
    axes[1, 0].set_ylabel("translation error (mm)", fontsize=8.5)
    axes[1, 0].set_xlabel("median range of the trial (m)", fontsize=8.5)
    axes[1, 1].set_xlabel("viewing angle: optical axis below horizontal (deg)", fontsize=8.5)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], ls="", marker="o", color=group_colour(i), label=g) for i, g in enumerate(groups)]
    handles += [Line2D([], [], ls="", marker="o", color="#6b7280", label="pose stated ok"),
                Line2D([], [], ls="", marker="x", color="#6b7280", label="not ok (ambiguous, ...)"),
                Line2D([], [], color="#9ca3af", label="success threshold")]
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=7.5, frameon=False)
    return to_png(fig)


# -- pictures -----------------------------------------------------------------------------------------------
TITLE_IN = 0.36  # the title band of a picture
LEGEND_IN = 0.62  # the legend band (legend, colour bar or key), reserved on every picture so rows line up
PAD_IN = 0.1


def picture_figure(image_hw: tuple[int, int], width_in: float = WIDTH_IN) -> tuple[Figure, Any, Any]:
    """The shared layout of a picture of one scan: a figure of ``width_in`` with a title band, the image axes
    and a legend band below it. Returns ``(figure, image axes, legend band axes)``."""
    h, w = image_hw
    img_w = width_in - 2 * PAD_IN
    img_h = img_w * h / max(w, 1)
    height = img_h + TITLE_IN + LEGEND_IN
    fig = Figure(figsize=(width_in, height), dpi=DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((PAD_IN / width_in, LEGEND_IN / height, img_w / width_in, img_h / height))
    band = fig.add_axes((0.02, 0.0, 0.96, (LEGEND_IN - 0.04) / height))
    band.axis("off")
    ax.set_xticks([])
    ax.set_yticks([])
    return fig, ax, band


def _picture(image: np.ndarray, title: str, legend: Sequence[tuple[str, str]] = (), width_in: float = WIDTH_IN,
             annotations: Sequence[tuple[float, float, str]] = (), key: str = "", ncol: int | None = None
             ) -> bytes:
    """An (H, W, 3) image with a title, a colour legend (or a line of ``key`` text) below it and text
    annotations (region numbers) on it."""
    fig, ax, band = picture_figure(image.shape[:2], width_in)
    ax.imshow(image, interpolation="nearest")
    h, w = image.shape[:2]
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    size = 10 if len(annotations) <= 25 else 8.5
    for x, y, text in annotations:
        ax.text(x, y, text, fontsize=size, fontweight="bold", ha="center", va="center", color="#111827",
                bbox={"boxstyle": "round,pad=0.18", "fc": "white", "ec": "#111827", "lw": 0.5, "alpha": 0.85})
    ax.set_title(title, fontsize=11, pad=4)
    if legend:
        band.legend(handles=[Patch(facecolor=c, edgecolor="#6b7280", lw=0.5, label=lab) for lab, c in legend],
                    loc="center", ncol=ncol or min(len(legend), 6), fontsize=9, frameon=False, handlelength=1.2,
                    columnspacing=1.1)
    elif key:
        band.text(0.5, 0.5, key, ha="center", va="center", fontsize=9, color="#374151", wrap=True)
    return to_png(fig)


def grey(shade: np.ndarray) -> np.ndarray:
    """A shaded image (H, W) in [0, 1] (NaN = no return) as RGB (H, W, 3); no return is black."""
    s = np.nan_to_num(np.clip(np.asarray(shade, dtype=float), 0, 1), nan=0.0)
    return np.repeat(s[..., None], 3, axis=-1)


def shaded_picture(shade: np.ndarray, title: str = "cosine-shaded range image") -> bytes:
    """The cosine-shaded range image (like the paper's Fig. 2), (H, W) in [0, 1], NaN = no return (black)."""
    return _picture(grey(shade), title, key="shade: |cos| of the angle between surface normal and ray; "
                                            "black: no return")


def range_picture(range_m: np.ndarray, title: str = "range image", limits_m: tuple[float, float] | None = None
                  ) -> bytes:
    """The range image itself, in metres, with its colour bar (NaN = no return, black).

    Parameters
    ----------
    range_m : ndarray of shape (H, W), metres (Euclidean distance along the ray; NaN: no return).
    limits_m : the colour scale (default: the 1st and 99th percentiles of the returns).
    """
    r = np.asarray(range_m, dtype=float)
    finite = r[np.isfinite(r)]
    if limits_m is None:
        limits_m = ((float(np.percentile(finite, 1)), float(np.percentile(finite, 99))) if finite.size
                    else (0.0, 1.0))
    lo, hi = limits_m
    hi = hi if hi > lo else lo + 1e-3
    fig, ax, band = picture_figure(r.shape)
    from matplotlib import colormaps

    cmap = colormaps["viridis"].with_extremes(bad=NO_RETURN)
    im = ax.imshow(np.ma.masked_invalid(r), cmap=cmap, vmin=lo, vmax=hi, interpolation="nearest")
    ax.set_title(title, fontsize=11, pad=4)
    cax = band.inset_axes((0.15, 0.62, 0.7, 0.22))
    bar = fig.colorbar(im, cax=cax, orientation="horizontal")
    bar.ax.tick_params(labelsize=8)
    bar.set_label("range along the ray (m); black: no return", fontsize=8.5, labelpad=1)
    return to_png(fig)


def hk_picture(hk_class: np.ndarray, edges: np.ndarray | None = None, valid: np.ndarray | None = None,
               title: str = "H-K curvature classes") -> bytes:
    """The H-K class image (the paper's central step): each pixel coloured by the sign class of its mean (H)
    and Gaussian (K) curvature (:class:`recognition.segmentation.SurfaceType`), jump and crease edges white,
    no return black.

    Parameters
    ----------
    hk_class : ndarray of shape (H, W), int, ``SurfaceType`` values (0: undefined).
    edges : optional ndarray of shape (H, W), nonzero on jump or crease edges.
    valid : optional bool ndarray of shape (H, W): pixels with a return (default: hk_class > 0).
    """
    from recognition.segmentation import SurfaceType

    hk = np.asarray(hk_class)
    palette = np.stack([rgb(HK_COLOURS[t.name]) for t in SurfaceType])
    img = palette[np.clip(hk, 0, len(palette) - 1)]
    ret = (hk > 0) if valid is None else np.asarray(valid, dtype=bool)
    img[~ret] = rgb(NO_RETURN)
    legend = [(HK_NAMES[t.name], HK_COLOURS[t.name]) for t in SurfaceType if t != SurfaceType.NONE]
    legend.append((HK_NAMES[SurfaceType.NONE.name], HK_COLOURS[SurfaceType.NONE.name]))
    if edges is not None:
        e = np.asarray(edges) != 0
        img[e & ret] = rgb(EDGE_COLOUR)
        legend.append(("edge (jump or crease)", EDGE_COLOUR))
    return _picture(img, title, legend, ncol=3)


def patch_centres(labels: np.ndarray, min_pixels: int = MIN_SCORED_PIXELS) -> list[tuple[float, float, int]]:
    """(x, y, id) of a representative pixel of every region of ``min_pixels`` or more: the pixel of the region
    closest to its centroid (so the number sits on the region even when it is not convex)."""
    lab = np.asarray(labels)
    out = []
    ids, counts = np.unique(lab[lab >= 0], return_counts=True)
    for i, n in zip(ids, counts, strict=True):
        if n < min_pixels:
            continue
        ys, xs = np.nonzero(lab == i)
        k = int(np.argmin((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2))
        out.append((float(xs[k]), float(ys[k]), int(i)))
    return out


def region_picture(labels: np.ndarray, title: str = "regions (core segmentation)",
                   number_min_pixels: int = MIN_SCORED_PIXELS, colours: np.ndarray | None = None,
                   key: str | None = None) -> bytes:
    """The region image (like the paper's Fig. 3): each patch id (>= 0) in its own colour, -1 black, regions of
    ``number_min_pixels`` or more numbered with their patch id.

    Parameters
    ----------
    labels : ndarray of shape (H, W), int; region ids (-1: none).
    colours : optional ndarray of shape (max id + 1, 3): the colour of each id (default
        :func:`reports.colours.region_colours`; :func:`reports.colours.matched_region_colours` gives the truth's).
    key : the line of text in the legend band (default: what the numbers are).
    """
    lab = np.asarray(labels)
    n = int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0
    colours = region_colours(n) if colours is None else np.asarray(colours, dtype=float)
    img = np.zeros((*lab.shape, 3))
    img[lab >= 0] = colours[lab[lab >= 0]]
    ann = [(x, y, str(i)) for x, y, i in patch_centres(lab, number_min_pixels)]
    if key is None:
        key = (f"numbers: region ids (regions of {number_min_pixels} pixels or more); black: no region"
               if ann else "black: no region")
    return _picture(img, title, annotations=ann, key=key)


def class_overlay_picture(shade: np.ndarray, class_index: np.ndarray, wrong: np.ndarray | None = None,
                          title: str = "classification (core)") -> bytes:
    """Each patch tinted with its label's class colour over the shaded image; ``wrong`` pixels (patches whose
    label differs from the truth class) are hatched in red stripes.

    Parameters
    ----------
    shade : ndarray of shape (H, W), the shaded image in [0, 1] (NaN = no return).
    class_index : ndarray of shape (H, W), index into ``CLASSES`` (-1 = no patch).
    wrong : optional bool ndarray of shape (H, W).
    """
    base = grey(shade)
    ci = np.asarray(class_index)
    palette = np.stack([rgb(CLASS_COLOURS[c]) for c in CLASSES])
    img = base.copy()
    m = ci >= 0
    img[m] = 0.35 * base[m] + 0.65 * palette[ci[m]]
    legend = [(c, CLASS_COLOURS[c]) for c in CLASSES]
    if wrong is not None and np.any(wrong):
        yy, xx = np.indices(ci.shape)
        stripes = ((xx + yy) // 4) % 3 == 0
        img[np.asarray(wrong) & stripes] = rgb("#dc2626")
        legend.append(("wrong label", "#dc2626"))
    return _picture(img, title, legend)


def class_picture(class_index: np.ndarray, title: str = "classes",
                  annotations: Sequence[tuple[float, float, str]] = ()) -> bytes:
    """Pixels coloured by their patch's class (the palette of :data:`reports.colours.CLASS_COLOURS`), black
    where no patch, with the class legend (``harness describe``'s ``classes.png``)."""
    ci = np.asarray(class_index)
    palette = np.stack([rgb(CLASS_COLOURS[c]) for c in CLASSES])
    img = np.zeros((*ci.shape, 3))
    img[ci >= 0] = palette[ci[ci >= 0]]
    return _picture(img, title, [(c, CLASS_COLOURS[c]) for c in CLASSES] + [("no patch", NO_RETURN)],
                    annotations=annotations)


def change_picture(shade: np.ndarray, label_index: np.ndarray, title: str) -> bytes:
    """A change map: each pixel of a visible feature tinted with its change label's colour over the shaded image.

    Parameters
    ----------
    shade : ndarray of shape (H, W) in [0, 1] (NaN = no return).
    label_index : ndarray of shape (H, W), index into ``CHANGE_MAP_LABELS`` (the change labels, then
        ``unobserved``; -1 = no label: shown grey).
    """
    base = grey(shade)
    li = np.asarray(label_index)
    palette = np.stack([rgb(CHANGE_COLOURS[c]) for c in CHANGE_MAP_LABELS])
    img = base.copy()
    m = (li >= 0) & (li < len(CHANGE_MAP_LABELS))
    img[m] = 0.3 * base[m] + 0.7 * palette[li[m]]
    present = [CHANGE_MAP_LABELS[i] for i in sorted(set(np.unique(li[m]).tolist()))] or list(CHANGE_LABELS)
    return _picture(img, title, [(c, CHANGE_COLOURS[c]) for c in present])


def registration_picture(residual_before_m: np.ndarray | None, residual_after_m: np.ndarray, title: str,
                         limit_m: float | None = None, subtitles: Sequence[str] = ()) -> bytes:
    """Registration: measured minus model range (cast from the estimated pose), before and after ICP, side by
    side (a wide figure: ``Image(span=2)``).

    Parameters
    ----------
    residual_before_m, residual_after_m : ndarray of shape (H, W), metres (NaN where either has no return).
    limit_m : colour scale limit (default: the 95th percentile of |residual| before ICP, at least 5 mm).
    subtitles : optional panel titles (default "before ICP", "after ICP"), e.g. with the pose errors.
    """
    panels = [("before ICP", residual_before_m), ("after ICP", residual_after_m)]
    panels = [(sub or name, np.asarray(r, dtype=float))
              for (name, r), sub in zip(panels, [*subtitles, "", ""], strict=False) if r is not None]
    if limit_m is None:
        ref = np.abs(panels[0][1][np.isfinite(panels[0][1])])
        limit_m = max(float(np.percentile(ref, 95)) if ref.size else 0.005, 0.005)
    h, w = panels[0][1].shape
    n = len(panels)
    width = WIDE_IN if n > 1 else WIDTH_IN
    fig = new_figure(width, (width / n - 0.3) * h / max(w, 1) + 1.3)
    axes = fig.subplots(1, n, squeeze=False)[0]
    im = None
    from matplotlib import colormaps

    cmap = colormaps["RdBu_r"].with_extremes(bad="#d1d5db")
    for ax, (name, r) in zip(axes, panels, strict=True):
        im = ax.imshow(np.ma.masked_invalid(r * 1000.0), cmap=cmap, vmin=-limit_m * 1000, vmax=limit_m * 1000,
                       interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_xticks([])
        ax.set_yticks([])
    bar = fig.colorbar(im, ax=list(axes), orientation="horizontal", location="bottom", shrink=0.5, aspect=40,
                       extend="both")
    bar.set_label("measured - model range (mm): red, the scene is behind the model; blue, in front; "
                  "light grey: no return in one of them", fontsize=8.5)
    fig.suptitle(title, fontsize=11)
    return to_png(fig)
