"""Scene description (the paper's section 3): segmentation, then classification of every patch.

``describe(scan)`` is what the core makes of one range image before any matching: a set of labelled
patches (PLAN, CYL, SPH, CONE, OTH) with their dedicated fits, uncertainties and invariants, in the
sensor frame. It sees only the :class:`sensors.range_image.Scan` (range, points, sensor and noise
model); its per-pixel sigma comes from the noise model and its own normal estimates (DESIGN 10.1).

A patch is labelled with confidence only where its support is better than noise (:func:`local_scatter`): the
ranges of a surface the sensor saw agree with their neighbours' to within the sensor's noise, so the robust scale
of the patch's second differences of range (rows and columns) is about the noise model's sigma (0.7-1.2 of it on
the simulated suites' patches of 200 pixels or more). A patch whose neighbouring ranges scatter significantly more
than ``max_local_scatter`` times the sigma is not a surface this sensor measured (pure noise, or data of a noisier
sensor than the noise model says): it is OTH with a nearly flat probability (:data:`NOISE_PROBABILITIES`: no class
at 0.5 or more) and the reason "support not better than noise". The test cannot see a noise model that is wrong
by being far too large (``kinect_like``'s metres of sigma at 30 m): data as scattered as the model says are, to
the model, a surface; the readers keep such returns out (:mod:`sensors.readers`: the preset's working range).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from recognition.classification import (
    CLASSES,
    PaperParams,
    PatchClassification,
    SelectParams,
    classify_patch,
    merge_test,
)
from recognition.segmentation import Segmentation, SegmentationParams, SurfaceType, segment
from recognition.tuning import tuned
from sensors.config import MAX_PIXELS
from sensors.range_image import Scan

CLASSIFIERS = ("select", "paper")
BYTES_PER_PIXEL = 400  # peak working memory of describe() per pixel, measured at 1000^2 and 2000^2 (with margin)


@dataclass(frozen=True)
class DescribeParams:
    """Parameters of :func:`describe`.

    Attributes
    ----------
    classifier : ``select`` (the core's model-selection classifier) or ``paper`` (the paper's rule).
    segmentation : parameters of the H-K segmenter.
    classifier_params : ``SelectParams`` or ``PaperParams`` (None: the classifier's defaults).
    min_classify_pixels : patches smaller than this are labelled OTH without fitting (reason ``too small``).
    max_pixels : largest image (H x W) accepted. The segmentation's working memory grows with the pixel count
        (about ``BYTES_PER_PIXEL``; measured 1.5 GB peak for 2000 x 2000), so a larger image is refused with
        a clear error up front rather than exhausting the machine's memory part-way; raise it knowingly.
    merge_explained : with the ``select`` classifier, merge touching patches of one label that one dedicated
        primitive explains (:func:`recognition.classification.merge_test`): a pipe or wall the segmenter's quadric
        and plane fits left in pieces. The description's labels are then the merged ones (the segmentation's
        stay in :attr:`SceneDescription.segmentation`). On the ``calibration`` suite (seed 4242, never
        ``default``; DESIGN 10.8) it raised the pooled correct detection 0.730 -> 0.743 (factory scanner
        0.715 -> 0.740); 8-neighbour contact measured the same as within 2 pixels, and cones added nothing.
    merge_min_contacts : int
        Two patches touch (for ``merge_explained``) when at least this many pairs of their pixels are
        8-neighbours.
    max_local_scatter : float or None
        A patch whose neighbouring ranges scatter more than this many times the noise model's sigma
        (:func:`local_scatter`: robust scale of the second differences of range over their sigma) is OTH with a
        nearly flat probability, reason "support not better than noise", whatever the classifier says; None: no
        test. A surface gives about 1 (the smoke suite's and four calibration trials' patches of >= 200 pixels:
        0.7-1.2; slivers of 30-50 pixels up to 3.6); Gaussian noise of 50-300 mm about 2 m read as ``kinect_like``
        (6 mm there) 8-50.
        The scatter must exceed the limit by ``local_scatter_z`` standard errors of its estimate (a one-sided test,
        so that a small patch is not flagged by the spread of its own estimate: :func:`scatter_limit`).
    local_scatter_z : float
        Standard errors by which a patch's scatter must exceed ``max_local_scatter``.
    min_scatter_triples : int
        Second differences a patch needs for the test (fewer: no test; its classification stands).

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    classifier: str = tuned("select", unit="-", chosen="the core's classifier; paper is the baseline")
    segmentation: SegmentationParams = tuned(default_factory=SegmentationParams, unit="-",
                                             chosen="SegmentationParams' own defaults")
    classifier_params: SelectParams | PaperParams | None = tuned(
        None, unit="-", chosen="None: the chosen classifier's own defaults (SelectParams or PaperParams)")
    min_classify_pixels: int = tuned(30, unit="px", chosen="not tuned: set with the runner in c35aad5")
    max_pixels: int = tuned(MAX_PIXELS, unit="px", chosen="not tuned: the sensors' largest image, a memory bound "
                            "(1.5 GB peak measured at 2000 x 2000; 865ef63)")
    merge_explained: bool = tuned(
        True, unit="-", chosen="calibration (phase 1): pooled correct detection 0.730 -> 0.743 (97ec30f)")
    merge_min_contacts: int = tuned(
        3, unit="pixel pairs", chosen="calibration (phase 1), with merge_explained: 8-neighbour contact measured the "
        "same as within 2 pixels; the count itself not varied (97ec30f)")
    max_local_scatter: float | None = tuned(
        3.0, unit="sigma", chosen="not tuned: above the simulated suites' patches (0.7-1.2 at >= 200 pixels) and "
        "below pure noise (8 and more)")
    local_scatter_z: float = tuned(3.0, unit="standard errors", chosen="not tuned: a one-sided test at 3 standard "
                                   "errors (the simulated suites' patches of 30 pixels or more stay below 2)")
    min_scatter_triples: int = tuned(8, unit="second differences", chosen="not tuned: pure noise's fragments of 30 "
                                     "pixels have 8 or more (the simulated suites' patches of 30 pixels or more: 13 or "
                                     "more); fewer say little")

    def __post_init__(self):
        if not isinstance(self.classifier, str) or self.classifier not in CLASSIFIERS:
            raise ValueError(f"classifier must be one of {', '.join(CLASSIFIERS)}, got {self.classifier!r:.80}")
        if self.min_classify_pixels < 1:
            raise ValueError(f"min_classify_pixels must be >= 1, got {self.min_classify_pixels}")
        if self.max_pixels < 1:
            raise ValueError(f"max_pixels must be >= 1, got {self.max_pixels}")
        if self.merge_min_contacts < 1:
            raise ValueError(f"merge_min_contacts must be >= 1, got {self.merge_min_contacts}")
        if self.max_local_scatter is not None and not self.max_local_scatter > 0:
            raise ValueError(f"max_local_scatter must be > 0 or None, got {self.max_local_scatter}")
        if not self.local_scatter_z >= 0:
            raise ValueError(f"local_scatter_z must be >= 0, got {self.local_scatter_z}")
        if self.min_scatter_triples < 3:
            raise ValueError(f"min_scatter_triples must be >= 3, got {self.min_scatter_triples}")


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
    """Patches of one range image, their label image (the segmentation's, after ``merge_explained``) and the
    segmentation they came from."""

    patches: tuple[ScenePatch, ...]
    labels: np.ndarray
    segmentation: Segmentation
    sigma: np.ndarray
    timing_s: dict[str, float]

    def class_image(self) -> np.ndarray:
        """(H, W) int8 index into ``CLASSES`` of each pixel's patch label (-1 where none)."""
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

    Returns an empty description for an image with no returns (all NaN or inf, or too small to fit).

    Raises
    ------
    ValueError
        For a scan whose arrays disagree in shape, with negative ranges, or larger than ``params.max_pixels``.
    """
    check_scan(scan, params.max_pixels)
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
    offsets = _footprint_offsets(scan.noise) if params.classifier == "select" else None
    window = scan.noise.matching_window_px
    flat_range = scan.range.reshape(-1)
    scratch = np.zeros(flat_range.size, bool)
    # without range noise in the model (exact ranges) there is no sigma to compare the scatter with
    check_support = params.max_local_scatter is not None and bool(getattr(scan.noise, "has_range_noise", True))

    support = None if segmentation.support is None else segmentation.support.ravel()

    def classify(pix: np.ndarray, surface_type: SurfaceType, interior: np.ndarray | None) -> PatchClassification:
        if support is not None:  # not the pixels the border completion added (Segmentation.support)
            pix = pix[support[pix]]
        if len(pix) < params.min_classify_pixels:
            return _too_small(len(pix))
        if check_support:
            scatter, n = local_scatter(flat_range, flat_sigma, pix, scan.range.shape, scratch)
            if n >= params.min_scatter_triples and \
                    scatter > scatter_limit(params.max_local_scatter, n, params.local_scatter_z):
                return not_better_than_noise(scatter, n, params.max_local_scatter)
        # fitted on the pixels whose matching window stays on the patch, when enough of them remain
        use = slice(None)
        inner = None if interior is None else interior[pix]
        if inner is not None and inner.sum() >= max(params.min_classify_pixels, 0.25 * len(pix)):
            use = inner
        rows, cols = np.unravel_index(pix[use], scan.range.shape)
        return classify_patch(flat_points[pix[use]], np.maximum(flat_sigma[pix[use]], 1e-6),
                              flat_normals[pix[use]], method=params.classifier, params=params.classifier_params,
                              planar_hint=surface_type == SurfaceType.PLANAR,
                              correlation_area=scan.noise.correlation_area,
                              rays=None if offsets is None else functools.partial(
                                  patch_subrays, scan.sensor, offsets, rows, cols))

    interior = window_interior(segmentation.labels, window).ravel() if window > 1 else None
    patches = []
    for seg_patch in segmentation.patches:
        pix = np.ravel_multi_index((seg_patch.pixels[:, 0], seg_patch.pixels[:, 1]), scan.range.shape)
        stype = SurfaceType(seg_patch.surface_type)
        patches.append(ScenePatch(seg_patch.id, pix, flat_points[pix], flat_sigma[pix], stype,
                                  classify(pix, stype, interior), seg_patch.small, seg_patch.noisy))
    labels = segmentation.labels
    if params.merge_explained and params.classifier == "select":
        patches, labels = _merge_explained(patches, labels, params, scan.noise.correlation_area, classify,
                                           window)
    timing["classification"] = time.perf_counter() - t0
    return SceneDescription(tuple(patches), labels, segmentation, sigma, timing)


MERGE_LABELS = ("PLAN", "CYL", "SPH", "CONE")


def _touching_pairs(labels: np.ndarray, min_contacts: int) -> list[tuple[int, int]]:
    """Pairs ``(a, b)``, ``a < b``, of patches with at least ``min_contacts`` 8-neighbour pixel contacts."""
    H, W = labels.shape
    n = int(labels.max()) + 1
    codes = []
    for dr, dc in ((0, 1), (1, -1), (1, 0), (1, 1)):
        a = labels[: H - dr, max(0, -dc): W - max(0, dc)]
        b = labels[dr:, max(0, dc): W - max(0, -dc)]
        m = (a >= 0) & (b >= 0) & (a != b)
        lo, hi = np.minimum(a[m], b[m]).astype(np.int64), np.maximum(a[m], b[m]).astype(np.int64)
        codes.append(lo * n + hi)
    u, c = np.unique(np.concatenate(codes), return_counts=True)
    return [(int(x // n), int(x % n)) for x in u[c >= min_contacts]]


def _merge_explained(patches: list, labels: np.ndarray, params: DescribeParams, correlation_area: float, classify,
                     window: int) -> tuple[list, np.ndarray]:
    """Merge touching patches of one primitive label that one dedicated primitive explains, best first (the most
    negative criterion gain), until no pair passes :func:`recognition.classification.merge_test`; the merged patches
    are classified again. Returns the patches (in the original order, merged ones in place of their first part)
    and the label image."""
    sp = params.classifier_params if isinstance(params.classifier_params, SelectParams) else SelectParams()
    by_id = {p.id: p for p in patches}
    fits = {p.id: p.classification.primitive for p in patches
            if p.label in MERGE_LABELS and p.classification.primitive is not None}
    labels = labels.copy()
    merged: set[int] = set()
    tested: dict[tuple[int, int], tuple | None] = {}
    while True:
        best = None
        for a, b in _touching_pairs(labels, params.merge_min_contacts):
            pa, pb = by_id[a], by_id[b]
            if pa.label != pb.label or a not in fits or b not in fits:
                continue
            if (a, b) not in tested:
                big, small = (pa, pb) if pa.n_pixels >= pb.n_pixels else (pb, pa)
                tested[(a, b)] = merge_test(fits[big.id], big.points, np.maximum(big.sigma, 1e-6), fits[small.id],
                                            small.points, np.maximum(small.sigma, 1e-6), sp, correlation_area)
            got = tested[(a, b)]
            if got is not None and (best is None or got[1] < best[0]):
                best = (got[1], a, b, got[0])
        if best is None:
            break
        _, a, b, union = best
        pa, pb = by_id[a], by_id.pop(b)
        labels[labels == b] = a
        pix = np.concatenate([pa.pixels, pb.pixels])
        big = pa if pa.n_pixels >= pb.n_pixels else pb
        by_id[a] = ScenePatch(a, pix, np.concatenate([pa.points, pb.points]), np.concatenate([pa.sigma, pb.sigma]),
                              big.surface_type, pa.classification,
                              len(pix) < params.segmentation.min_patch_pixels, big.noisy)
        fits[a] = union
        fits.pop(b, None)
        merged.add(a)
        merged.discard(b)
        tested = {k: v for k, v in tested.items() if a not in k and b not in k}
    if not merged:
        return patches, labels
    interior = window_interior(labels, window).ravel() if window > 1 else None
    out = []
    for p in patches:
        q = by_id.get(p.id)
        if q is None:
            continue  # merged into another patch
        if p.id in merged:
            order = np.argsort(q.pixels, kind="stable")  # raster order, as the segmentation's patches
            q = ScenePatch(q.id, q.pixels[order], q.points[order], q.sigma[order], q.surface_type,
                           classify(q.pixels[order], q.surface_type, interior), q.small, q.noisy)
        out.append(q)
    return out, labels


#: Class probabilities of a patch whose support is not better than noise: nearly flat, OTH the label, every
#: primitive below 0.2 (change detection lets a patch show a feature of a class it gives 0.2 or more).
NOISE_PROBABILITIES = {"PLAN": 0.15, "CYL": 0.15, "SPH": 0.15, "CONE": 0.15, "OTH": 0.4}


def scatter_limit(limit: float, n: int, z: float) -> float:
    """The scatter above which ``n`` second differences show more scatter than ``limit`` by ``z`` standard errors:
    ``limit (1 + z 1.166 / sqrt(n))`` (for ``limit`` = ``z`` = 3: 7.4 for 8, 4.6 for 20, 3.1 for 10,000). 1.166 /
    sqrt(n) is the relative standard error of the median-based scale of n Gaussian values (the asymptotic variance
    of a median, ``1 / (4 n g²)`` with ``g`` the density of ``|z|`` at its median 0.6745, over 0.6745²)."""
    return limit * (1.0 + z * 1.166 / np.sqrt(max(n, 1)))


def local_scatter(flat_range: np.ndarray, flat_sigma: np.ndarray, pix: np.ndarray, shape: tuple[int, int],
                  scratch: np.ndarray | None = None) -> tuple[float, int]:
    """How much a patch's neighbouring ranges scatter, in units of the noise model's sigma.

    Over every three consecutive pixels of the patch along a row or a column, the second difference of range
    ``d = r[-1] - 2 r[0] + r[+1]`` over its noise sigma ``sqrt(s[-1]² + 4 s[0]² + s[+1]²)``; returns the robust
    scale (1.4826 median absolute value) of these and their number. A surface seen by the sensor the noise model
    describes gives about 1 (its geometry adds little over three pixels, correlated errors give less);
    independent random ranges give about the spread of the patch's ranges over the sigma. ``(NaN, n)`` for
    fewer than 3 finite second differences.

    Parameters
    ----------
    flat_range, flat_sigma : ndarray of shape (H * W,), metres (the scan's range and the core's sigma).
    pix : flat indices of the patch's pixels.
    shape : (H, W).
    scratch : optional all-False bool array of shape (H * W,), reused (and left all False).
    """
    H, W = shape
    pix = np.asarray(pix, dtype=np.intp)
    if len(pix) < 3:
        return float("nan"), 0
    inside = np.zeros(H * W, bool) if scratch is None else scratch
    inside[pix] = True
    try:
        rows, cols = np.divmod(pix, W)
        parts = []
        for ok, step in (((cols > 0) & (cols < W - 1), 1), ((rows > 0) & (rows < H - 1), W)):
            c = pix[ok]
            c = c[inside[c - step] & inside[c + step]]
            r0, s0 = flat_range[c], flat_sigma[c]
            rm, sm, rp, sp = flat_range[c - step], flat_sigma[c - step], flat_range[c + step], flat_sigma[c + step]
            with np.errstate(invalid="ignore", divide="ignore"):
                parts.append((rm - 2.0 * r0 + rp) / np.sqrt(sm * sm + 4.0 * s0 * s0 + sp * sp))
    finally:
        inside[pix] = False
    z = np.concatenate(parts)
    z = z[np.isfinite(z)]
    if len(z) < 3:
        return float("nan"), len(z)
    return float(1.4826 * np.median(np.abs(z))), len(z)


def not_better_than_noise(scatter: float, n: int, limit: float) -> PatchClassification:
    """The classification of a patch whose support is not better than noise (its :func:`local_scatter` over ``n``
    second differences beyond :func:`scatter_limit`): OTH with :data:`NOISE_PROBABILITIES`, no fit."""
    probs = {c: NOISE_PROBABILITIES[c] for c in CLASSES}
    return PatchClassification("OTH", probs, {"CYL": 0.0, "SPH": 0.0, "CONE": 0.0}, None, {},
                               reason=f"support not better than noise: neighbouring ranges scatter {scatter:.3g} x "
                                      f"the sensor model's sigma (a surface: about 1; limit {limit:g})",
                               details={"local_scatter": scatter, "n_second_differences": n})


def window_interior(labels: np.ndarray, window: int) -> np.ndarray:
    """(H, W) bool: pixels whose ``window x window`` neighbourhood lies in their own patch (``labels``, -1 for
    none). A stereo matcher's window that straddles another surface blends the two (the foreground's depth
    spreads over the background by about half a window), so those pixels are left out of the fits of
    sensors with a matching window (:attr:`sensors.noise.NoiseModel.matching_window_px`); all labelled
    pixels for ``window`` 1."""
    if window <= 1:
        return labels >= 0
    lo = ndi.minimum_filter(labels, size=window, mode="constant", cval=-1)
    hi = ndi.maximum_filter(labels, size=window, mode="constant", cval=-1)
    return (labels >= 0) & (lo == hi)


def check_scan(scan: Scan, max_pixels: int = MAX_PIXELS) -> None:
    """Raise ``ValueError`` for a scan the core cannot use: ``range`` not (H, W) matching the sensor model,
    ``points`` not (H, W, 3), a negative range (no return is NaN, never a sign), or more than ``max_pixels``
    pixels (see :attr:`DescribeParams.max_pixels`). Non-finite values are allowed: they mean no return."""
    rng, pts = np.asanyarray(scan.range), np.asanyarray(scan.points)
    if rng.ndim != 2 or rng.shape[0] < 1 or rng.shape[1] < 1:
        raise ValueError(f"scan.range must have shape (H, W), got {rng.shape}")
    if pts.shape != (*rng.shape, 3):
        raise ValueError(f"scan.points must have shape {(*rng.shape, 3)} (H, W, 3), got {pts.shape}")
    if tuple(scan.sensor.shape) != rng.shape:
        raise ValueError(f"scan.range has shape {rng.shape} but the sensor model's image is {scan.sensor.shape}")
    if rng.size > max_pixels:
        h, w = rng.shape
        raise ValueError(f"range image {h} x {w} ({rng.size / 1e6:.1f} M pixels) is larger than max_pixels = "
                         f"{max_pixels} (about {rng.size * BYTES_PER_PIXEL / 1e9:.1f} GB of working memory would be "
                         "needed): decimate the scan (every k-th row and column, intrinsics scaled by 1/k) or pass "
                         "DescribeParams(max_pixels=...) if the machine has the memory")
    negative = int(np.count_nonzero(np.isfinite(rng) & (np.nan_to_num(rng, nan=0.0) < 0)))
    if negative:
        raise ValueError(f"scan.range has {negative} negative value(s): ranges are >= 0 metres, NaN where no return")


def _footprint_offsets(noise) -> tuple[tuple[float, float], ...] | None:
    """The noise model's beam-footprint sub-ray offsets in pixels (centre first), or None without one."""
    try:
        return tuple((float(u), float(v)) for u, v in np.asarray(noise.footprint_offsets()).reshape(-1, 2))
    except (AttributeError, TypeError, ValueError):
        return None


def patch_subrays(sensor, offsets, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Unit sub-ray directions (k, N, 3) of the pixels ``(rows, cols)`` for the footprint ``offsets`` (k, 2)
    in pixels: sensor knowledge (its model and noise model), not truth (DESIGN 10.1). Equal to
    ``sensor.ray_directions(offset)[rows, cols]`` (a test checks it) without building whole images: only the
    patches that end up cylinders or spheres need them."""
    out = np.empty((len(offsets), len(rows), 3))
    for k, off in enumerate(offsets):
        if hasattr(sensor, "angles"):  # scanning laser: azimuth x elevation grid
            az, el = sensor.angles(off)
            a, e = az[cols], el[rows]
            ce = np.cos(e)
            out[k, :, 0] = ce * np.sin(a)
            out[k, :, 1] = -np.sin(e)
            out[k, :, 2] = ce * np.cos(a)
        elif all(hasattr(sensor, n) for n in ("fx", "fy", "cx", "cy")):  # pinhole
            out[k, :, 0] = (cols + off[0] - sensor.cx) / sensor.fx
            out[k, :, 1] = (rows + off[1] - sensor.cy) / sensor.fy
            out[k, :, 2] = 1.0
            out[k] /= np.linalg.norm(out[k], axis=1, keepdims=True)
        else:
            out[k] = sensor.ray_directions(off)[rows, cols]
    return out


def _too_small(n: int) -> PatchClassification:
    probs = dict.fromkeys(CLASSES, 0.0)
    probs["OTH"] = 1.0
    return PatchClassification("OTH", probs, {"CYL": 0.0, "SPH": 0.0, "CONE": 0.0}, None, {},
                               reason=f"too small to classify ({n} pixels)")
