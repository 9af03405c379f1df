"""Per-trial evaluation of a scene description against the scan's truth: Hoover segmentation scores and
per-patch classification records (truth class of the surface each patch mostly covers, invariant errors)."""

from __future__ import annotations

from typing import Any

import numpy as np

from evaluation.hoover import (
    DEFAULT_SWEEP,
    HooverScore,
    connected_truth_regions,
    missed_causes,
    overlap_table,
    score_table,
)
from evaluation.metrics import HOOVER_RATES, MIN_SCORED_PIXELS
from scenes.features import Cone, Cylinder, Sphere
from scenes.model import SceneModel
from sensors.range_image import FLAG_MIXED, FLAG_OUTLIER, ScanTruth

TOLERANCE = 0.8
MIN_TRUTH_PIXELS = MIN_SCORED_PIXELS  # truth regions of fewer pixels are not scored (evaluation.metrics)
#: lower edges (pixels) of the truth-region size classes; the last is open
SIZE_BINS = (MIN_SCORED_PIXELS, 500, 1000, 5000)
TRUTH_CLASSES = ("correct", "over", "under", "missed")


def truth_regions(truth: ScanTruth, valid: np.ndarray) -> np.ndarray:
    """Connected pieces of each truth surface over the pixels that measured it (-1 elsewhere).

    Pixels without a return, and mixed pixels and outliers (whose measured point lies on no surface: a
    blend across a depth edge, or a random range), belong to no truth region.
    """
    measured = valid & ((truth.flags & (FLAG_MIXED | FLAG_OUTLIER)) == 0)
    ids = np.where(measured, truth.surface_id, -1)
    return connected_truth_regions(ids)


def segmentation_section(labels: np.ndarray, truth: ScanTruth, valid: np.ndarray) -> dict[str, Any]:
    """Hoover rates at T = 0.8 over truth regions of >= 200 pixels, the counts per region size (``by_size``),
    plus the sweep over T in [0.51, 0.95]."""
    regions = truth_regions(truth, valid)
    table = overlap_table(labels, regions)  # independent of the tolerance: computed once for the sweep too
    score = score_table(table, TOLERANCE, min_truth_pixels=MIN_TRUTH_PIXELS)
    # a rate with nothing to count (no truth region of 200 px, or no machine region) is null, not NaN
    out = {k: (None if isinstance(v, float | np.floating) and not np.isfinite(v) else
               float(v) if isinstance(v, float | np.floating) else v) for k, v in score.as_dict().items()}
    out["min_truth_pixels"] = MIN_TRUTH_PIXELS
    out["n_truth"] = int(score.n_truth)
    # the missed rate split by cause (they sum to it)
    causes = missed_causes(labels, regions, score, table)
    out["missed_causes"] = {k: (v / score.n_truth if score.n_truth else None) for k, v in causes.items()}
    out["n_machine"] = int(score.n_machine)
    out["by_size"] = counts_by_size(regions, score)
    out["sweep"] = [{"tolerance": float(t), **{k: _finite(getattr(s, k)) for k in HOOVER_RATES}}
                    for t, s in ((t, score_table(table, float(t), MIN_TRUTH_PIXELS)) for t in DEFAULT_SWEEP)]
    return out


def counts_by_size(regions: np.ndarray, score: HooverScore) -> list[dict[str, Any]]:
    """The scored truth regions counted per size class (``SIZE_BINS``) and Hoover category: where a segmenter
    fails is mostly a matter of size (``max_pixels`` None: no upper bound; classes are ``[min, max)``)."""
    category = np.asarray(score.truth_class)
    scored = np.isin(category, TRUTH_CLASSES)
    ids = np.asarray(score.truth_ids, np.int64)[scored]
    sizes = np.bincount(regions[regions >= 0].ravel(), minlength=int(ids.max()) + 1 if ids.size else 0)[ids]
    size_class = np.searchsorted(SIZE_BINS, sizes, side="right") - 1  # -1: below the smallest class
    category = category[scored]
    counts = {c: np.bincount(size_class[(category == c) & (size_class >= 0)], minlength=len(SIZE_BINS))
              for c in TRUTH_CLASSES}
    edges = [*SIZE_BINS, None]
    return [{"min_pixels": edges[i], "max_pixels": edges[i + 1],
             "n_truth": int(sum(counts[c][i] for c in TRUTH_CLASSES)),
             **{f"n_{c}": int(counts[c][i]) for c in TRUTH_CLASSES}} for i in range(len(SIZE_BINS))]


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def patch_truth(pixels: np.ndarray, surface_id_flat: np.ndarray) -> tuple[int, float]:
    """The truth surface a patch mostly covers (-1 = none) and the fraction of its pixels on it."""
    ids = surface_id_flat[pixels]
    values, counts = np.unique(ids, return_counts=True)
    k = int(np.argmax(counts))
    return int(values[k]), float(counts[k] / len(ids))


def classification_section(description, truth: ScanTruth, actual: SceneModel) -> dict[str, Any]:
    """One record per patch: truth class and feature, label, probabilities, and invariant errors."""
    sid = truth.surface_id.reshape(-1)
    rows = []
    for patch in description.patches:
        s, frac = patch_truth(patch.pixels, sid)
        surf = truth.surfaces[s] if s >= 0 else None
        cls = patch.classification
        row: dict[str, Any] = {
            "patch": int(patch.id), "n_pixels": int(patch.n_pixels),
            "truth": surf.truth_class if surf else "OTH", "truth_feature": surf.feature_id if surf else None,
            "truth_part": surf.part if surf else None, "truth_fraction": frac,
            "label": cls.label, "probabilities": {k: float(v) for k, v in cls.probabilities.items()},
            "plausibilities": {k: float(v) for k, v in cls.plausibilities.items()},
            "reason": cls.reason, "small": bool(patch.small), "noisy": bool(patch.noisy),
        }
        if "path" in cls.details:  # how the label was reached, and the floor its probabilities were mixed with
            row["path"], row["floor"] = cls.details["path"], float(cls.details["floor"])
        if surf is not None and "radius_m" in cls.invariants and surf.part in ("side", "surface"):
            true_r = _true_radius(actual.feature(surf.feature_id))
            if true_r is not None:
                r, r_sigma = cls.invariants["radius_m"]
                row["radius"] = {"estimate_m": float(r), "sigma_m": float(r_sigma), "truth_m": true_r}
        rows.append(row)
    return {"patches": rows}


def _true_radius(feature) -> float | None:
    if isinstance(feature, Cylinder | Sphere):
        return float(feature.radius)
    if isinstance(feature, Cone):
        return None  # a cone's radius varies along the patch; its half-angle is compared instead
    return None
