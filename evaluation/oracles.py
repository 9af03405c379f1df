"""Stage-isolating oracles (DESIGN 10.10): stage outputs built from the truth, to feed the next stage
through its ordinary interface. The core never learns that an oracle is in use.

* ``segmentation``: the truth surfaces' connected pixel sets become the patches (with the truth normals);
* ``classification``: every patch carries the truth class of its surface, with that class's dedicated fit;
* ``pairing``: the pose stage receives the truth correspondences patch -> model feature;
* ``pose``: change detection receives the true ``T_world_sensor``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from evaluation.patches import patch_truth, truth_regions
from recognition import fitting as primitives
from recognition.classification import PatchClassification
from recognition.describe import SceneDescription
from recognition.fitting import fit_plane_lsq
from recognition.segmentation import Patch, Segmentation, SurfaceType
from scenes.perturb import ChangeTruth
from scenes.vocabulary import CLASSES
from sensors.range_image import Scan, ScanTruth

ORACLES = ("segmentation", "classification", "pairing", "pose")
_SURFACE_TYPE = {"PLAN": SurfaceType.PLANAR, "CYL": SurfaceType.CYLINDRICAL, "CONE": SurfaceType.CYLINDRICAL,
                 "SPH": SurfaceType.ELLIPTIC, "OTH": SurfaceType.HYPERBOLIC}


def truth_segmentation(scan: Scan, truth: ScanTruth, sigma: np.ndarray) -> Segmentation:
    """The ideal segmentation: one patch per connected piece of each truth surface, truth normals.

    Curvature images are not part of the ideal segmentation's information and are left NaN.
    """
    regions = truth_regions(truth, scan.valid)
    h, w = regions.shape
    ids, inverse = np.unique(regions.reshape(-1), return_inverse=True)
    labels = np.full(h * w, -1, dtype=np.int32)
    order = np.argsort(inverse, kind="stable")
    starts = np.searchsorted(inverse[order], np.arange(len(ids)))
    groups = np.split(order, starts[1:])
    patches = []
    pieces = [(ids[k], g) for k, g in enumerate(groups) if ids[k] >= 0]
    pieces.sort(key=lambda item: -len(item[1]))
    sid_flat = truth.surface_id.reshape(-1)
    pts = scan.points.reshape(-1, 3)
    for new_id, (_, pix) in enumerate(pieces):
        labels[pix] = new_id
        cls = truth.surfaces[int(sid_flat[pix[0]])].truth_class
        rc = np.column_stack(np.unravel_index(pix, (h, w)))
        fit = fit_plane_lsq(pts[pix], sigma.reshape(-1)[pix]) if len(pix) >= 3 else None
        patches.append(Patch(new_id, rc, len(pix), _SURFACE_TYPE[cls], fit, len(pix) < 50, False))
    nan = np.full((h, w), np.nan)
    normals = np.where(scan.valid[..., None], truth.normals, np.nan)
    return Segmentation(labels.reshape(h, w), np.zeros((h, w), np.int8), nan, nan, nan, nan, normals,
                        np.zeros((h, w), np.uint8), tuple(patches))


def truth_classification(description: SceneDescription, truth: ScanTruth) -> SceneDescription:
    """The description with every patch labelled by its truth class and fitted with that class's primitive."""
    sid = truth.surface_id.reshape(-1)
    normals = description.segmentation.normals.reshape(-1, 3)
    patches = []
    for p in description.patches:
        s, _ = patch_truth(p.pixels, sid)
        cls = truth.surfaces[s].truth_class if s >= 0 else "OTH"
        prim = _fit_class(cls, p.points, np.maximum(p.sigma, 1e-6), normals[p.pixels])
        probs = {c: float(c == cls) for c in CLASSES}
        plaus = {c: float(c == cls) for c in ("CYL", "SPH", "CONE")}
        inv = dict(p.classification.invariants) if p.classification.label == cls else {}
        if prim is not None and getattr(prim, "ok", False) and hasattr(prim, "radius"):
            inv["radius_m"] = (float(prim.radius), float(getattr(prim, "radius_sigma", np.nan)))
        patches.append(replace(p, classification=PatchClassification(cls, probs, plaus, prim, inv,
                                                                     reason="classification oracle")))
    return replace(description, patches=tuple(patches))


def _fit_class(cls: str, points: np.ndarray, sigma: np.ndarray, normals: np.ndarray):
    if len(points) < 10:
        return None
    nrm = normals if np.all(np.isfinite(normals)) else None
    return primitives.fit_primitive(cls, points, sigma, nrm)


def truth_pairings(description: SceneDescription, truth: ScanTruth,
                   change_truth: ChangeTruth) -> dict[int, tuple[str, str]]:
    """Patch id -> (model feature, part) it truly lies on, for patches on a priori features that kept their
    place (unchanged in the truth): the correspondences an ideal matcher would give the pose stage."""
    sid = truth.surface_id.reshape(-1)
    out = {}
    for p in description.patches:
        s, frac = patch_truth(p.pixels, sid)
        if s < 0 or frac < 0.5:
            continue
        surface = truth.surfaces[s]
        change = change_truth.features.get(surface.feature_id)
        if change is not None and change.label == "unchanged":
            out[int(p.id)] = (surface.feature_id, surface.part)
    return out
