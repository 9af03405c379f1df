"""The report's fixed palette: one colour per surface class, per change label and per method.

Every figure and picture of a report takes its colours from here, so that CYL is the same orange in the
confusion matrix, the classification overlay and the per-class bars, and ``missing`` the same red in the
change map and the F1 chart. Colours are hex strings (``#rrggbb``); :func:`rgb` converts them for images.
"""

from __future__ import annotations

import numpy as np

from scenes.vocabulary import CHANGE_LABELS, CLASSES  # the keys of the palettes below (declared in scenes)

__all__ = ["CLASSES", "CHANGE_LABELS", "CLASS_COLOURS", "CHANGE_COLOURS", "HOOVER_COLOURS", "METHOD_COLOURS",
           "PEER_CYCLE", "STAGE_COLOURS", "method_colour", "rgb", "region_colours"]

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
    "unobserved": "#f0f0f0",
}

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

STAGE_COLOURS: dict[str, str] = {
    "sensor": "#64748b", "segmentation": "#0b5fa5", "classification": "#dd8452", "matching": "#8172b3",
    "icp": "#55a868", "change": "#d62728", "total": "#1f2937",
}

def method_colour(name: str, methods: list[str] | tuple[str, ...] = ()) -> str:
    """The colour of method ``name``: fixed for ``core`` and ``paper``, from :data:`PEER_CYCLE` otherwise
    (by the name's position among the non-fixed ``methods``, sorted, so it is stable within a report)."""
    if name in METHOD_COLOURS:
        return METHOD_COLOURS[name]
    peers = sorted(m for m in {*methods, name} if m not in METHOD_COLOURS)
    return PEER_CYCLE[peers.index(name) % len(PEER_CYCLE)]


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
