"""Scene description (the paper's section 3): segmentation, then classification of every patch.

``describe(scan)`` is what the core makes of one range image before any matching: a set of labelled
patches (PLAN, CYL, SPH, CONE, OTH) with their dedicated fits, uncertainties and invariants, in the
sensor frame. It sees only the :class:`sensors.range_image.Scan` (range, points, sensor and noise
model); its per-pixel sigma comes from the noise model and its own normal estimates (DESIGN 10.1).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from recognition.classify import PaperParams, PatchClassification, SelectParams, classify_patch
from recognition.segmentation import Segmentation, SegmentationParams, SurfaceType, segment
from sensors.range_image import Scan

CLASSIFIERS = ("select", "paper")


@dataclass(frozen=True)
class DescribeParams:
    """Parameters of :func:`describe`.

    Attributes
    ----------
    classifier : ``select`` (the core's model-selection classifier) or ``paper`` (the paper's rule).
    segmentation : parameters of the H-K segmenter.
    classifier_params : ``SelectParams`` or ``PaperParams`` (None: the classifier's defaults).
    min_classify_pixels : patches smaller than this are labelled OTH without fitting (reason ``too small``).
    """

    classifier: str = "select"
    segmentation: SegmentationParams = field(default_factory=SegmentationParams)
    classifier_params: SelectParams | PaperParams | None = None
    min_classify_pixels: int = 30

    def __post_init__(self):
        if self.classifier not in CLASSIFIERS:
            raise ValueError(f"classifier must be one of {', '.join(CLASSIFIERS)}, got {self.classifier!r}")
        if self.min_classify_pixels < 1:
            raise ValueError(f"min_classify_pixels must be >= 1, got {self.min_classify_pixels}")


@dataclass(frozen=True)
class ScenePatch:
    """One labelled patch of the scene description (sensor frame, metres).

    Attributes
    ----------
    id : the patch's value in :attr:`SceneDescription.labels`.
    pixels : ndarray of shape (N,), flat indices into the (H, W) image.
    points : ndarray of shape (N, 3), the patch's points in the sensor frame.
    sigma : ndarray of shape (N,), the core's per-point range sigma (metres).
    surface_type : the segmenter's H-K class of the patch.
    classification : label, probabilities, plausibilities, dedicated fit, invariants.
    small, noisy : the segmenter's flags (kept, never dropped).
    """

    id: int
    pixels: np.ndarray
    points: np.ndarray
    sigma: np.ndarray
    surface_type: SurfaceType
    classification: PatchClassification
    small: bool
    noisy: bool

    @property
    def label(self) -> str:
        return self.classification.label

    @property
    def n_pixels(self) -> int:
        return len(self.pixels)


@dataclass(frozen=True)
class SceneDescription:
    """Patches of one range image, their label image and the segmentation they came from."""

    patches: tuple[ScenePatch, ...]
    labels: np.ndarray
    segmentation: Segmentation
    sigma: np.ndarray
    timing_s: dict[str, float]

    def class_image(self) -> np.ndarray:
        """(H, W) int8 index into ``CLASSES`` of each pixel's patch label (-1 where none)."""
        from recognition.classify import CLASSES

        out = np.full(self.labels.shape, -1, dtype=np.int8)
        for p in self.patches:
            out.flat[p.pixels] = CLASSES.index(p.label)
        return out


def core_sigma(scan: Scan, normals: np.ndarray | None = None) -> np.ndarray:
    """The core's own per-pixel range sigma (H, W), metres: the noise model at the measured range, at the
    incidence of the estimated normals when given (head-on otherwise); NaN where there is no return."""
    rays = scan.sensor.ray_directions()
    cos_inc = 1.0 if normals is None else np.where(np.isfinite(normals[..., 0]),
                                                   np.abs(np.sum(normals * rays, axis=-1)), 1.0)
    sigma = scan.noise.sigma(scan.range, cos_inc, rays[..., 2])
    return np.where(scan.valid, sigma, np.nan)


def describe(scan: Scan, params: DescribeParams = DescribeParams(),
             segmentation: Segmentation | None = None) -> SceneDescription:
    """Segment ``scan`` (unless ``segmentation`` is given) and classify every patch.

    Returns an empty description for an image with no returns.
    """
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    sigma0 = core_sigma(scan)
    if segmentation is None:
        segmentation = segment(scan.points, sigma0, params.segmentation)
    timing["segmentation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sigma = core_sigma(scan, segmentation.normals)
    flat_points = scan.points.reshape(-1, 3)
    flat_sigma = sigma.reshape(-1)
    flat_normals = segmentation.normals.reshape(-1, 3)
    patches = []
    for seg_patch in segmentation.patches:
        pix = np.ravel_multi_index((seg_patch.pixels[:, 0], seg_patch.pixels[:, 1]), scan.range.shape)
        pts, sig = flat_points[pix], flat_sigma[pix]
        planar = seg_patch.surface_type == SurfaceType.PLANAR
        if len(pix) < params.min_classify_pixels:
            cls = _too_small(len(pix))
        else:
            cls = classify_patch(pts, np.maximum(sig, 1e-6), flat_normals[pix], method=params.classifier,
                                 params=params.classifier_params, planar_hint=planar)
        patches.append(ScenePatch(seg_patch.id, pix, pts, sig, SurfaceType(seg_patch.surface_type), cls,
                                  seg_patch.small, seg_patch.noisy))
    timing["classification"] = time.perf_counter() - t0
    return SceneDescription(tuple(patches), segmentation.labels, segmentation, sigma, timing)


def _too_small(n: int) -> PatchClassification:
    probs = dict.fromkeys(("PLAN", "CYL", "SPH", "CONE", "OTH"), 0.0)
    probs["OTH"] = 1.0
    return PatchClassification("OTH", probs, {"CYL": 0.0, "SPH": 0.0, "CONE": 0.0}, None, {},
                               reason=f"too small to classify ({n} pixels)")
