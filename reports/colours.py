"""The project's one colour language: one colour per surface class, H-K curvature class, change label, method
and timing stage, shared by the report, the per-trial pages and ``harness describe``.

Every figure and picture takes its colours from here, so that CYL is the same orange in the confusion matrix,
the classification overlay, the per-class bars and ``harness describe``'s ``classes.png``, and ``missing`` the
same red in the change map, the F1 chart and the 3D scene. The H-K classes take the colour of the surface class
they lead to (planar: PLAN's blue, cylindrical: CYL's orange, elliptic: SPH's green), so the curvature image
and the classification read together. Colours are hex strings (``#rrggbb``); :func:`rgb` converts them for
images. Region pictures colour a machine region like the truth surface it mostly covers
(:func:`matched_region_colours`), so a correct segmentation looks like its truth.
"""

from __future__ import annotations

import numpy as np

from recognition.segmentation import SurfaceType  # the H-K classes (the core's own enum; no truth in it)
from scenes.vocabulary import CHANGE_LABELS, CLASSES, UNOBSERVED  # the keys of the palettes below

__all__ = ["CLASSES", "CHANGE_LABELS", "CLASS_COLOURS", "CHANGE_COLOURS", "HK_COLOURS", "HK_NAMES",
           "HOOVER_COLOURS", "METHOD_COLOURS", "PEER_CYCLE", "GROUP_CYCLE", "STAGE_COLOURS", "EDGE_COLOUR",
           "NO_RETURN", "method_colour", "group_colour", "rgb", "region_colours", "matched_region_colours",
           "shade_variant"]

CLASS_COLOURS: dict[str, str] = {
    "PLAN": "#4c72b0",  # blue
    "CYL": "#dd8452",  # orange
    "SPH": "#55a868",  # green
    "CONE": "#8172b3",  # purple
    "OTH": "#8c8c8c",  # grey
}

CHANGE_COLOURS: dict[str, str] = {
    "unchanged": "#b8b8b8",  # light grey
    "moved": "#1f77b4",  # blue
    "missing": "#d62728",  # red
    "altered": "#ff7f0e",  # orange
    "new": "#2ca02c",  # green
    UNOBSERVED: "#f0f0f0",
}

#: H-K curvature classes (:class:`recognition.segmentation.SurfaceType`), keyed by the enum's name.
HK_COLOURS: dict[str, str] = {
    SurfaceType.NONE.name: "#3f3f46",  # curvature undefined (a return, but no class): dark grey
    SurfaceType.PLANAR.name: CLASS_COLOURS["PLAN"],  # H = 0, K = 0
    SurfaceType.CYLINDRICAL.name: CLASS_COLOURS["CYL"],  # K = 0, H != 0 (cones too)
    SurfaceType.ELLIPTIC.name: CLASS_COLOURS["SPH"],  # K > 0
    SurfaceType.HYPERBOLIC.name: "#c44e52",  # K < 0 (saddles: the inside of an elbow's bend)
}
HK_NAMES: dict[str, str] = {
    SurfaceType.NONE.name: "undefined", SurfaceType.PLANAR.name: "planar (H=0, K=0)",
    SurfaceType.CYLINDRICAL.name: "cylindrical (K=0)", SurfaceType.ELLIPTIC.name: "elliptic (K>0)",
    SurfaceType.HYPERBOLIC.name: "hyperbolic (K<0)",
}
EDGE_COLOUR = "#ffffff"  # jump and crease edges over the H-K image
NO_RETURN = "#000000"  # pixels without a return, in every picture

HOOVER_COLOURS: dict[str, str] = {
    "correct_detection_rate": "#2ca02c",
    "over_rate": "#1f77b4",
    "under_rate": "#9467bd",
    "missed_rate": "#d62728",
    "noise_rate": "#7f7f7f",
}

#: Fixed colours of the known methods; other (later) peers take :data:`PEER_CYCLE` in name order.
METHOD_COLOURS: dict[str, str] = {"core": "#0b5fa5", "paper": "#c2410c"}
PEER_CYCLE = ("#15803d", "#7e22ce", "#a16207", "#be185d", "#0e7490", "#4d7c0f")
#: Groups (scene/sensor) in scatter plots, in the order the run lists them.
GROUP_CYCLE = ("#0e7490", "#a16207", "#7e22ce", "#be185d", "#4d7c0f", "#1f2937")

STAGE_COLOURS: dict[str, str] = {
    "sensor": "#64748b", "segmentation": "#0891b2", "classification": "#dd8452", "matching": "#8172b3",
    "icp": "#55a868", "change": "#db2777", "oracles": "#a8a29e", "evaluation + overhead": "#e7e5e4",
    "total": "#1f2937",
}


def method_colour(name: str, methods: list[str] | tuple[str, ...] = ()) -> str:
    """The colour of method ``name``: fixed for ``core`` and ``paper``, from :data:`PEER_CYCLE` otherwise
    (by the name's position among the non-fixed ``methods``, sorted, so it is stable within a report)."""
    if name in METHOD_COLOURS:
        return METHOD_COLOURS[name]
    peers = sorted(m for m in {*methods, name} if m not in METHOD_COLOURS)
    return PEER_CYCLE[peers.index(name) % len(PEER_CYCLE)]


def group_colour(index: int) -> str:
    """The colour of the ``index``-th group of a run (scatter plots)."""
    return GROUP_CYCLE[index % len(GROUP_CYCLE)]


def rgb(colour: str) -> np.ndarray:
    """``#rrggbb`` -> ndarray of shape (3,), float64 in [0, 1]."""
    c = colour.lstrip("#")
    if len(c) != 6:
        raise ValueError(f"expected a colour '#rrggbb', got {colour!r}")
    return np.array([int(c[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])


def region_colours(n: int) -> np.ndarray:
    """``n`` distinct, deterministic colours for region (patch) ids, ndarray of shape (n, 3) in [0, 1].

    A golden-ratio walk around the hue circle at two saturations, so neighbouring ids differ clearly.
    """
    from matplotlib.colors import hsv_to_rgb

    k = np.arange(max(n, 0))
    hue = (k * 0.618033988749895) % 1.0
    sat = np.where(k % 2 == 0, 0.65, 0.45)
    val = np.where(k % 3 == 0, 0.95, 0.8)
    return hsv_to_rgb(np.stack([hue, sat, val], axis=-1).reshape(-1, 3)) if n > 0 else np.zeros((0, 3))


def shade_variant(colour: np.ndarray, k: int) -> np.ndarray:
    """The ``k``-th variant of an RGB colour (k = 0: itself; then alternately lighter and darker), for the
    second, third, ... machine region on one truth surface."""
    c = np.asarray(colour, dtype=float)
    if k <= 0:
        return c
    step = (k + 1) // 2
    if k % 2:  # lighter
        return c + (1.0 - c) * min(0.3 * step, 0.75)
    return c * max(1.0 - 0.3 * step, 0.25)  # darker


def matched_region_colours(labels: np.ndarray, truth_ids: np.ndarray, min_share: float = 0.5
                           ) -> np.ndarray:
    """Colours of the machine regions of ``labels`` in the truth's palette.

    A machine region takes the colour (:func:`region_colours`) of the truth surface it mostly covers (at
    least ``min_share`` of its pixels); the largest region on a surface takes the colour itself, further
    regions on the same surface (an over-segmentation) a lighter or darker variant of it
    (:func:`shade_variant`). Regions that no truth surface dominates take colours of the palette beyond the
    truth's, so they stand out.

    Parameters
    ----------
    labels : ndarray of shape (H, W), int; machine region ids (-1: none).
    truth_ids : ndarray of shape (H, W), int; truth surface ids (-1: none), the ids that index the truth
        picture's :func:`region_colours`.
    min_share : fraction of a region's pixels that must lie on one surface for it to take that colour.

    Returns
    -------
    ndarray of shape (max(labels) + 1, 3), RGB in [0, 1].
    """
    lab = np.asarray(labels)
    tru = np.asarray(truth_ids)
    if lab.shape != tru.shape:
        raise ValueError(f"expected truth ids of shape {lab.shape}, got {tru.shape}")
    n = int(lab.max()) + 1 if lab.size and lab.max() >= 0 else 0
    n_truth = int(tru.max()) + 1 if tru.size and tru.max() >= 0 else 0
    out = np.zeros((n, 3))
    if n == 0:
        return out
    truth_palette = region_colours(n_truth)
    m = (lab >= 0) & (tru >= 0)
    overlap = np.zeros((n, max(n_truth, 1)), dtype=np.int64)
    np.add.at(overlap, (lab[m], tru[m]), 1)
    size = np.bincount(lab[lab >= 0], minlength=n)
    best = overlap.argmax(axis=1)
    share = np.divide(overlap[np.arange(n), best], size, out=np.zeros(n), where=size > 0)
    taken: dict[int, int] = {}
    spare = region_colours(n_truth + n)[n_truth:]
    for i in sorted(range(n), key=lambda j: (-size[j], j)):  # the largest region on a surface first
        if n_truth and share[i] >= min_share:
            g = int(best[i])
            out[i] = shade_variant(truth_palette[g], taken.get(g, 0))
            taken[g] = taken.get(g, 0) + 1
        else:
            out[i] = spare[i]
    return out
