"""Figures of the report, drawn with matplotlib's Agg canvas (no pyplot, no global state) and returned as PNG bytes.

Plots take plain summary data (the dicts of ``summary.json`` and trial records); pictures take image arrays.
Colours come from :mod:`reports.colours`; axes carry their units. Figures are about 640 px wide at 100 dpi.
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
    HOOVER_COLOURS,
    STAGE_COLOURS,
    method_colour,
    region_colours,
    rgb,
)

DPI = 100
WIDTH_IN = 6.4
HOOVER_NAMES = {"correct_detection_rate": "correct detection", "over_rate": "over-segmentation",
                "under_rate": "under-segmentation", "missed_rate": "missed", "noise_rate": "noise"}
METHOD_STYLES = ("-", "--", ":", "-.")


def new_figure(width_in: float = WIDTH_IN, height_in: float = 3.6) -> Figure:
    """A figure on its own Agg canvas."""
    fig = Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def to_png(fig: Figure) -> bytes:
    """The figure as PNG bytes."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, facecolor="white")
    return buf.getvalue()


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
def hoover_sweep_figure(sweeps: Mapping[str, Sequence[Mapping[str, float]]], tolerance: float | None = None
                        ) -> bytes:
    """Hoover rates against the overlap tolerance T, one line style per method.

    Parameters
    ----------
    sweeps : method name -> the ``segmentation.sweep`` rows ``[{tolerance, correct_detection_rate, ...}]``.
    tolerance : the headline tolerance, marked with a vertical line.
    """
    fig = new_figure(height_in=3.8)
    ax = fig.add_subplot()
    methods = list(sweeps)
    for i, (method, rows) in enumerate(sweeps.items()):
        t = [r["tolerance"] for r in rows]
        for key, colour in HOOVER_COLOURS.items():
            ax.plot(t, [r[key] for r in rows], _style(i), color=colour, marker="o", markersize=3,
                    label=f"{HOOVER_NAMES[key]}" + (f" ({method})" if len(methods) > 1 else ""))
    if tolerance is not None:
        ax.axvline(tolerance, color="#9ca3af", lw=1, zorder=0)
    ax.set_xlabel("overlap tolerance T (fraction of region pixels)")
    ax.set_ylabel("rate (fraction of regions)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2 if len(methods) > 1 else 1, loc="upper left", bbox_to_anchor=(1.01, 1.0))
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


def reliability_figure(tables: Mapping[str, Sequence[Mapping[str, float]]]) -> bytes:
    """Reliability diagram: accuracy against the stated probability of the winning label, per bin.

    Parameters
    ----------
    tables : method name -> ``classification.reliability`` rows ``[{low, high, confidence, accuracy, count}]``.
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
    axc.set_xlabel("stated probability of the winning label")
    axc.set_ylabel("patches")
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
                    rotation_threshold_deg: float = 1.0) -> bytes:
    """Cumulative distributions of the rotation and translation errors, before and after ICP.

    Parameters
    ----------
    errors : method -> ``{"rotation_error_deg": {"after ICP": [...], "initial": [...]},
        "translation_error_mm": {...}}``, one value per trial (non-finite values are dropped).
    rotation_threshold_deg : the success threshold on rotation, marked on its axis.
    """
    fig = new_figure(height_in=3.2)
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
                        color=method_colour(method, methods), label=f"{method}, {stage}")
        if key == "rotation_error_deg":
            ax.axvline(rotation_threshold_deg, color="#9ca3af", lw=1, zorder=0)
        ax.set_xscale("symlog", linthresh=0.1 if key == "rotation_error_deg" else 1.0)
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
    """Median seconds per stage (bars) with the 90th percentile (whisker), grouped by method.

    Parameters
    ----------
    timing : method -> ``timing_s`` ``{stage: {median, p90} or None}``.
    """
    stages = [s for s in STAGE_COLOURS if any((t or {}).get(s) for t in timing.values())]
    fig = new_figure(height_in=0.9 + 0.35 * max(len(stages), 1) * max(len(timing), 1) ** 0.5)
    ax = fig.add_subplot()
    methods = list(timing)
    height = 0.8 / max(len(methods), 1)
    y = np.arange(len(stages))
    for i, (method, t) in enumerate(timing.items()):
        med = [((t or {}).get(s) or {}).get("median", np.nan) for s in stages]
        p90 = [((t or {}).get(s) or {}).get("p90", np.nan) for s in stages]
        err = np.clip(np.array(p90) - np.array(med), 0, None)
        ax.barh(y - 0.4 + (i + 0.5) * height, med, height=height * 0.9, xerr=[np.zeros_like(err), err],
                color=[STAGE_COLOURS[s] for s in stages], alpha=max(1.0 - 0.3 * i, 0.45),
                edgecolor=method_colour(method, methods),
                hatch=None if i == 0 else "//", label=method, capsize=2)
    ax.set_yticks(y, stages)
    ax.invert_yaxis()
    ax.set_xlabel("time per trial (s): median, whisker to p90")
    ax.grid(axis="x", alpha=0.3)
    if len(methods) > 1:
        ax.legend(fontsize=7, loc="lower right")
    return to_png(fig)


# -- pictures -----------------------------------------------------------------------------------------------
def _picture(image: np.ndarray, title: str, legend: Sequence[tuple[str, str]] = (), width_in: float = 4.2,
             annotations: Sequence[tuple[float, float, str]] = ()) -> bytes:
    """An (H, W, 3) image with a title, an optional colour legend below it and text annotations."""
    h, w = image.shape[:2]
    legend_in = 0.35 if legend else 0.0
    fig = new_figure(width_in, width_in * h / max(w, 1) + 0.35 + legend_in)
    ax = fig.add_subplot()
    ax.imshow(image, interpolation="nearest")
    for x, y, text in annotations:
        ax.text(x, y, text, fontsize=6, ha="center", va="center", color="black",
                bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.75})
    ax.set_title(title, fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    if legend:
        fig.legend(handles=[Patch(color=c, label=lab) for lab, c in legend], loc="outside lower center",
                   ncol=min(len(legend), 6), fontsize=7, frameon=False, handlelength=1.0, columnspacing=0.8)
    return to_png(fig)


def grey(shade: np.ndarray) -> np.ndarray:
    """A shaded image (H, W) in [0, 1] (NaN = no return) as RGB (H, W, 3); no return is black."""
    s = np.nan_to_num(np.clip(np.asarray(shade, dtype=float), 0, 1), nan=0.0)
    return np.repeat(s[..., None], 3, axis=-1)


def shaded_picture(shade: np.ndarray, title: str = "cosine-shaded range image") -> bytes:
    """The cosine-shaded range image (like the paper's Fig. 2), (H, W) in [0, 1], NaN = no return (black)."""
    return _picture(grey(shade), title)


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
                   number_min_pixels: int = MIN_SCORED_PIXELS) -> bytes:
    """The region image (like the paper's Fig. 3): each patch id (>= 0) in its own colour, -1 black, regions of
    ``number_min_pixels`` or more numbered with their patch id."""
    lab = np.asarray(labels)
    colours = region_colours(int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0)
    img = np.zeros((*lab.shape, 3))
    img[lab >= 0] = colours[lab[lab >= 0]]
    ann = [(x, y, str(i)) for x, y, i in patch_centres(lab, number_min_pixels)]
    return _picture(img, title, annotations=ann)


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


def change_picture(shade: np.ndarray, label_index: np.ndarray, title: str) -> bytes:
    """A change map: each pixel of a visible feature tinted with its change label's colour over the shaded image.

    Parameters
    ----------
    shade : ndarray of shape (H, W) in [0, 1] (NaN = no return).
    label_index : ndarray of shape (H, W), index into ``CHANGE_LABELS`` (-1 = no label: shown grey).
    """
    base = grey(shade)
    li = np.asarray(label_index)
    palette = np.stack([rgb(CHANGE_COLOURS[c]) for c in CHANGE_LABELS])
    img = base.copy()
    m = li >= 0
    img[m] = 0.3 * base[m] + 0.7 * palette[li[m]]
    present = [CHANGE_LABELS[i] for i in sorted(set(np.unique(li[m]).tolist()))] or list(CHANGE_LABELS)
    return _picture(img, title, [(c, CHANGE_COLOURS[c]) for c in present])


def registration_picture(residual_before_m: np.ndarray | None, residual_after_m: np.ndarray, title: str,
                         limit_m: float | None = None) -> bytes:
    """Registration: measured minus model range (cast from the estimated pose), before and after ICP.

    Parameters
    ----------
    residual_before_m, residual_after_m : ndarray of shape (H, W), metres (NaN where either has no return).
    limit_m : colour scale limit (default: the 95th percentile of |residual| before ICP, at least 5 mm).
    """
    panels = [("before ICP", residual_before_m), ("after ICP", residual_after_m)]
    panels = [(name, np.asarray(r, dtype=float)) for name, r in panels if r is not None]
    if limit_m is None:
        ref = np.abs(panels[0][1][np.isfinite(panels[0][1])])
        limit_m = max(float(np.percentile(ref, 95)) if ref.size else 0.005, 0.005)
    h, w = panels[0][1].shape
    fig = new_figure(6.4, 3.2 * h / max(w, 1) + 0.9)
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    im = None
    for ax, (name, r) in zip(axes, panels, strict=True):
        im = ax.imshow(np.ma.masked_invalid(r * 1000.0), cmap="RdBu_r", vmin=-limit_m * 1000, vmax=limit_m * 1000,
                       interpolation="nearest")
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.colorbar(im, ax=list(axes), shrink=0.8, label="measured - model range (mm)")
    fig.suptitle(title, fontsize=9)
    return to_png(fig)
