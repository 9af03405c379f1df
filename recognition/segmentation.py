"""H-K segmentation of organised range images into surface patches (section 3 of Fillatreau & Fisher).

The paper follows Besl & Jain ("Segmentation through variable-order surface fitting", IEEE PAMI 10(2),
1988, doi:10.1109/34.3881): a patch is a maximal connected set of pixels whose mean (H) and Gaussian (K)
curvature signs do not change; patches are grown and merged by surface fitting, and a plane or a quadric is
fitted to each. The steps here:

1. **Derivatives** of the parametric surface ``P(u, v)`` (the point image; ``u`` column, ``v`` row) by local
   quadratic fits whose windows exclude neighbours across depth jumps (:mod:`recognition.derivatives`:
   separable Savitzky-Golay kernels where the whole window is on one surface, batched masked 6x6 solves
   elsewhere).
2. **Curvatures** from the fundamental forms, valid for perspective images: ``E = Pu.Pu, F = Pu.Pv,
   G = Pv.Pv``, ``n = Pu x Pv / |Pu x Pv|`` oriented to **face the sensor** (``n . P < 0``),
   ``L = Puu.n, M = Puv.n, N = Pvv.n``, ``K = (LN - M²) / (EG - F²)``,
   ``H = (EN - 2FM + GL) / (2 (EG - F²))``. With this normal a surface bulging towards the sensor (the
   outside of a sphere or pipe) has ``H < 0``: a sphere of radius r gives ``H = -1/r, K = 1/r²``, a
   cylinder ``H = -1/(2r), K = 0``.
3. **Zero thresholds from the noise.** The derivative estimates are linear in the data; range noise of
   sigma along the ray moves ``L, M, N`` by ``(ray . n) sum_k c_k dr_k``, so their covariance is
   ``sigma² (ray . n)²`` times the filter's unit-noise covariance. ``sigma_H`` is its first-order
   propagation; ``sigma_K`` adds the second-order term ``(var_L var_N + 2 var_M²) / (EG - F²)²`` (on a plane
   the first-order term of K vanishes). ``H = 0`` when ``|H| <= k sigma_H``, the same for K.
4. **Classes**: planar (H=0, K=0), cylindrical (K=0, H!=0; cones too: they are developable), elliptic
   (K>0), hyperbolic (K<0, whatever H). K>0 with H=0 is impossible (K <= H²): treated as planar noise.
   **Edges**: jump pairs (range difference beyond :func:`recognition.derivatives.jump_threshold`) and crease
   pairs (normals of neighbours further apart than ``crease_k`` times their propagated angular sigma and
   ``crease_min_angle``).
5. **Patches**: seeds are the connected components of one class, edge pixels removed, that survive a
   morphological erosion of ``seed_erosion`` pixels (thin bands of transitional curvature along creases
   vanish) with at least ``min_seed_pixels`` left. Each seed gets a plane (planar seeds) or a quadric; seeds
   grow into adjacent unlabelled pixels (never across a jump) whose range residual to the patch's surface is
   within ``grow_k`` sigma, with refits between rounds. Leftover connected pixels with defined curvature
   become patches of their own (isolated pieces under ``min_leftover_pixels`` stay unlabelled).
   Adjacent patches are merged greedily, best first, while the fit of their
   union (plane for two planar patches, quadric otherwise) has an RMS range residual within ``merge_k``
   sigma; small fragments lying wholly inside one other patch are merged into it (the Hoover metric counts
   them as over-segmentation otherwise), and small pieces cut off by jumps (grazing limbs) join the patch
   across the jump whose surface fits them. Small and noisy patches are kept and flagged, never dropped.

What the simulated suites (mixed pixels, outliers, grazing dropouts, incidence-dependent noise) added:

6. **Noise self-calibration** (:func:`noise_scale`): the sigma a sensor model gives is a floor; the
   residual of the local quadratic fit of the range, per block of the image, measures the real noise
   (1.2-1.9x the model's on the simulated presets, far more on walls at grazing incidence), and every
   threshold uses the scaled sigma. Patch fits and the ``noisy`` flag stay in units of the declared sigma.
7. **Coarse grid** (``decimation``; automatic: 2 for images of >= 400 rows, VGA-class). Curvature, seeds, growing and
   merging run on every second pixel: four times less work, and four times less curvature noise for the
   same window (a 7-pixel window on a dense mock-up scan cannot tell a pipe from a plane). Labels are then
   brought back to full resolution: patches are refitted on their coarse samples (trimmed), pixels near a
   label change, hole or jump that are off their patch's surface are released and regrown.
8. **Growing restarts from the seeds after every (trimmed) refit**, so pixels admitted by a seed's
   extrapolated surface are not kept. On decimated grids (``split_seeds``) seeds that one surface does not
   fit (a class component spanning two faces across a blurred crease, a pipe and its tangent elbow) are cut
   into tiles that merging reassembles; so are unseeded leftover pieces (a thin pipe run). The quick fits
   behind these tests are Taubin fits: the plain algebraic quadric fit is biased on small arcs.
   Two patches that each fit a plane merge only as one plane, never as the plane pair a quadric fits.
   After the full-resolution refinement, adjacent patches are merged once more at full resolution (pieces of
   one pipe the coarse grid kept apart now touch); then a patch that no plane fits but a plane pair does (two
   faces of a far, small box reassembled from noisy tiles) is cut along its crease
   (:func:`_split_plane_pairs`), one that no quadric fits either into the faces k-planes finds
   (:func:`_faces`), and a large curved patch along its axis where its radius profile bends (a pipe
   merged with its reducer under strong noise, :func:`_split_along_axis`).
9. **Border reassignment** (:func:`_reassign`, decimated grids): a border pixel moves to the neighbouring patch whose
   surface fits it clearly better, a few rounds with refits (tiles straddling a pipe and its reducer give
   up the pixels of the other surface). Default suite: correct detection 0.705 -> 0.724, ``select``
   accuracy 0.895 -> 0.913, for about 0.05 s per VGA frame.
10. **Hoover-literal hygiene**: fragments under ``min_region_pixels`` join a bordering patch whose surface
   fits them; pixels with at most two 4-neighbours in their own patch are left unlabelled (mixed pixels
   and one-pixel slivers of other surfaces at corners: the metric counts a patch that wholly covers a
   one-pixel truth region as an under-segmentation).

The segmenter reads only the point image and the per-pixel sigma; never any ground truth.
"""

from __future__ import annotations

import heapq
import time
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np
import scipy.ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from recognition.derivatives import clean_windows, jump_pairs, norm3, quadratic_derivatives, ray_angles, savgol_kernels
from recognition.primitives import fit_cylinder
from recognition.quadric import MONOMIAL_GRADIENT, quadric_matrices, taubin_fit
from recognition.surface_fit import (
    _MIN_GRAZING,
    PlaneFit,
    QuadricSurfaceFit,
    fit_plane,
    fit_quadric_lsq,
    normalisation_transform,
    plane_params,
    quadric_gradient,
    quadric_monomials,
    ray_residuals,
)
from scenes.geometry import perpendicular_basis

__all__ = [
    "SurfaceType",
    "EdgeType",
    "SegmentationParams",
    "Patch",
    "Segmentation",
    "CurvatureImages",
    "segment",
    "curvature_images",
    "classify_hk",
]


class SurfaceType(IntEnum):
    """H-K surface class of a pixel or patch."""

    NONE = 0
    PLANAR = 1
    CYLINDRICAL = 2
    ELLIPTIC = 3
    HYPERBOLIC = 4


class EdgeType(IntEnum):
    """Bits of :attr:`Segmentation.edges`."""

    JUMP = 1
    CREASE = 2


@dataclass(frozen=True)
class SegmentationParams:
    """Parameters of :func:`segment` (all thresholds in units of the propagated noise unless stated).

    Attributes
    ----------
    window : int
        Odd size of the square window of the local quadratic fits (>= 3). Larger: smoother curvature,
        wider transition bands at creases.
    zero_k : float
        ``H = 0`` when ``|H| <= zero_k * sigma_H`` (same for K).
    jump_k : float
        Range-noise allowance of the jump test, in sigma.
    jump_tan : float
        ``tan`` of the steepest incidence still considered one continuous surface: neighbours may differ in
        range by ``jump_tan * range * ray angle`` beyond the noise allowance (5.0 ~ 79 deg).
    crease_k : float
        Crease when the angle between neighbouring normals exceeds ``crease_k`` times its propagated sigma...
    crease_min_angle : float, radians
        ...and this angle (also the floor of the wide-baseline test).
    crease_baseline : int or None
        Half baseline ``k`` (pixels of the segmentation grid) of the wide-baseline crease test
        (:func:`_wide_creases`) and of the crease split of badly fitted seeds (:func:`_split_at_creases`);
        None: ``window``; 0 (default) disables both. The windowed normal fits spread a crease over about
        ``window`` pixels, so on noisy (real) data no pair of neighbours crosses the neighbour test. Measured
        with None on /tmp/segw's 10 scans per group: Kinect-like 0.21 -> 0.43, mock-up 0.76 (same), factory
        scanner 0.63 -> 0.60; on the real scans it separates the box faces, the mug from the table and the
        tunnel floor from its wall, but the classifier then labels the box faces CYL (their plane residual is
        ~1.6x the declared sigma), so it stays off until the classifier's noise handles real data.
    crease_wide_k : float
        Its threshold in robust scales (MAD) of the statistic over the image (real noise is spatially
        correlated: the propagated sigma of independent pixels under-states it).
    crease_wide_min_angle : float, radians
        Floor of that threshold.
    sigma_floor_m : float, metres
        Floor applied to the input sigma (quantisation level; keeps noise-free images usable).
    seed_erosion : int or None
        Erosion (pixels) that a class component must survive to seed a patch (None: ``window // 2``).
    min_seed_pixels : int
        Fewest pixels left after erosion for a seed.
    grow_k : float
        A pixel joins an adjacent patch when its range residual to the patch's surface is within
        ``grow_k`` sigma.
    grow_rounds : int
        Grow / refit rounds (>= 1).
    max_grow_iterations : int
        One-pixel growth steps per round at most.
    merge_k : float
        Adjacent patches merge when the RMS range residual of their union's fit is within ``merge_k`` sigma.
    min_patch_pixels : int
        Patches below this size are flagged ``small``; small fragments enclosed by one patch are merged, and
        the pixels of fragments go to the linked patch whose surface fits them (:func:`_reassign`).
    noisy_k : float
        Patches whose fit RMS range residual exceeds ``noisy_k`` sigma are flagged ``noisy``.
    min_leftover_pixels : int
        Leftover pieces (pixels that fit no neighbouring patch, linked without jumps) with fewer pixels
        stay unlabelled: isolated returns (flying pixels, grazing limb samples) are not patches. Larger
        pieces become patches of their own, flagged ``small`` / ``noisy`` as they deserve.
    max_fit_points : int
        Points used per fit while growing (a deterministic stride subsample).
    merge_fit_points : int
        Points per patch in the fits that test a merge.
    max_tiled_leftover : int
        Leftover pieces (no seed: thin pipes, every window of which crosses a jump) below this size (pixels
        of the segmentation grid) that one surface does not fit are cut into tiles like bad seeds. A whole
        pipe run (pipe, reducer, pipe, elbow) is otherwise one patch: correct detection with the factory
        scanner 0.59 -> 0.66 on the default suite.
    class_min_pixels : int
        Classified pixels a patch needs for its dominant class to veto a merge across a cylindrical /
        doubly-curved class boundary (pixels of the segmentation grid); 0 (default) disables the veto: on
        the simulated suites tangent joins were lost before merging (one seed or leftover piece spanning
        both surfaces), and the veto cost two regions elsewhere.
    connectivity : int
        4 or 8: pixel connectivity of class components.
    decimation : int or None
        Grid step of curvature, seeding, growing and merging (labels are refined at full resolution);
        None: 2 for images of at least 400 rows, else 1 (:meth:`step`).
    final_fit_points : int
        Points (deterministic stride subsample) of the final plane / quadric fit of each patch.
    split_seeds : bool or None
        Cut seeds that one surface does not fit into tiles (:func:`_split_bad_seeds`); merging reassembles
        the tiles that share a surface. None (default): on for decimated grids (VGA-class images). There it
        recovers pipe runs and faces that one class component spans (a tangent elbow, a blurred crease:
        correct detection on the default suite 0.81 -> 0.92 mock-up, 0.57 -> 0.59 factory scanner, 0.18 ->
        0.23 Kinect-like). Off on full-resolution grids: on the real pyRANSAC-3D box scans (structured light,
        245 x 276) the faces are warped by more than the noise, so their tiles are never reassembled and come
        out labelled CYL / CONE (DESIGN 10.12 wants PLAN there).
    seed_tile : int
        Side (pixels of the segmentation grid) of the tiles that a seed badly fitted by one surface is cut into.
    split_k : float
        A seed is badly fitted when the RMS range residual of its trimmed fit exceeds ``split_k`` sigma.
    min_region_pixels : int
        Fragments below this size join a bordering patch whose surface fits them (RMS range residual within
        ``absorb_k`` sigma).
    absorb_k : float
    calibrate_noise : bool
        Scale the input sigma by the noise measured in the image (:func:`noise_scale`), never below 1: sensor
        models tend to under-state the noise (incidence, quantisation, mixed returns). Thresholds use the
        scaled sigma; patch fits and the ``noisy`` flag stay in units of the declared one.
    max_noise_scale : float
        Upper bound of that scale.
    curved_planar_merge : bool
        Two planar-class patches whose union no plane fits may merge as a quadric (not a plane pair): a large
        pipe close to a noisy sensor is curved within the curvature noise, and its tiles were left apart.
        Kinect-like correct detection on the default suite 0.38 -> 0.42 and `select` accuracy 0.63 -> 0.71,
        for more merge fits.
    axis_split_pixels : int or None
        Curved patches of at least this many pixels are cut along their axis where the radius changes (a pipe
        merged with its reducer or elbow, see :func:`_split_along_axis`); None: never. 400 (was 1500), with
        slices of ``_SLICE_POINTS`` points on far pipes, on the ``calibration`` suite: pooled correct
        detection 0.730 -> 0.739 (factory scanner 0.715 -> 0.732), accuracy 0.929 -> 0.930; on the same suite
        with perturbation seeds 10-14 (60 frames), accuracy 0.948 -> 0.951, factory-scanner correct detection
        0.763 -> 0.774 (mean over frames).
    reassign_rounds : int
        Rounds of border reassignment (:func:`_reassign`) before the final hygiene, on decimated grids (whose
        blocks and tiles leave such borders); 0: none. Full-resolution grids have neither: on the real box
        scans (245 x 276) it turned two warped OTH faces into CONE.
    reassign_margin : float
        A border pixel moves to a neighbouring patch only when its range residual to that patch's surface is
        smaller, by this many sigma, than to its own (and within ``2 grow_k``).
    """

    window: int = 7
    zero_k: float = 3.0
    jump_k: float = 4.0
    jump_tan: float = 5.0
    crease_k: float = 4.0
    crease_min_angle: float = float(np.deg2rad(12.0))
    crease_baseline: int | None = 0
    crease_wide_k: float = 3.0
    crease_wide_min_angle: float = float(np.deg2rad(30.0))
    sigma_floor_m: float = 1e-5
    seed_erosion: int | None = None
    min_seed_pixels: int = 8
    grow_k: float = 3.0
    grow_rounds: int = 2
    max_grow_iterations: int = 100
    merge_k: float = 2.0
    min_patch_pixels: int = 50
    noisy_k: float = 3.0
    min_leftover_pixels: int = 3
    max_fit_points: int = 1500
    merge_fit_points: int = 400
    class_min_pixels: int = 0
    max_tiled_leftover: int = 1_000_000
    connectivity: int = 4
    calibrate_noise: bool = True
    min_region_pixels: int = 200
    decimation: int | None = None
    split_seeds: bool | None = None
    seed_tile: int = 12
    split_k: float = 4.0
    final_fit_points: int = 5000
    absorb_k: float = 4.0
    max_noise_scale: float = 10.0
    curved_planar_merge: bool = True
    axis_split_pixels: int | None = 400
    reassign_rounds: int = 16
    reassign_margin: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.window, int | np.integer) or self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"window must be an odd integer >= 3, got {self.window!r}")
        if self.crease_baseline is not None and self.crease_baseline < 0:
            raise ValueError(f"crease_baseline must be >= 0 or None, got {self.crease_baseline!r}")
        for name in ("zero_k", "jump_k", "crease_k", "crease_wide_k", "grow_k", "merge_k", "noisy_k", "split_k"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not np.isfinite(self.jump_tan) or self.jump_tan < 0:
            raise ValueError(f"jump_tan must be >= 0, got {self.jump_tan!r}")
        if not 0 <= self.crease_min_angle <= np.pi:
            raise ValueError(f"crease_min_angle must be in [0, pi] radians, got {self.crease_min_angle!r}")
        if not self.sigma_floor_m > 0:
            raise ValueError(f"sigma_floor_m must be > 0, got {self.sigma_floor_m!r}")
        if self.seed_erosion is not None and self.seed_erosion < 0:
            raise ValueError(f"seed_erosion must be >= 0 or None, got {self.seed_erosion!r}")
        for name in ("min_seed_pixels", "grow_rounds", "max_grow_iterations", "min_patch_pixels",
                     "min_leftover_pixels", "min_region_pixels", "seed_tile", "final_fit_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("max_fit_points", "merge_fit_points"):
            if getattr(self, name) < 10:
                raise ValueError(f"{name} must be >= 10, got {getattr(self, name)!r}")
        if self.decimation is not None and self.decimation < 1:
            raise ValueError(f"decimation must be >= 1 or None, got {self.decimation!r}")
        if not (np.isfinite(self.absorb_k) and self.absorb_k > 0):
            raise ValueError(f"absorb_k must be a positive finite number, got {self.absorb_k!r}")
        if self.reassign_rounds < 0:
            raise ValueError(f"reassign_rounds must be >= 0, got {self.reassign_rounds!r}")
        if not (np.isfinite(self.reassign_margin) and self.reassign_margin >= 0):
            raise ValueError(f"reassign_margin must be a finite number >= 0, got {self.reassign_margin!r}")
        if not (np.isfinite(self.max_noise_scale) and self.max_noise_scale >= 1):
            raise ValueError(f"max_noise_scale must be >= 1, got {self.max_noise_scale!r}")
        if self.connectivity not in (4, 8):
            raise ValueError(f"connectivity must be 4 or 8, got {self.connectivity!r}")

    def step(self, shape: tuple[int, int]) -> int:
        """Grid step of the segmentation proper (``decimation``, or 2 for images of at least 400 rows)."""
        if self.decimation is not None:
            return int(self.decimation)
        return 2 if min(shape) >= 400 else 1

    def scaled(self, d: int) -> SegmentationParams:
        """Parameters for a grid subsampled by ``d``: pixel counts divided by ``d²``."""
        if d == 1:
            return self
        a = d * d
        return replace(self, min_seed_pixels=max(2, self.min_seed_pixels // a),
                       class_min_pixels=max(4, self.class_min_pixels // a) if self.class_min_pixels else 0,
                       min_patch_pixels=max(2, self.min_patch_pixels // a),
                       min_region_pixels=max(2, self.min_region_pixels // a),
                       min_leftover_pixels=max(2, self.min_leftover_pixels // a), decimation=1)

    @property
    def baseline(self) -> int:
        """Effective half baseline of the wide-baseline crease test (0: off)."""
        return self.window if self.crease_baseline is None else int(self.crease_baseline)

    @property
    def erosion(self) -> int:
        """Effective seed erosion in pixels."""
        return self.window // 2 if self.seed_erosion is None else self.seed_erosion


@dataclass(frozen=True)
class Patch:
    """One segmented surface patch.

    Attributes
    ----------
    id : int
        Its value in :attr:`Segmentation.labels`.
    pixels : ndarray of shape (N, 2), int
        (row, column) of its pixels, raster order.
    n_pixels : int
    surface_type : SurfaceType
        Dominant H-K class of its pixels (after growing and merging).
    fit : PlaneFit or QuadricSurfaceFit
        Plane ``n . x = d`` (n facing the sensor) for planar patches, a general quadric otherwise; with
        covariance and RMS residuals (``rms_sigma``: along the ray, in sigma units). A failed fit is falsy.
    small : bool
        Fewer than ``min_patch_pixels`` pixels.
    noisy : bool
        Fit RMS range residual above ``noisy_k`` sigma (or the fit failed).
    class_counts : tuple of int
        Pixels of each class (NONE, PLANAR, CYLINDRICAL, ELLIPTIC, HYPERBOLIC).
    """

    id: int
    pixels: np.ndarray
    n_pixels: int
    surface_type: SurfaceType
    fit: PlaneFit | QuadricSurfaceFit
    small: bool
    noisy: bool
    class_counts: tuple[int, ...] = field(default=(0, 0, 0, 0, 0))


@dataclass(frozen=True)
class Segmentation:
    """Result of :func:`segment`.

    Attributes
    ----------
    labels : ndarray of shape (H, W), int32
        Patch id per pixel, -1 for none.
    hk_class : ndarray of shape (H, W), int8
        :class:`SurfaceType` per pixel (0 where curvature is undefined).
    H, K : ndarray of shape (H, W), float64
        Mean curvature (1/m, normal facing the sensor) and Gaussian curvature (1/m²); NaN where undefined.
    sigma_H, sigma_K : ndarray of shape (H, W), float64
        Their propagated noise sigmas.
    normals : ndarray of shape (H, W, 3)
        Unit surface normals from the local fits, facing the sensor (NaN where undefined).
    edges : ndarray of shape (H, W), uint8
        Bitmask of :class:`EdgeType` (1 jump, 2 crease).
    patches : tuple of Patch
        Ordered by decreasing size; ``patches[i].id == i``.
    noise_scale : ndarray of shape (H, W) or None
        The measured-to-declared range noise ratio (:func:`noise_scale`, >= 1) the thresholds used; None
        when not measured (``calibrate_noise`` off, or no returns).
    """

    labels: np.ndarray
    hk_class: np.ndarray
    H: np.ndarray
    K: np.ndarray
    sigma_H: np.ndarray
    sigma_K: np.ndarray
    normals: np.ndarray
    edges: np.ndarray
    patches: tuple[Patch, ...]
    noise_scale: np.ndarray | None = None

    @property
    def n_patches(self) -> int:
        """Number of patches."""
        return len(self.patches)


@dataclass(frozen=True)
class CurvatureImages:
    """Per-pixel curvature and its propagated noise (see :func:`curvature_images`)."""

    H: np.ndarray
    K: np.ndarray
    sigma_H: np.ndarray
    sigma_K: np.ndarray
    normals: np.ndarray
    sigma_normal: np.ndarray


# --------------------------------------------------------------------------------------------- validation


def _check_inputs(points: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asanyarray(points, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] < 1 or p.shape[1] < 1:
        raise ValueError(f"expected points of shape (H, W, 3), got {p.shape}")
    s = np.asanyarray(sigma, dtype=np.float64)
    if s.shape != p.shape[:2]:
        raise ValueError(f"expected sigma of shape {p.shape[:2]} (H, W), got {s.shape}")
    if np.any(s < 0):
        raise ValueError("sigma must be >= 0 (NaN where no return)")
    return p, s


# --------------------------------------------------------------------------------------------- noise


def noise_scale(rng: np.ndarray, sigma: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                window: int, max_scale: float = 10.0, block: int = 8) -> np.ndarray:
    """Ratio of the range noise measured in the image to the declared sigma, per pixel, clipped to
    ``[1, max_scale]`` (an (H, W) array).

    The range image is fitted by the same local quadratic as the derivatives (a Savitzky-Golay
    value-at-centre kernel ``k``) on windows free of holes and jumps, centred on every third pixel; the
    centre's residual then has variance ``sigma² (1 - k_00)`` (``k_00`` the centre weight: the fit's
    leverage), so the robust (median-based) scale of ``(r - fit) / (sigma sqrt(1 - k_00))`` estimates the
    ratio. It is taken per block of ``block x block`` samples (``3 block`` pixels; the noise of a sensor grows
    with incidence, so one wall at grazing incidence is much noisier than the rest), blocks with fewer than
    16 samples take the image-wide median, and the block values are smoothed (3x3 block median) and spread
    to their pixels. Windows across creases inflate a few residuals; the medians ignore them. All ones when
    fewer than 100 windows qualify.
    """
    H, W = rng.shape
    ones = np.ones((H, W))
    if H < window or W < window:
        return ones
    k = savgol_kernels(window)
    h = window // 2
    c = float(np.mean(np.arange(-h, h + 1.0) ** 2))
    # value at the centre of the 2D total-degree-2 fit: box (x) box - c (d2 (x) box + box (x) d2)
    K2 = np.outer(k["box"], k["box"]) - c * (np.outer(k["d2"], k["box"]) + np.outer(k["box"], k["d2"]))
    lev = float(K2[h, h])
    full = clean_windows(valid, jump_h, jump_v, window)
    step = 3
    rs = np.arange(1, H, step)
    cs = np.arange(1, W, step)
    fs = full[np.ix_(rs, cs)]
    if fs.sum() < 100:
        return ones
    r0 = np.where(valid, rng, 0.0)
    si, sj = np.nonzero(fs)
    rows, cols = rs[si], cs[sj]
    offs = np.arange(-h, h + 1)
    patch = r0.ravel().take((rows * W + cols)[:, None, None] + (offs[:, None] * W + offs[None, :])[None])
    fit = np.einsum("nij,ij->n", patch, K2)
    az = np.abs(rng[rows, cols] - fit) / (sigma[rows, cols] * np.sqrt(max(1.0 - lev, 1e-6)) * 0.6745)
    glob = float(np.median(az))
    if not np.isfinite(glob):
        return ones
    # per-block medians (sort by block, then the middle element of each run)
    nbr, nbc = -(-len(rs) // block), -(-len(cs) // block)
    b = (si // block) * nbc + (sj // block)
    order = np.lexsort((az, b))
    bs, azs = b[order], az[order]
    cnt = np.bincount(bs, minlength=nbr * nbc)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = np.full(nbr * nbc, glob)
    ok = cnt >= 16
    med[ok] = azs[start[ok] + cnt[ok] // 2]
    med = ndi.median_filter(med.reshape(nbr, nbc), size=3, mode="nearest")
    med = np.clip(med, 1.0, max_scale)
    pix_r = np.minimum(np.arange(H) // (step * block), nbr - 1)
    pix_c = np.minimum(np.arange(W) // (step * block), nbc - 1)
    return med[pix_r[:, None], pix_c[None, :]]


# --------------------------------------------------------------------------------------------- curvature


def curvature_images(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams,
                     jumps: tuple[np.ndarray, np.ndarray] | None = None) -> CurvatureImages:
    """Mean and Gaussian curvature of a perspective point image, with propagated noise.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame, NaN where no return
    sigma : ndarray of shape (H, W), metres, range sigma along the ray (already floored)
    params : SegmentationParams
    jumps : (ndarray, ndarray), optional
        The image's :func:`~recognition.derivatives.jump_pairs` (``params.jump_k``, ``params.jump_tan``), when
        already at hand.

    Returns
    -------
    CurvatureImages
        ``H`` (1/m) with the normal facing the sensor, ``K`` (1/m²), their sigmas, unit normals (H, W, 3),
        and ``sigma_normal`` (H, W), radians, the propagated angular sigma of the normal.
    """
    der = quadratic_derivatives(points, sigma, params.window, params.jump_k, params.jump_tan, jumps=jumps)
    Pu, Pv = der.Pu, der.Pv
    E = np.einsum("ijk,ijk->ij", Pu, Pu)
    F = np.einsum("ijk,ijk->ij", Pu, Pv)
    G = np.einsum("ijk,ijk->ij", Pv, Pv)
    cr = np.cross(Pu, Pv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = cr / norm3(cr)[..., None]
        flip = np.einsum("ijk,ijk->ij", n, points) > 0
        n[flip] *= -1.0
        L = np.einsum("ijk,ijk->ij", der.Puu, n)
        M = np.einsum("ijk,ijk->ij", der.Puv, n)
        N = np.einsum("ijk,ijk->ij", der.Pvv, n)
        det = E * G - F * F
        K = (L * N - M * M) / det
        Hc = (E * N - 2.0 * F * M + G * L) / (2.0 * det)
        rays = points / norm3(points)[..., None]
        cos2 = np.einsum("ijk,ijk->ij", rays, n) ** 2
        s2 = sigma**2 * cos2
        c = der.cov2  # (H, W, 6): LL, MM, NN, LM, LN, MN per unit variance
        cLL, cMM, cNN, cLM, cLN, cMN = (c[..., i] * s2 for i in range(6))
        hL, hM, hN = G / (2.0 * det), -F / det, E / (2.0 * det)
        var_H = (hL * hL * cLL + hM * hM * cMM + hN * hN * cNN
                 + 2.0 * (hL * hM * cLM + hL * hN * cLN + hM * hN * cMN))
        kL, kM, kN = N / det, -2.0 * M / det, L / det
        var_K = (kL * kL * cLL + kM * kM * cMM + kN * kN * cNN
                 + 2.0 * (kL * kM * cLM + kL * kN * cLN + kM * kN * cMN))
        var_K += (cLL * cNN + 2.0 * cMM * cMM) / det**2
        sig_n = np.sqrt(s2 * (der.var_u / E + der.var_v / G))
    return CurvatureImages(Hc, K, np.sqrt(var_H), np.sqrt(var_K), n, sig_n)


def classify_hk(H: np.ndarray, K: np.ndarray, sigma_H: np.ndarray, sigma_K: np.ndarray, k: float) -> np.ndarray:
    """H-K sign classes with noise-derived zero thresholds.

    Parameters
    ----------
    H, K, sigma_H, sigma_K : ndarray of shape (H, W)
    k : float
        A value is zero when within ``k`` of its sigma.

    Returns
    -------
    ndarray of shape (H, W), int8
        :class:`SurfaceType` values; NONE where H or K is undefined.
    """
    with np.errstate(invalid="ignore"):
        defined = np.isfinite(H) & np.isfinite(K) & np.isfinite(sigma_H) & np.isfinite(sigma_K)
        h0 = np.abs(H) <= k * sigma_H
        k0 = np.abs(K) <= k * sigma_K
        out = np.zeros(H.shape, dtype=np.int8)
        out[k0 & h0] = SurfaceType.PLANAR
        out[k0 & ~h0] = SurfaceType.CYLINDRICAL
        out[~k0 & (K > 0) & ~h0] = SurfaceType.ELLIPTIC
        out[~k0 & (K > 0) & h0] = SurfaceType.PLANAR  # K > 0 with H = 0 cannot happen (K <= H²): noise
        out[~k0 & (K < 0)] = SurfaceType.HYPERBOLIC
    out[~defined] = SurfaceType.NONE
    return out


def _crease_pairs(normals, sig_n, params) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for sl_a, sl_b in (
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        dot = np.clip(np.einsum("ijk,ijk->ij", normals[sl_a], normals[sl_b]), -1.0, 1.0)
        with np.errstate(invalid="ignore"):
            ang = np.arccos(dot)
            thr = np.maximum(params.crease_k * np.hypot(sig_n[sl_a], sig_n[sl_b]), params.crease_min_angle)
            out.append(ang > thr)
    return out[0], out[1]


def _shift(a: np.ndarray, dr: int, dc: int, fill: float = np.nan) -> np.ndarray:
    """``out[r, c] = a[r + dr, c + dc]`` (``fill`` outside the image), as float."""
    out = np.full(a.shape, fill, dtype=np.result_type(a.dtype, np.float64))
    H, W = a.shape[:2]
    if abs(dr) >= H or abs(dc) >= W:
        return out
    ro, ri = (slice(0, H - dr), slice(dr, H)) if dr >= 0 else (slice(-dr, H), slice(0, H + dr))
    co, ci = (slice(0, W - dc), slice(dc, W)) if dc >= 0 else (slice(-dc, W), slice(0, W + dc))
    out[ro, co] = a[ri, ci]
    return out


def _smooth_normals(n: np.ndarray, b: int) -> np.ndarray:
    """Box-filtered unit normals (``b x b``, NaN-aware; NaN where undefined or under half the box defined)."""
    ok = np.isfinite(n[..., 0])
    w = ndi.uniform_filter(ok.astype(np.float64), b, mode="constant")
    s = np.stack([ndi.uniform_filter(np.where(ok, n[..., i], 0.0), b, mode="constant") for i in range(3)], -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s /= norm3(s)[..., None]
    s[~ok | (w < 0.5)] = np.nan
    return s


def _wide_creases(normals: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                  params: SegmentationParams) -> np.ndarray:
    """Crease pixels from the change of the normal across a wide baseline (an (H, W) bool mask).

    Along rows and along columns, with ``k`` the half baseline and ``n`` the normals box-smoothed over
    ``window`` pixels, ``D(i) = angle(n[i-k], n[i+k]) - (angle(n[i-3k], n[i-k]) + angle(n[i+k], n[i+3k])) / 2``:
    the normal turns at a constant rate on a cylinder (D ~ 0) but all at once at a crease (D ~ the crease
    angle). Segments crossing a jump or a hole do not count. A pixel is a crease where D is a local maximum
    (within 2 pixels along the direction) above half the threshold, in a connected line that somewhere
    exceeds the threshold ``max(crease_wide_min_angle, median + crease_wide_k * 1.4826 MAD)`` (robust statistics
    of D over the image: the noise of real sensors is spatially correlated and quantised, so the
    propagated sigma of independent pixels is no guide at this scale).
    """
    k = params.baseline
    H, W = valid.shape
    out = np.zeros((H, W), bool)
    if k <= 0 or min(H, W) <= 2 * k:
        return out
    n = _smooth_normals(normals, params.window)
    for axis, jp in ((1, jump_h), (0, jump_v)):
        dr, dc = (0, 1) if axis == 1 else (1, 0)
        if axis == 1:
            brk = jp | ~valid[:, :-1] | ~valid[:, 1:]
            cum = np.concatenate([np.zeros((H, 1)), np.cumsum(brk, axis=1, dtype=np.float64)], axis=1)
        else:
            brk = jp | ~valid[:-1, :] | ~valid[1:, :]
            cum = np.concatenate([np.zeros((1, W)), np.cumsum(brk, axis=0, dtype=np.float64)], axis=0)

        def ang(o1: int, o2: int, dr=dr, dc=dc, cum=cum) -> np.ndarray:
            a, b = _shift(n, o1 * dr, o1 * dc), _shift(n, o2 * dr, o2 * dc)
            with np.errstate(invalid="ignore"):
                t = np.arccos(np.clip(np.einsum("ijk,ijk->ij", a, b), -1.0, 1.0))
                free = (_shift(cum, o2 * dr, o2 * dc) - _shift(cum, o1 * dr, o1 * dc)) == 0
            return np.where(free, t, np.nan)

        D = ang(-k, k) - 0.5 * (np.nan_to_num(ang(-3 * k, -k)) + np.nan_to_num(ang(k, 3 * k)))
        fin = np.isfinite(D)
        if fin.sum() < 100:
            continue
        med = float(np.median(D[fin]))
        scale = 1.4826 * float(np.median(np.abs(D[fin] - med)))
        thr = max(params.crease_wide_min_angle, med + params.crease_wide_k * scale)
        Dz = np.where(fin, D, -np.inf)
        m = Dz > 0.5 * thr
        for o in (1, 2):
            m &= (Dz >= _shift(Dz, o * dr, o * dc, -np.inf)) & (Dz >= _shift(Dz, -o * dr, -o * dc, -np.inf))
        lab, nl = ndi.label(m, structure=np.ones((3, 3), bool))
        keep = np.zeros(nl + 1, bool)
        keep[lab[m & (Dz > thr)]] = True
        keep[0] = False
        out |= keep[lab]
    return out


# --------------------------------------------------------------------------------------------- patches


def _structure(connectivity: int) -> np.ndarray:
    return ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)


def _seed_labels(hk: np.ndarray, edges: np.ndarray, params: SegmentationParams) -> np.ndarray:
    """Class components (edges removed) that survive the seed erosion, labelled 0..n-1 (-1 elsewhere)."""
    labels = np.full(hk.shape, -1, dtype=np.int32)
    struct = _structure(params.connectivity)
    nxt = 0
    for cls in (SurfaceType.PLANAR, SurfaceType.CYLINDRICAL, SurfaceType.ELLIPTIC, SurfaceType.HYPERBOLIC):
        m = (hk == cls) & (edges == 0)
        if not m.any():
            continue
        lab, n = ndi.label(m, structure=struct)
        er = ndi.binary_erosion(m, structure=np.ones((3, 3), bool), iterations=params.erosion) \
            if params.erosion > 0 else m
        counts = np.bincount(lab[er], minlength=n + 1)
        keep = counts >= params.min_seed_pixels
        keep[0] = False
        if not keep.any():
            continue
        remap = np.where(keep, np.cumsum(keep) - 1 + nxt, -1).astype(np.int32)
        sel = remap[lab]
        labels[sel >= 0] = sel[sel >= 0]
        nxt += int(keep.sum())
    return labels


def _split_at_creases(seeds: np.ndarray, wide: np.ndarray, st: _State, params: SegmentationParams) -> np.ndarray:
    """Cut seeds that one surface does not fit along the wide-baseline creases inside them.

    Crease lines stop about a baseline short of the seed's outline (the test needs both ends of its baseline
    on the surface) and may have gaps, so one class component can run around them from face to face. A seed
    whose trimmed fit leaves an RMS range residual beyond ``split_k`` sigma is reduced to its core: eroded by
    the baseline, minus the creases widened by 2 pixels; when that core falls into several connected pieces
    (of at least ``min_seed_pixels``) they become the seeds (growing gives the rest back), else the seed stays.
    """
    k = params.baseline
    groups = _groups(seeds)
    if k <= 0 or not groups or not wide.any():
        return seeds
    n = int(seeds.max()) + 1
    P = _fit_groups(groups, st, n, trim=2.0 * params.grow_k)
    H, W = seeds.shape
    crease = ndi.binary_dilation(wide, structure=np.ones((3, 3), bool), iterations=2)
    out = seeds.copy()
    nxt = n
    for lab, idx in groups.items():
        if idx.size < 4 * params.min_seed_pixels:
            continue
        r, c = np.divmod(idx, W)
        if not crease[r, c].any():
            continue
        sub = _subsample(idx, st.params.max_fit_points)
        z = _pixel_residuals(P[[lab]], np.zeros(sub.size, np.int64), st.X[sub], st.U[sub], st.S[sub])
        if _rms(z) <= params.split_k:
            continue
        r0, r1, c0, c1 = r.min(), r.max() + 1, c.min(), c.max() + 1
        m = np.zeros((r1 - r0 + 2 * k + 2, c1 - c0 + 2 * k + 2), bool)
        m[r - r0 + k + 1, c - c0 + k + 1] = True
        core = ndi.binary_erosion(m, structure=np.ones((3, 3), bool), iterations=k)
        core[k + 1:k + 1 + r1 - r0, k + 1:k + 1 + c1 - c0] &= ~crease[r0:r1, c0:c1]
        comp, nc = ndi.label(core)
        if nc < 2:
            continue
        sizes = np.bincount(comp.ravel(), minlength=nc + 1)
        keep = sizes >= params.min_seed_pixels
        keep[0] = False
        if keep.sum() < 2:
            continue
        remap = np.where(keep, np.cumsum(keep) - 1 + nxt, -1)
        cr, cc = np.nonzero(comp > 0)
        new = remap[comp[cr, cc]]
        out[r, c] = -1
        ok = new >= 0
        out[cr[ok] + r0 - k - 1, cc[ok] + c0 - k - 1] = new[ok]
        nxt += int(keep.sum())
    if nxt == n:
        return seeds
    used = np.unique(out[out >= 0])
    remap = np.full(nxt, -1, np.int32)
    remap[used] = np.arange(used.size, dtype=np.int32)
    return np.where(out >= 0, remap[np.maximum(out, 0)], -1).astype(np.int32)


def _split_bad_seeds(seeds: np.ndarray, st: _State, params: SegmentationParams) -> np.ndarray:
    """Cut seeds that one surface does not fit into square tiles of ``seed_tile`` pixels.

    A class component can span two surfaces with the same curvature signs (a pipe and the cylindrical-looking
    end of a tangent elbow, two faces meeting at a blurred crease): when the trimmed fit of the seed leaves
    an RMS range residual beyond ``split_k`` sigma while its tiles are fitted within ``merge_k`` (median
    over tiles: otherwise the data are just noisier than declared), its tiles become seeds of their own, and merging
    reassembles the tiles that share a surface.
    """
    groups = _groups(seeds)
    if not groups:
        return seeds
    n = int(seeds.max()) + 1
    P = _fit_groups(groups, st, n, trim=2.0 * params.grow_k)
    W = seeds.shape[1]
    t = params.seed_tile
    out = seeds.copy().ravel()
    labs = [lab for lab, idx in groups.items() if idx.size >= 2 * params.min_seed_pixels]
    bad = []
    if labs:  # the seeds' RMS residuals to their fits, in one batch
        subs = [_subsample(groups[lab], st.params.max_fit_points) for lab in labs]
        cnt = np.array([sub.size for sub in subs])
        ix = np.concatenate(subs)
        z = _pixel_residuals(P, np.repeat(labs, cnt), st.X[ix], st.U[ix], st.S[ix])
        rms = np.sqrt(_group_sums(z * z, np.concatenate([[0], np.cumsum(cnt)[:-1]])) / cnt)
        bad = [lab for lab, r in zip(labs, rms, strict=True) if not r <= params.split_k]
    tiles = {}
    for lab in bad:
        r, c = np.divmod(groups[lab], W)
        tiles[lab] = np.unique((r // t) * (W // t + 1) + c // t, return_inverse=True)[1]
    fit = _tiles_fit({lab: groups[lab] for lab in bad}, tiles, st, params)
    nxt = n
    for lab in bad:
        if not fit[lab]:
            continue  # the tiles fit no better: the noise is larger than declared, not two surfaces
        out[groups[lab]] = nxt + tiles[lab]
        nxt += int(tiles[lab].max()) + 1
    out = out.reshape(seeds.shape)
    # tiles may be disconnected pieces: relabel connected components of each label, drop tiny pieces
    lab_cc = _split_disconnected(out, out >= 0)
    sizes = np.bincount(lab_cc[lab_cc >= 0])
    keep = sizes >= params.min_seed_pixels
    remap = np.where(keep, np.cumsum(keep) - 1, -1).astype(np.int32)
    return np.where(lab_cc >= 0, remap[np.maximum(lab_cc, 0)], -1).astype(np.int32)


def _tiles_fit(seeds: dict[int, np.ndarray], tiles: dict[int, np.ndarray], st: _State,
               params: SegmentationParams) -> dict[int, bool]:
    """For each badly fitted seed (pixels ``seeds[k]``, tile index per pixel ``tiles[k]``): are most of its
    tiles fitted well (median tile RMS within ``merge_k``)? All tiles fitted in one batch."""
    parts, owner = [], []
    for k, idx in seeds.items():
        inv = tiles[k]
        order = np.argsort(inv, kind="stable")
        cuts = np.flatnonzero(np.diff(inv[order])) + 1
        mine = [part for part in np.split(idx[order], cuts) if part.size >= 10]
        parts += mine
        owner += [k] * len(mine)
    out = dict.fromkeys(seeds, False)
    if not parts:
        return out
    planar = np.array([_is_planar_counts(np.bincount(st.hk[part], minlength=5)) for part in parts])
    _, zs = _quick_fits(parts, planar, st)
    rms = np.array([_rms(z) for z in zs])
    owner = np.array(owner)
    for k in seeds:
        mine = owner == k
        if mine.any():
            out[k] = float(np.median(rms[mine])) <= params.merge_k
    return out


def _tile_small_leftovers(comp: np.ndarray, st: _State, params: SegmentationParams) -> np.ndarray:
    """Leftover components below ``max_tiled_leftover`` pixels go through :func:`_split_bad_seeds`
    (pieces under ``min_seed_pixels`` are released); labels stay 0..n-1, -1 elsewhere."""
    if not (comp >= 0).any():
        return comp
    sizes = np.bincount(comp[comp >= 0])
    small = (comp >= 0) & (sizes[np.maximum(comp, 0)] < params.max_tiled_leftover)
    if not small.any():
        return comp
    tiled = _split_bad_seeds(np.where(small, comp, -1).astype(np.int32), st, params)
    n_t = int(tiled.max()) + 1
    out = np.where(small, tiled, np.where(comp >= 0, comp + n_t, -1))
    used = np.unique(out[out >= 0])
    remap = np.full(int(out.max()) + 1 if used.size else 1, -1, np.int64)
    remap[used] = np.arange(used.size)
    return np.where(out >= 0, remap[np.maximum(out, 0)], -1)


def _groups(labels: np.ndarray) -> dict[int, np.ndarray]:
    """Flat pixel indices of each label >= 0 (increasing)."""
    flat = labels.ravel()
    if flat.size == 0 or flat.max() < 0:
        return {}
    found = ndi.value_indices(np.maximum(flat, -1), ignore_value=-1)
    return {int(k): found[k][0] for k in sorted(found)}


def _subsample(idx: np.ndarray, n_max: int) -> np.ndarray:
    if idx.size <= n_max:
        return idx
    return idx[np.linspace(0, idx.size - 1, n_max).astype(np.int64)]


def _quick_fit(x: np.ndarray, u: np.ndarray, s: np.ndarray, planar: bool,
               want_params: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """Plane (TLS) or quadric (unit-norm LSQ) fit; its parameters (10,) in metres and the ray z-residuals.

    ``x`` points (N, 3), ``u`` their unit rays, ``s`` their sigmas. The residual of each point is the range
    change putting it on the surface to first order, in sigma units (the incidence cosine floored at 0.25).
    """
    if planar or len(x) < 10:
        if len(x) < 3:
            return (np.full(10, np.nan) if want_params else None), np.full(len(x), np.inf)
        c = x.mean(axis=0)
        d = x - c
        _, V = np.linalg.eigh(d.T @ d)
        n = V[:, 0]
        f = d @ n
        g = np.broadcast_to(n, x.shape)
        p = plane_params(n, float(n @ c)) if want_params else None
        scale = 1.0
    else:
        mean = x.mean(axis=0)
        scale = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1)))) or 1.0
        y = (x - mean) / scale
        D = quadric_monomials(y)
        pn, _ = taubin_fit(D, y, np.ones(len(y)))
        if pn is None:
            _, V = np.linalg.eigh(D.T @ D)
            pn = V[:, 0]
        f = D @ pn
        g = quadric_gradient(pn, y)
        p = None
        if want_params:
            p = normalisation_transform(mean, scale) @ pn
            p /= np.linalg.norm(p)
    gr = np.sum(g * u, axis=1)
    floor = _MIN_GRAZING * norm3(g)
    gr = np.where(np.abs(gr) < floor, floor, np.abs(gr))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = scale * np.abs(f) / (gr * s)
    return p, np.where(np.isfinite(z), z, np.inf)


def _rms(z: np.ndarray) -> float:
    return float(np.sqrt(z @ z / z.size)) if z.size else float("inf")


@dataclass
class _State:
    """Working arrays of the region growing / merging (private)."""

    X: np.ndarray  # (H*W, 3) points
    U: np.ndarray  # (H*W, 3) unit rays
    S: np.ndarray  # (H*W,) sigma
    hk: np.ndarray  # (H*W,) class
    params: SegmentationParams


def _is_planar_counts(counts: np.ndarray) -> bool:
    """Whether planar pixels (class 1) are the patch's most common curvature class (or it has none)."""
    c = counts.tolist()
    return c[1] >= max(c[1:])


# --------------------------------------------------------------------------------------------- batched fits
# The quick fits of many groups at once (seeds, tiles, patches): one pass of numpy over all their points
# instead of a Python loop of small fits. Same fits as :func:`_quick_fit`; points arrive sorted by group.

_UPPER3 = np.triu_indices(3)


def _group_sums(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (N, ...) over the contiguous groups beginning at ``starts``."""
    return np.add.reduceat(values, starts, axis=0)


def _group_grams(A: np.ndarray, starts: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Gram matrices ``A_g' A_g`` (G, k, k) of the contiguous row groups of ``A`` (N, k)."""
    return np.stack([A[s:s + c].T @ A[s:s + c] for s, c in zip(starts.tolist(), cnt.tolist(), strict=True)])


def _symmetric(upper: np.ndarray, n: int, iu) -> np.ndarray:
    out = np.zeros((upper.shape[0], n, n))
    out[:, iu[0], iu[1]] = upper
    out[:, iu[1], iu[0]] = upper
    return out


def _plane_fits(X, U, S, gid, starts, cnt):
    """Total-least-squares planes of the groups: parameters (G, 10) and per-point ray z-residuals (N,)."""
    mean = _group_sums(X, starts) / cnt[:, None]
    d = X - mean[gid]
    C = _group_sums(d[:, [0, 0, 0, 1, 1, 2]] * d[:, [0, 1, 2, 1, 2, 2]], starts)
    _, V = np.linalg.eigh(_symmetric(C, 3, _UPPER3))
    n = V[:, :, 0]
    f = np.einsum("ij,ij->i", d, n[gid])
    gr = np.maximum(np.abs(np.einsum("ij,ij->i", U, n[gid])), _MIN_GRAZING)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(f) / (gr * S)
    P = np.zeros((len(cnt), 10))
    P[:, 6:9] = n
    P[:, 9] = -np.einsum("ij,ij->i", n, mean)
    bad = cnt < 3
    P[bad] = np.nan
    z[bad[gid]] = np.inf
    return P, np.where(np.isfinite(z), z, np.inf)


# Taubin's normalisation N9 = sum_k G_k' S4 G_k (G_k = MONOMIAL_GRADIENT[k]) as a linear map of S4's 16 entries
_TAUBIN_MAP = np.einsum("kmi,knj->mnij", MONOMIAL_GRADIENT, MONOMIAL_GRADIENT)[:, :, :9, :9].reshape(16, 81)


def _quadric_fits(X, U, S, gid, starts, cnt):
    """Taubin quadrics of the groups (unit-norm algebraic fit where Taubin's is undefined), in normalised
    coordinates per group: parameters (G, 10) in metres and per-point ray z-residuals (N,).

    Per-point quantities are laid out by rows (one contiguous row per monomial or coordinate): the products
    below then run on contiguous memory.
    """
    G = len(cnt)
    mean = _group_sums(X, starts) / cnt[:, None]
    d = X - mean[gid]
    scale = np.sqrt(_group_sums(np.einsum("ij,ij->i", d, d), starts) / cnt)
    scale = np.where(scale > 0, scale, 1.0)
    yT = (d / scale[gid, None]).T.copy()
    x0, x1, x2 = yT
    DT = np.empty((10, x0.size))  # quadric_monomials(y).T
    np.multiply(x0, x0, out=DT[0])
    np.multiply(x1, x1, out=DT[1])
    np.multiply(x2, x2, out=DT[2])
    DT[3], DT[4], DT[5] = 2 * x0 * x1, 2 * x0 * x2, 2 * x1 * x2
    DT[6:9] = yT
    DT[9] = 1.0
    M = np.stack([DT[:, s:s + c] @ DT[:, s:s + c].T for s, c in zip(starts.tolist(), cnt.tolist(), strict=True)])
    S4 = M[:, 6:, 6:]  # the moments of (x, y, z, 1), the last four monomials
    N9 = (S4.reshape(G, 16) @ _TAUBIN_MAP).reshape(G, 9, 9)
    tr = np.trace(M, axis1=1, axis2=2)
    ev = np.linalg.eigvalsh(M / np.where(tr > 0, tr, 1.0)[:, None, None])
    evn = np.linalg.eigvalsh(N9)
    ok = (ev[:, 1] >= 1e-12) & (evn[:, 0] > 1e-12 * np.maximum(evn[:, -1], 1e-300)) & (M[:, 9, 9] > 0)
    N9 = np.where(ok[:, None, None], N9, np.eye(9))
    m99 = np.where(ok, M[:, 9, 9], 1.0)
    Sg = M[:, :9, :9] - M[:, :9, 9:10] @ M[:, 9:10, :9] / m99[:, None, None]
    L = np.linalg.cholesky(N9)
    A = np.linalg.solve(L, Sg)
    A = np.linalg.solve(L, A.transpose(0, 2, 1))
    _, W = np.linalg.eigh(0.5 * (A + A.transpose(0, 2, 1)))
    q = np.linalg.solve(L.transpose(0, 2, 1), W[:, :, :1])[:, :, 0]
    c = -np.einsum("gi,gi->g", M[:, 9, :9], q) / m99
    pn = np.column_stack([q, c])
    if not ok.all():
        _, V = np.linalg.eigh(M[~ok])
        pn[~ok] = V[:, :, 0]
    pn /= np.linalg.norm(pn, axis=1, keepdims=True)
    p = pn.T if G == 1 else pn.T.take(gid, axis=1)  # (10, 1) broadcast, or (10, N): each point's quadric
    f = np.einsum("ij,ij->j", DT, np.broadcast_to(p, DT.shape))
    z = _ray_z(p, yT, U, S, scale[gid] * f)  # |s f| = s |f|: back to metres
    # back to metres (normalisation_transform of every group at once): A / s², b / s - 2 A m / s², ...
    Ay = pn[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(G, 3, 3)
    Am = np.einsum("gij,gj->gi", Ay, mean)
    is2 = 1.0 / scale**2
    P = np.empty((G, 10))
    P[:, :6] = pn[:, :6] * is2[:, None]
    P[:, 6:9] = pn[:, 6:9] / scale[:, None] - 2.0 * Am * is2[:, None]
    P[:, 9] = np.einsum("gi,gi->g", mean, Am) * is2 - np.einsum("gi,gi->g", pn[:, 6:9], mean) / scale + pn[:, 9]
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    return P, z


def _quick_fits(idx_list: list[np.ndarray], planar: np.ndarray, st: _State):
    """:func:`_quick_fit` of many groups (flat pixel indices each): parameters (G, 10), per-group z arrays.

    Groups of fewer than 10 points get planes, as in :func:`_quick_fit`.
    """
    G = len(idx_list)
    P = np.full((G, 10), np.nan)
    zs: list[np.ndarray] = [np.zeros(0)] * G
    cnt_all = np.array([len(i) for i in idx_list])
    use_plane = np.asarray(planar, bool) | (cnt_all < 10)
    for flag, fitter in ((True, _plane_fits), (False, _quadric_fits)):
        sel = np.flatnonzero((use_plane == flag) & (cnt_all > 0))
        if sel.size == 0:
            continue
        cnt = cnt_all[sel]
        ix = np.concatenate([idx_list[k] for k in sel])
        gid = np.repeat(np.arange(sel.size), cnt)
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        try:
            Pk, z = fitter(st.X.take(ix, axis=0), st.U.take(ix, axis=0), st.S.take(ix), gid, starts, cnt)
        except np.linalg.LinAlgError:  # a numerically singular group: fit them one by one
            fits = [_quick_fit(st.X[idx_list[k]], st.U[idx_list[k]], st.S[idx_list[k]], flag) for k in sel]
            Pk, z = np.array([f[0] for f in fits]), np.concatenate([f[1] for f in fits])
        P[sel] = Pk
        for j, s0, n in zip(sel.tolist(), starts.tolist(), cnt.tolist(), strict=True):
            zs[j] = z[s0:s0 + n]
    for k in np.flatnonzero(cnt_all == 0):
        zs[k] = np.zeros(0)
    return P, zs


def _quick_fits_of(groups: dict[int, np.ndarray], keys: list[int], st: _State) -> dict[int, np.ndarray]:
    """The quick fit (plane or quadric by the patch's H-K classes, on a subsample) of each patch ``keys`` of
    ``groups``, in one batch: ``{label: parameters (10,)}``."""
    P, _ = _quick_fits([_subsample(groups[k], st.params.max_fit_points) for k in keys],
                       np.array([_is_planar_counts(np.bincount(st.hk[groups[k]], minlength=5)) for k in keys]), st)
    return dict(zip(keys, P, strict=True))


def _trim_threshold(z: np.ndarray, trim: float) -> float:
    """``max(trim, 3 median(z))`` for residuals ``z >= 0``; counting instead of sorting when the middle
    element(s) are within ``trim / 3``."""
    n = z.size
    m = (n + 1) // 2  # rank of the (lower) middle element
    within = int(np.count_nonzero(3.0 * z <= trim))
    if within >= m + (n % 2 == 0):  # the middle element(s) within: so is their mean
        return trim
    return max(trim, 3.0 * float(np.median(z)))


def _fit_groups(groups: dict[int, np.ndarray], st: _State, n_labels: int, trim: float | None = None) -> np.ndarray:
    """Plane / quadric parameters (n_labels, 10) of each group (on a subsample of its pixels).

    With ``trim``, each fit is repeated once without the points whose residual exceeds ``trim`` sigma (and
    3x the median residual): a few points of another surface ruin an algebraic quadric fit.
    """
    P = np.full((max(n_labels, 1), 10), np.nan)
    if not groups:
        return P
    labs = list(groups)
    subs = [_subsample(groups[k], st.params.max_fit_points) for k in labs]
    planar = np.array([_is_planar_counts(np.bincount(st.hk[groups[k]], minlength=5)) for k in labs])
    Pg, zs = _quick_fits(subs, planar, st)
    # not a plane after all: curvature undefined (thin pipes: every window crosses a jump) or within its
    # noise (a pipe seen close up by a fine-grained sensor, whose windows span a few mm)
    rms = [_rms(z) for z in zs]
    retry = [k for k in range(len(labs)) if planar[k] and subs[k].size >= 20 and not rms[k] <= st.params.merge_k]
    if retry:
        Pq, zq = _quick_fits([subs[k] for k in retry], np.zeros(len(retry), bool), st)
        for j, k in enumerate(retry):
            # ... but not two faces across a blurred crease, which a plane pair fits exactly
            if _rms(zq[j]) < 0.5 * rms[k] and not _is_plane_pair(Pq[j], st.X[subs[k]], _PLANE_PAIR_TOL):
                planar[k], Pg[k], zs[k] = False, Pq[j], zq[j]
    if trim is not None:
        redo = []
        for k in range(len(labs)):
            if subs[k].size < 10:
                continue
            keep = zs[k] <= _trim_threshold(zs[k], trim)
            if 10 <= keep.sum() < subs[k].size:
                subs[k] = subs[k][keep]
                redo.append(k)
        if redo:
            Pg[redo], _ = _quick_fits([subs[k] for k in redo], planar[redo], st)
    P[labs] = Pg
    return P


# relative tolerance of the plane-pair test (rank and constant of the quadric); 0.05 and 0.15 gave the same
# segmentations on the default suite
_PLANE_PAIR_TOL = 0.05


def _is_plane_pair(p: np.ndarray, x: np.ndarray, tol: float) -> bool:
    """True when the quadric ``p`` (10,) is, over the extent of points ``x`` (N, 3), two intersecting planes.

    ``A`` of rank 2 with eigenvalues of opposite signs, the linear term within its range and the canonical
    constant near zero: ``(n1 . y)(n2 . y) = 0``. Each test is relative to the largest eigenvalue, on the
    scale of the points' RMS radius ``R`` (``tol`` for the rank and constant).
    """
    if not np.all(np.isfinite(p)):
        return False
    A, b, c = quadric_matrices(p)
    mean = x.mean(axis=0)
    R = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1)))) or 1.0
    # in centred coordinates: f = y'Ay + (2 A mean + b)'y + f(mean)
    b0 = 2 * A @ mean + b
    c0 = float(mean @ A @ mean + b @ mean + c)
    lam, V = _eig_by_magnitude(A)
    l1 = abs(lam[0])
    if l1 == 0 or abs(lam[2]) > tol * l1 or lam[0] * lam[1] >= 0:
        return False
    bv = V.T @ b0
    if abs(bv[2]) > tol * l1 * R:
        return False
    t = -0.5 * bv[:2] / lam[:2]  # centre within the range of A
    c_cano = c0 + 0.5 * float(bv[:2] @ t)
    return abs(c_cano) <= tol * l1 * R * R


def _eig_by_magnitude(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (3,) of the symmetric ``A`` by decreasing magnitude, and their eigenvectors (columns)."""
    lam, V = np.linalg.eigh(A)
    order = np.argsort(-np.abs(lam))
    return lam[order], V[:, order]


def _plane_pair_sides(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Side (0 or 1) of each point ``x`` (N, 3): the nearer of the two planes of the plane-pair quadric ``p``.

    With ``A = l1 v1 v1' + l2 v2 v2'`` (``l1 > 0 > l2``) and centre ``t`` (``2 A t = -b``, in the range of
    ``A``), the quadric is ``(m+ . (y - t)) (m- . (y - t))`` with ``m± = sqrt(l1) v1 ± sqrt(-l2) v2``.
    """
    A, b, _ = quadric_matrices(p)
    lam, V = _eig_by_magnitude(A)
    if lam[0] < 0:
        lam = -lam
    t = np.linalg.pinv(A, rcond=1e-6) @ (-0.5 * b)
    m1 = np.sqrt(lam[0]) * V[:, 0] + np.sqrt(-lam[1]) * V[:, 1]
    m2 = np.sqrt(lam[0]) * V[:, 0] - np.sqrt(-lam[1]) * V[:, 1]
    y = x - t
    d1 = np.abs(y @ m1) / np.linalg.norm(m1)
    d2 = np.abs(y @ m2) / np.linalg.norm(m2)
    return (d2 < d1).astype(np.int8)


def _k_planes(x: np.ndarray, u: np.ndarray, s: np.ndarray, k: int, iterations: int = 10,
              inlier_z: float = 3.0, trials: int = 100) -> np.ndarray | None:
    """Part (0 .. k-1) of each point ``x`` (N, 3) by k planes fitted alternately (k-planes): each point goes
    to the plane nearest along its ray ``u`` (in its sigmas ``s``), each plane is refitted to its points.

    Started by sequential RANSAC: the plane through three of the points (``trials`` triples, a fixed seed:
    deterministic) with most points within ``inlier_z`` sigmas, refitted on them, then the next one among
    the points left. A start from the pixels' normals (k mutually distant ones) put a far box's narrow top
    and its front in one part: its normals are too noisy there. None when a part empties."""
    n_pts = len(x)
    if n_pts < 3 * k:
        return None
    gen = np.random.default_rng(0)

    def dist(c, n):
        return np.abs((x - c) @ n) / (np.maximum(np.abs(u @ n), _MIN_GRAZING) * s)

    def plane_of(m):
        c = x[m].mean(axis=0)
        return c, np.linalg.eigh((x[m] - c).T @ (x[m] - c))[1][:, 0]

    left = np.ones(n_pts, bool)
    planes = []
    for _ in range(k):
        pool = np.flatnonzero(left)
        if pool.size < 3:
            return None
        tri = x[pool[gen.integers(0, pool.size, size=(trials, 3))]]  # (trials, 3 points, 3)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(nrm, axis=1)
        good = norm > 1e-12
        if not good.any():
            return None
        nrm, c0 = nrm[good] / norm[good, None], tri[good, 0]
        # inlier counts of all candidates at once: (candidates, points) distances along the rays
        z = np.abs(np.einsum("cj,cj->c", nrm, c0)[:, None] - nrm @ x[pool].T)
        z /= np.maximum(np.abs(nrm @ u[pool].T), _MIN_GRAZING) * s[pool]
        b = int(np.argmax((z <= inlier_z).sum(axis=1)))
        inl = np.zeros(n_pts, bool)
        inl[pool[z[b] <= inlier_z]] = True
        for _ in range(3):
            if inl.sum() < 3:
                return None
            inl = (dist(*plane_of(inl)) <= inlier_z) & left
        if inl.sum() < 3:
            return None
        planes.append(plane_of(inl))
        left &= ~inl
    part = np.argmin(np.stack([dist(c, n) for c, n in planes]), axis=0)
    for _ in range(iterations):
        z = np.full((k, n_pts), np.inf)
        for j in range(k):
            m = part == j
            if m.sum() < 3:
                return None
            z[j] = dist(*plane_of(m))
        new = np.argmin(z, axis=0)
        if np.array_equal(new, part):
            break
        part = new
    return part


def _broad(x: np.ndarray, s: np.ndarray, ratio: float = 10.0) -> bool:
    """Whether points ``x`` (N, 3) spread across their plane (the narrower in-plane standard deviation) over
    ``ratio`` times their median sigma ``s``: a face, not a strip of a pipe that the noise lets pass for flat."""
    c = x.mean(axis=0)
    w = np.linalg.eigvalsh((x - c).T @ (x - c) / len(x))
    return bool(np.sqrt(max(w[1], 0.0)) >= ratio * float(np.median(s)))


def _trimmed_rms(z: np.ndarray, keep: float = 0.9) -> float:
    """RMS of the smallest ``keep`` share of ``z`` (the pixels mixed at a crease are the rest)."""
    return _rms(np.sort(z)[: max(int(keep * z.size), 1)])


_FACE_COS = np.cos(np.radians(30.0))  # faces cut apart by _faces meet at 30 deg or more


def _faces(idx: np.ndarray, st: _State, params: SegmentationParams) -> list[np.ndarray]:
    """The two or three faces (:func:`_k_planes`) of the patch of pixels ``idx`` that each fit a plane within
    ``1.5 merge_k`` (but for a tenth of their pixels, mixed at the creases: a far box's faces are a few pixels
    wide), are broad against the noise (:func:`_broad`) and meet at 30 deg or more (not one face with a few
    stray pixels); [] when there are none. Of three parts, one parallel to a face, at 30 deg or more from
    the other and of at most half that face's pixels is the face's layer (returns mixed at its edge, or a
    piece of the surface behind it) and goes with it, unchecked. (Larger parallel parts were facets of a
    near pipe on the ``calibration`` suite.)"""
    for k in (2, 3):
        part = _k_planes(st.X[idx], st.U[idx], st.S[idx], k)
        if part is None:
            continue
        faces = [idx[part == j] for j in range(k)]
        Pf, zf = _quick_fits([_subsample(f, params.max_fit_points) for f in faces], np.ones(k, bool), st)
        cos = np.abs(Pf[:, 6:9] @ Pf[:, 6:9].T)
        pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
        parallel = [(i, j) for i, j in pairs if cos[i, j] > _FACE_COS]
        layer = host = None
        if k == 3 and len(parallel) == 1:
            host, layer = sorted(parallel[0], key=lambda j: -faces[j].size)
            if 2 * faces[layer].size > faces[host].size:
                host = layer = None
        keep = [j for j in range(k) if j != layer]
        if min(faces[j].size for j in keep) < params.min_patch_pixels or \
                not all(_broad(st.X[faces[j]], st.S[faces[j]]) for j in keep):
            continue
        if all(cos[i, j] <= _FACE_COS for i, j in pairs if i in keep and j in keep) and \
                all(_trimmed_rms(zf[j]) <= 1.5 * params.merge_k for j in keep):
            if layer is not None:
                faces[host] = np.sort(np.concatenate([faces[host], faces[layer]]))
            return [faces[j] for j in keep]
    return []


def _split_plane_pairs(labels: np.ndarray, st: _State, params: SegmentationParams,
                       cut_faces: bool = False) -> np.ndarray:
    """Cut each patch that no plane fits (RMS beyond ``merge_k``) but a plane pair does (two faces of a far,
    small box whose crease the curvature could not see, reassembled from noisy tiles) along its crease,
    when each side then fits its own plane. With ``cut_faces``, a patch that no quadric fits either is cut
    into the two or three faces that fit planes (:func:`_faces`)."""
    groups = {k: v for k, v in _groups(labels).items() if v.size >= 2 * params.min_patch_pixels}
    if not groups:
        return labels
    labs = list(groups)
    subs = [_subsample(groups[k], params.max_fit_points) for k in labs]
    _, zp = _quick_fits(subs, np.ones(len(labs), bool), st)
    bad = [j for j in range(len(labs)) if not _rms(zp[j]) <= params.merge_k]
    if not bad:
        return labels
    Pq, zq = _quick_fits([subs[j] for j in bad], np.zeros(len(bad), bool), st)
    out = labels
    nxt = int(labels.max()) + 1
    for q, z, j in zip(Pq, zq, bad, strict=True):
        idx = groups[labs[j]]
        if _is_plane_pair(q, st.X[subs[j]], _PLANE_PAIR_TOL):
            side = _plane_pair_sides(q, st.X[idx])
            pieces = [idx[side == 0], idx[side == 1]]
            if min(h.size for h in pieces) < params.min_patch_pixels:
                continue
            _, zh = _quick_fits([_subsample(h, params.max_fit_points) for h in pieces], np.ones(2, bool), st)
            if not all(_rms(z) <= params.merge_k for z in zh):
                continue
        elif not _rms(z) <= params.merge_k and cut_faces:
            # no quadric fits either: the pixels mixed at the crease spoil the plane pair
            pieces = _faces(idx, st, params)
        else:
            continue
        if out is labels and pieces:
            out = labels.copy()
        for piece in pieces[1:]:
            out.reshape(-1)[piece] = nxt
            nxt += 1
    return out


def _neighbour_links(shape, valid, jump_h, jump_v):
    """For each direction (left, right, up, down): (row shift, col shift, link allowed (H, W) bool)."""
    H, W = shape
    links = []
    left = np.zeros(shape, bool)
    left[:, 1:] = valid[:, :-1] & ~jump_h
    right = np.zeros(shape, bool)
    right[:, :-1] = valid[:, 1:] & ~jump_h
    up = np.zeros(shape, bool)
    up[1:, :] = valid[:-1, :] & ~jump_v
    down = np.zeros(shape, bool)
    down[:-1, :] = valid[1:, :] & ~jump_v
    for (dr, dc), ok in (((0, -1), left), ((0, 1), right), ((-1, 0), up), ((1, 0), down)):
        links.append((dr, dc, ok & valid))
    return links


def _grow(labels: np.ndarray, P: np.ndarray, st: _State, links, max_iter: int, thr: float) -> None:
    """Grow labelled patches into unlabelled valid pixels whose residual fits (in place)."""
    H, W = labels.shape
    flat = labels.ravel()
    cand = np.flatnonzero((flat < 0) & np.isfinite(st.S))
    if cand.size == 0:
        return
    r, c = np.divmod(cand, W)
    nb = []
    for dr, dc, ok in links:
        allowed = ok[r, c]
        nidx = np.where(allowed, (r + dr) * W + (c + dc), -1)
        nb.append(nidx)
    nb = np.stack(nb)  # (4, n)
    x = st.X[cand]
    u = st.U[cand]
    s = st.S[cand]
    where = np.full(H * W, -1, np.int64)  # candidate index of each pixel
    where[cand] = np.arange(cand.size)
    # the front: candidates with a labelled neighbour; after the first pass only those next to a pixel just
    # labelled (a candidate whose neighbours did not change would be rejected again)
    fi = np.flatnonzero((np.where(nb >= 0, flat[np.maximum(nb, 0)], -1) >= 0).any(axis=0))
    for _ in range(max_iter):
        if fi.size == 0:
            break
        nbf = nb[:, fi]
        nl = np.where(nbf >= 0, flat[np.maximum(nbf, 0)], -1)
        z = np.full((4, fi.size), np.inf)
        for k in range(4):
            m = nl[k] >= 0
            if m.any():
                sel = fi[m]
                z[k, m] = _pixel_residuals(P, nl[k, m], x[sel], u[sel], s[sel])
        best = np.argmin(z, axis=0)
        acc = z[best, np.arange(fi.size)] <= thr
        if not acc.any():
            break
        new = cand[fi[acc]]
        flat[new] = nl[best[acc], np.flatnonzero(acc)]
        r_new, c_new = np.divmod(new, W)
        around = np.concatenate([new[c_new > 0] - 1, new[c_new < W - 1] + 1, new[r_new > 0] - W,
                                 new[r_new < H - 1] + W])
        touched = np.zeros(cand.size + 1, bool)  # (the last slot takes the -1 of pixels that are not candidates)
        touched[where[around]] = True
        ci = np.flatnonzero(touched[:-1])
        fi = ci[flat[cand[ci]] < 0]


def _link_components(mask: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """4-connected components of ``mask`` whose links never cross a jump pair; labels 0..n-1, -1 elsewhere."""
    H, W = mask.shape
    idx = np.full(mask.shape, -1, dtype=np.int64)
    n = int(mask.sum())
    idx[mask] = np.arange(n)
    rows, cols = [], []
    for a, b, j in ((idx[:, :-1], idx[:, 1:], jump_h), (idx[:-1, :], idx[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & ~j
        rows.append(a[m])
        cols.append(b[m])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    out = np.full(mask.shape, -1, dtype=np.int64)
    out[mask] = comp
    return out


def _adjacency(labels: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray) -> set[tuple[int, int]]:
    pairs = []
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & (a != b) & ~j
        if m.any():
            pa, pb = a[m].astype(np.int64), b[m].astype(np.int64)
            pairs.append(np.stack([np.minimum(pa, pb), np.maximum(pa, pb)], axis=1))
    if not pairs:
        return set()
    u = np.unique(np.concatenate(pairs), axis=0)
    return {(int(p), int(q)) for p, q in u}


def _dominant(counts: np.ndarray, min_pixels: int) -> int:
    """The class holding at least 60 % of a patch's classified pixels (0 when none or too few pixels)."""
    cc = counts[1:]
    n = int(cc.sum())
    if n < min_pixels:
        return 0
    k = int(np.argmax(cc))
    return k + 1 if cc[k] >= 0.6 * n else 0


def _class_boundary(ca: np.ndarray, cb: np.ndarray, min_pixels: int) -> bool:
    """True when one patch is clearly cylindrical and the other clearly doubly curved (elliptic or
    hyperbolic): a G1 join such as pipe / elbow or tank / dome, which a quadric can bridge within the noise.
    Planar-dominated patches (curvature below the noise: large radii) may join anything the fit accepts."""
    a, b = _dominant(ca, min_pixels), _dominant(cb, min_pixels)
    return {a, b} in ({SurfaceType.CYLINDRICAL, SurfaceType.ELLIPTIC},
                      {SurfaceType.CYLINDRICAL, SurfaceType.HYPERBOLIC})


@dataclass(frozen=True)
class _FitPart:
    """A patch's merge-test sample (its points, rays and sigmas) with its centroid and centred scatter: the
    total-least-squares plane of a union of parts follows from these moments alone."""

    n: int
    XU: np.ndarray  # (n, 6): points and unit rays
    S: np.ndarray  # (n,) sigmas
    mean: np.ndarray
    scatter: np.ndarray

    @classmethod
    def of(cls, idx: np.ndarray, st: _State) -> _FitPart:
        X = st.X[idx]
        mean = X.mean(axis=0) if len(X) else np.zeros(3)
        d = X - mean
        return cls(len(X), np.hstack([X, st.U[idx]]), st.S[idx], mean, d.T @ d)

    @classmethod
    def batch(cls, subs: dict[int, np.ndarray], st: _State) -> dict[int, _FitPart]:
        """:meth:`of` for every (non-empty) sample of ``subs`` at once."""
        keys = list(subs)
        cnt = np.array([subs[k].size for k in keys])
        if cnt.size == 0 or cnt.min() == 0:
            return {k: cls.of(subs[k], st) for k in keys}
        ix = np.concatenate([subs[k] for k in keys])
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        XU = np.hstack([st.X[ix], st.U[ix]])
        S = st.S[ix]
        mean = _group_sums(XU[:, :3], starts) / cnt[:, None]
        scatter = _group_grams(XU[:, :3] - np.repeat(mean, cnt, axis=0), starts, cnt)
        return {k: cls(int(c), XU[s:s + c], S[s:s + c], mean[g], scatter[g])
                for g, (k, s, c) in enumerate(zip(keys, starts.tolist(), cnt.tolist(), strict=True))}

    def chi2(self, normal: np.ndarray, offset: float) -> float:
        """Sum of squared ray z-residuals (as in :func:`_plane_fits`) to the plane ``normal . x = offset``."""
        f = self.XU[:, :3] @ normal
        g = self.XU[:, 3:] @ normal
        z = (f - offset) / (np.maximum(np.abs(g), _MIN_GRAZING) * self.S)  # valid pixels: sigma > 0
        return float(z @ z)


def _plane_union_rms(pairs: list[tuple[_FitPart, _FitPart | None]]) -> list[tuple[float, float]]:
    """For each ``(large, small)``: the RMS ray z-residual (as in :func:`_plane_fits`) of the total-least-squares
    plane of both parts together, over all their points and over ``small``'s (``small`` None: ``large`` alone,
    both RMS over its points); inf for fewer than 3 points (NaN residuals, impossible for valid pixels, would
    make them NaN: never accepted). The planes' eigen-decompositions are done in one batch."""
    out = [(float("inf"), float("inf"))] * len(pairs)
    todo, means, scatters = [], [], []
    for i, (large, small) in enumerate(pairs):
        if small is None:
            if large.n >= 3:
                todo.append(i)
                means.append(large.mean)
                scatters.append(large.scatter)
            continue
        n = large.n + small.n
        if n < 3 or small.n == 0:
            continue
        d = large.mean - small.mean
        todo.append(i)
        means.append((large.n * large.mean + small.n * small.mean) / n)
        scatters.append(large.scatter + small.scatter + (large.n * small.n / n) * np.outer(d, d))
    if not todo:
        return out
    normals = np.linalg.eigh(np.array(scatters))[1][:, :, 0]
    for i, mean, normal in zip(todo, means, normals, strict=True):
        large, small = pairs[i]
        offset = float(mean @ normal)
        if small is None:
            c = large.chi2(normal, offset)
            out[i] = (float(np.sqrt(c / large.n)), float(np.sqrt(c / large.n)))
        else:
            c_small = small.chi2(normal, offset)
            out[i] = (float(np.sqrt((large.chi2(normal, offset) + c_small) / (large.n + small.n))),
                      float(np.sqrt(c_small / small.n)))
    return out


def _merge(labels: np.ndarray, st: _State, jump_h, jump_v) -> np.ndarray:
    """Greedy best-first merging of adjacent patches whose union fits one surface (returns new labels).

    A pair merges when the union's fit (plane when both patches are planar, by class or by fit; quadric
    otherwise) has an RMS range residual within ``merge_k`` sigma over the union and within ``1.5 merge_k``
    over the smaller part (a small fragment of another surface is not hidden by the larger patch's many good
    points). With ``curved_planar_merge`` a planar pair that no plane fits is tried as a quadric, which must
    not be a plane pair (:func:`_is_plane_pair`: two faces at a crease). Costs are computed in batches and
    re-evaluated lazily when a patch has changed since its pair was queued. With
    ``class_min_pixels`` set, two patches whose dominant curvature classes are cylindrical and doubly curved
    never merge (:func:`_class_boundary`): at a tangent join (a pipe and its elbow, a tank and its dome) the
    class change is the only cue.
    """
    groups = _groups(labels)
    if len(groups) < 2:
        return labels
    thr = st.params.merge_k
    nmax = st.params.merge_fit_points
    members = dict(groups)
    subs = {k: _subsample(v, nmax) for k, v in members.items()}
    counts = {k: np.bincount(st.hk[v], minlength=5) for k, v in members.items()}
    planar_class = {k: _is_planar_counts(c) for k, c in counts.items()}
    parts = _FitPart.batch(subs, st)

    flats: dict[int, bool] = {}  # whether a plane fits the patch, computed when needed

    def update_flats(keys) -> None:
        new = [k for k in keys if k not in flats]
        for k, (rms, _) in zip(new, _plane_union_rms([(parts[k], None) for k in new]), strict=True):
            flats[k] = rms <= thr

    update_flats(list(members))
    version = dict.fromkeys(members, 0)
    nbrs: dict[int, set[int]] = {k: set() for k in members}
    for a, b in _adjacency(labels, jump_h, jump_v):
        nbrs[a].add(b)
        nbrs[b].add(a)

    def costs(pairs: list[tuple[int, int]]) -> list[float]:
        """RMS residual of the union fit of each pair (inf when the smaller part does not fit it), all fitted
        in one batch."""
        out = [float("inf")] * len(pairs)
        update_flats(sorted({k for pair in pairs for k in pair}))
        todo, ordered, planar, n_large = [], [], [], []
        curved = []  # (index in todo) of the unions fitted by a quadric, in one batch
        flat_pairs = []  # (index in pairs, larger, smaller) of the unions fitted by a plane, in one batch
        for i, (a, b) in enumerate(pairs):
            if st.params.class_min_pixels and _class_boundary(counts[a], counts[b], st.params.class_min_pixels):
                continue
            if subs[a].size < subs[b].size:
                a, b = b, a
            todo.append(i)
            ordered.append((a, b))
            n_large.append(subs[a].size)
            # two planes (by class, or by fit: crease pixels make a face look curved) merge only as one
            # plane, never as the plane pair a general quadric fits exactly
            planar.append((planar_class[a] and planar_class[b]) or (flats[a] and flats[b]))
            if planar[-1] or subs[a].size + subs[b].size < 10:  # (< 10 points: a plane, as in _quick_fits)
                flat_pairs.append((i, a, b))
            else:
                curved.append(len(todo) - 1)
        flat_rms = _plane_union_rms([(parts[a], parts[b]) for _, a, b in flat_pairs])
        for (i, _, _), (rms_all, rms_small) in zip(flat_pairs, flat_rms, strict=True):
            if rms_small <= 1.5 * thr:
                out[i] = rms_all
        # two planar-looking pieces of one gently curved surface (a large pipe close to a noisy sensor) that
        # no plane fits are retried as a quadric, which must not be the plane pair of two faces at a crease
        retry = [j for j in range(len(todo))
                 if st.params.curved_planar_merge and planar[j] and not out[todo[j]] <= thr]
        if curved or retry:
            # the unions' pixels (larger part first) are gathered only for the quadric fits
            unions = {j: np.concatenate([subs[ordered[j][0]], subs[ordered[j][1]]]) for j in curved + retry}
            Pq, zq = _quick_fits([unions[j] for j in curved + retry], np.zeros(len(curved) + len(retry), bool), st)
            for j, z in zip(curved, zq, strict=False):
                if _rms(z[n_large[j]:]) <= 1.5 * thr:
                    out[todo[j]] = _rms(z)
            for j, p, z in zip(retry, Pq[len(curved):], zq[len(curved):], strict=True):
                if _rms(z) <= thr and _rms(z[n_large[j]:]) <= 1.5 * thr and \
                        not _is_plane_pair(p, st.X[unions[j]], _PLANE_PAIR_TOL):
                    out[todo[j]] = _rms(z)
        return out

    heap: list[tuple[float, int, int, int, int]] = []

    def push(pairs: list[tuple[int, int]]) -> None:
        pairs = [(min(a, b), max(a, b)) for a, b in pairs]
        for (a, b), c in zip(pairs, costs(pairs), strict=True):
            if c <= thr:
                heapq.heappush(heap, (c, a, b, version[a], version[b]))

    push([(a, b) for a in nbrs for b in sorted(nbrs[a]) if a < b])
    parent = np.arange(max(members) + 1)
    while heap:
        _, a, b, va, vb = heapq.heappop(heap)
        if a not in members or b not in members:
            continue
        if va != version[a] or vb != version[b]:
            push([(a, b)])
            continue
        members[a] = np.concatenate([members[a], members.pop(b)])
        members[a].sort(kind="stable")  # two sorted runs: a linear merge
        subs[a] = _subsample(members[a], nmax)
        subs.pop(b)
        parts[a] = _FitPart.of(subs[a], st)
        parts.pop(b)
        counts[a] = counts[a] + counts.pop(b)
        planar_class[a] = _is_planar_counts(counts[a])
        planar_class.pop(b)
        flats.pop(b)
        flats.pop(a)
        version[a] += 1
        parent[b] = a
        old = nbrs[a]
        nb_b = nbrs.pop(b)
        nbrs[a] = (old | nb_b) - {a, b}
        for q in nb_b - {a}:
            nbrs[q].discard(b)
            nbrs[q].add(a)
        push([(a, q) for q in sorted(nb_b - {a}) if q not in old])
    while True:  # follow each label's chain of merges to the patch that absorbed it last
        nxt = parent[parent]
        if np.array_equal(nxt, parent):
            break
        parent = nxt
    out = labels.copy()
    m = out >= 0
    out[m] = parent[out[m]]
    return out


def _unique_pairs(pairs: np.ndarray, return_counts: bool = False):
    """``np.unique(pairs, axis=0)`` (sorted rows; with their counts) of integer pairs (N, 2) whose entries
    are >= -2, through one integer key per row (much faster than the structured sort of ``axis=0``)."""
    pairs = np.asarray(pairs, np.int64)
    if pairs.size == 0:
        empty = np.zeros((0, 2), np.int64)
        return (empty, np.zeros(0, np.int64)) if return_counts else empty
    base = int(pairs.max()) + 3
    key, counts = np.unique(pairs[:, 0] * base + (pairs[:, 1] + 2), return_counts=True)
    out = np.stack([key // base, key % base - 2], axis=1)
    return (out, counts) if return_counts else out


def _merge_enclosed(labels: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                    min_pixels: int) -> np.ndarray:
    """Merge small patches lying wholly inside one other patch.

    A patch is enclosed by q when every pixel next to it (4-neighbours) is q, an unlabelled return, or on
    the far side of a jump; the image border and pixels without a return count as other neighbours. Small
    enclosed patches (fewer than ``min_pixels``) join q.
    """
    Hh, Ww = labels.shape
    # per direction: neighbour label, with -3 = transparent (unlabelled return or across a jump)
    across = []
    for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
        j = np.zeros((Hh, Ww), bool)
        if dc == -1:
            j[:, 1:] = jump_h
        elif dc == 1:
            j[:, :-1] = jump_h
        elif dr == -1:
            j[1:, :] = jump_v
        else:
            j[:-1, :] = jump_v
        across.append(j)
    for _ in range(10):
        pad = np.full((Hh + 2, Ww + 2), -2, dtype=np.int64)  # -2: border or no return
        lab = np.where(valid, labels, -2).astype(np.int64)
        lab[lab == -1] = -3
        pad[1:-1, 1:-1] = lab
        centre = pad[1:-1, 1:-1]
        pairs = []
        for nb, j in zip((pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]), across, strict=True):
            m = (centre >= 0) & (nb != centre) & (nb != -3) & ~j
            pairs.append(np.stack([centre[m], nb[m]], axis=1))
        pairs = np.concatenate(pairs)
        if pairs.size == 0:
            return labels
        pairs = _unique_pairs(pairs)
        sizes = np.bincount(labels[labels >= 0])
        owner, first, n_other = np.unique(pairs[:, 0], return_index=True, return_counts=True)
        changed = False
        remap = np.arange(sizes.size)
        for p, f, k in zip(owner, first, n_other, strict=True):
            q = int(pairs[f, 1])
            if k == 1 and q >= 0 and sizes[p] < min_pixels and sizes[q] > sizes[p] and remap[q] == q:
                remap[p] = q
                changed = True
        if not changed:
            return labels
        m = labels >= 0
        labels = labels.copy()
        labels[m] = remap[labels[m]]
    return labels


def _attach_isolated(labels: np.ndarray, st: _State, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Attach small patches cut off from everything by jumps to a patch across the jump whose surface fits.

    Grazing limb samples of a sphere or pipe are often separated from the rest of their surface by range
    steps larger than the jump allowance; they cannot grow back, but they lie on that surface (RMS range
    residual within ``grow_k`` sigma of its fit). A small object in front of a wall does not fit the wall
    and stays on its own.
    """
    pairs_j, pairs_n = [], []
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & (a != b)
        for dst, sel in ((pairs_j, m & j), (pairs_n, m & ~j)):
            dst.append(np.stack([a[sel], b[sel]], axis=1))
            dst.append(np.stack([b[sel], a[sel]], axis=1))
    across = _unique_pairs(np.concatenate(pairs_j))
    linked = np.unique(np.concatenate(pairs_n)[:, 0])
    if across.size == 0:
        return labels
    groups = _groups(labels)
    small = {k for k, v in groups.items() if v.size < st.params.min_patch_pixels}
    remap = np.arange(int(labels.max()) + 1)
    isolated = sorted(small - set(linked.tolist()))
    cands = {p: [int(q) for q in across[across[:, 0] == p, 1] if groups[int(q)].size > groups[p].size]
             for p in isolated}
    fits = _quick_fits_of(groups, sorted({q for c in cands.values() for q in c}), st)
    tests = [(p, q) for p in isolated for q in cands[p]]
    rms_of = {}
    if tests:  # the RMS residual of each isolated patch to each candidate's surface, in one pass
        P = np.array([fits[q] for _, q in tests])
        idx = np.concatenate([groups[p] for p, _ in tests])
        sizes = np.array([groups[p].size for p, _ in tests])
        z = _pixel_residuals(P, np.repeat(np.arange(len(tests)), sizes), st.X[idx], st.U[idx], st.S[idx])
        ms = np.add.reduceat(z * z, np.concatenate([[0], np.cumsum(sizes)[:-1]])) / sizes
        rms_of = dict(zip(tests, np.sqrt(ms).tolist(), strict=True))
    for p in isolated:
        best, best_rms = -1, st.params.grow_k
        for q in cands[p]:
            if rms_of[(p, q)] <= best_rms:
                best, best_rms = q, rms_of[(p, q)]
        if best >= 0 and remap[best] == best:
            remap[p] = best
    if np.all(remap == np.arange(remap.size)):
        return labels
    out = labels.copy()
    m = out >= 0
    out[m] = remap[out[m]]
    return out


def _border_pairs(labels: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique ordered pairs (a, b), a != b, of labels sharing a non-jump 4-border, with the border length."""
    parts = []
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & (a != b) & ~j
        pa, pb = a[m].astype(np.int64), b[m].astype(np.int64)
        parts += [np.stack([pa, pb], axis=1), np.stack([pb, pa], axis=1)]
    pairs = np.concatenate(parts) if parts else np.zeros((0, 2), np.int64)
    if pairs.size == 0:
        return pairs, np.zeros(0, np.int64)
    return _unique_pairs(pairs, return_counts=True)


def _absorb_fragments(labels: np.ndarray, st: _State, jump_h: np.ndarray, jump_v: np.ndarray,
                      min_pixels: int, max_rms: float, rounds: int = 3) -> np.ndarray:
    """Merge fragments (fewer than ``min_pixels``) into the bordering patch whose surface fits them best.

    A fragment joins a larger patch it touches without a jump when the RMS range residual of its pixels to
    that patch's fit is within ``max_rms`` sigma (the neighbour with the longest common border among those
    that fit). Fragments that fit no neighbour (a small object, a transition band between two surfaces)
    stay as they are. Hoover's metric counts any fragment wholly inside a truth region as an
    over-segmentation of it, so the pieces of one surface cut out by misclassified curvature must go back.
    """
    for _ in range(rounds):
        groups = _groups(labels)
        if len(groups) < 2:
            return labels
        sizes = np.zeros(max(groups) + 1, np.int64)
        for k, v in groups.items():
            sizes[k] = v.size
        pairs, blen = _border_pairs(labels, jump_h, jump_v)
        if pairs.size == 0:
            return labels
        sel = (sizes[pairs[:, 0]] < min_pixels) & (sizes[pairs[:, 1]] > sizes[pairs[:, 0]])
        pairs, blen = pairs[sel], blen[sel]
        if pairs.size == 0:
            return labels
        # the fits of every neighbour a fragment may join
        fits = _quick_fits_of(groups, [int(q) for q in np.unique(pairs[:, 1])], st)
        remap = np.arange(sizes.size)
        order = np.lexsort((-blen, pairs[:, 0]))
        pairs, blen = pairs[order], blen[order]
        starts = np.flatnonzero(np.r_[True, pairs[1:, 0] != pairs[:-1, 0]])
        ends = np.r_[starts[1:], len(pairs)]
        for s0, e0 in zip(starts, ends, strict=True):
            p = int(pairs[s0, 0])
            idx = groups[p]
            for q in pairs[s0:e0, 1]:
                q = int(q)
                if remap[q] != q:
                    continue
                _, _, z = ray_residuals(fits[q], st.X[idx], st.S[idx])
                if _rms(np.where(np.isfinite(z), z, np.inf)) <= max_rms:
                    remap[p] = q
                    break
        if np.all(remap == np.arange(remap.size)):
            return labels
        labels = labels.copy()
        m = labels >= 0
        labels[m] = remap[labels[m]]
    return labels


# --------------------------------------------------------------------------------------------- main entry


def _empty(shape: tuple[int, int], hk=None, Hc=None, Kc=None, sH=None, sK=None, nrm=None, edges=None):
    nan = np.full(shape, np.nan)
    return Segmentation(
        labels=np.full(shape, -1, dtype=np.int32),
        hk_class=np.zeros(shape, np.int8) if hk is None else hk,
        H=nan.copy() if Hc is None else Hc,
        K=nan.copy() if Kc is None else Kc,
        sigma_H=nan.copy() if sH is None else sH,
        sigma_K=nan.copy() if sK is None else sK,
        normals=np.full(shape + (3,), np.nan) if nrm is None else nrm,
        edges=np.zeros(shape, np.uint8) if edges is None else edges,
        patches=(),
    )


class _Laps:
    """Process time of consecutive steps, added to ``into[name]`` in seconds (nothing when ``into`` is None)."""

    def __init__(self, into: dict[str, float] | None):
        self.into = into
        self.t = time.process_time()

    def __call__(self, name: str) -> None:
        if self.into is not None:
            t = time.process_time()
            self.into[name] = self.into.get(name, 0.0) + t - self.t
            self.t = t


def segment(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams | None = None,
            steps: dict[str, float] | None = None) -> Segmentation:
    """Segment an organised range image into H-K surface patches with plane / quadric fits.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame (x right, y down, z forward)
        NaN where there is no return.
    sigma : ndarray of shape (H, W), metres
        Range-noise sigma along the ray per pixel (NaN where no return); floored at ``sigma_floor_m``.
    params : SegmentationParams, optional
    steps : dict, optional
        Receives the process time (s) of each step, added to what it holds under the step's name (``edges``,
        ``curvature``, ``seeds``, ``growing``, ``merging`` on the segmentation grid, then ``full resolution``,
        ``merging at full resolution``, ``splits``, ``reassignment``, ``peel``, ``final fits``): where a
        frame's time goes, for ``python -m harness.bench_segmentation --steps``.

    Returns
    -------
    Segmentation
        Empty (no patches, all labels -1) for an image without usable returns (e.g. all NaN, 1x1).

    Raises
    ------
    ValueError
        For arrays of the wrong shape or negative sigma.
    """
    params = SegmentationParams() if params is None else params
    lap = _Laps(steps)
    pts, sig = _check_inputs(points, sigma)
    shape = sig.shape
    # finite and > 0 where every coordinate is finite and one is not 0 (a range beyond 1e154 m, whose square
    # overflows, counts as no return)
    r2 = np.einsum("ijk,ijk->ij", pts, pts)
    valid = np.isfinite(r2) & (r2 > 0) & np.isfinite(sig)
    if not valid.any():
        return _empty(shape)
    sig = np.where(valid, np.maximum(sig, params.sigma_floor_m), np.nan)
    pts = np.where(valid[..., None], pts, np.nan)
    rng = np.where(valid, np.sqrt(r2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rays = pts / rng[..., None]
    declared = sig
    scale = None
    angles = ray_angles(rays)
    jump_h, jump_v = jump_pairs(rng, sig, rays, params.jump_k, params.jump_tan, angles)
    if params.calibrate_noise:
        scale = noise_scale(rng, sig, valid, jump_h, jump_v, params.window, params.max_noise_scale)
        sig = sig * scale
        jump_h, jump_v = jump_pairs(rng, sig, rays, params.jump_k, params.jump_tan, angles)
    d = params.step(shape)
    if params.split_seeds is None:
        params = replace(params, split_seeds=d >= 2)
    st_full = _State(X=pts.reshape(-1, 3), U=rays.reshape(-1, 3), S=sig.ravel(), hk=np.zeros(0, np.int64),
                     params=params)
    lap("edges")
    if d == 1:
        out = _segment_grid(pts, sig, valid, rng, rays, jump_h, jump_v, params, lap)
        if out is None:
            return _curvature_only(pts, sig, valid, jump_h, jump_v, params)
        labels, hk, cur, crease = out
        st_full.hk = hk.ravel().astype(np.int64)
    else:
        sl = (slice(0, None, d), slice(0, None, d))
        pd, sd, vd, rd, ud = pts[sl], sig[sl], valid[sl], rng[sl], rays[sl]
        jhd, jvd = jump_pairs(rd, sd, ud, params.jump_k, params.jump_tan)
        lap("edges")
        out = _segment_grid(pd, sd, vd, rd, ud, jhd, jvd, params.scaled(d), lap)
        if out is None:
            return _curvature_only(pts, sig, valid, jump_h, jump_v, params)
        labels_d, hk_d, cur_d, crease_d = out
        up = _upsampler(shape, d)
        hk = up(hk_d)
        cur = CurvatureImages(*(up(a) for a in (cur_d.H, cur_d.K, cur_d.sigma_H, cur_d.sigma_K, cur_d.normals,
                                                 cur_d.sigma_normal)))
        crease = up(crease_d)
        st_full.hk = hk.ravel().astype(np.int64)
        links = _neighbour_links(shape, valid, jump_h, jump_v)  # (the full-resolution grid's, for both steps)
        labels = _refine_full(up(labels_d), valid, st_full, links, jump_h, jump_v, params, d)
        lap("full resolution")
        labels = _merge(labels, st_full, jump_h, jump_v)  # (before the cuts below, which it would undo)
        lap("merging at full resolution")
        split = _split_plane_pairs(labels, st_full, params, cut_faces=True)
        if split is not labels:  # a split-off side too small to stand alone goes to the face it belongs to
            labels = _absorb_fragments(split, st_full, jump_h, jump_v, params.min_region_pixels, params.absorb_k)
        if params.axis_split_pixels is not None:
            labels = _split_along_axis(labels, st_full, cur.normals.reshape(-1, 3), params)
        lap("splits")
        if params.reassign_rounds:
            labels = _reassign(labels, st_full, links, jump_h, jump_v, params.reassign_rounds,
                               params.reassign_margin)
        lap("reassignment")
    edges = _edge_image(shape, jump_h, jump_v)
    edges[crease] |= np.uint8(EdgeType.CREASE)
    labels = _peel_weak(labels, params.min_region_pixels, jump_h, jump_v)
    lap("peel")
    labels, patches = _finalise(labels, st_full, params, declared.ravel())
    lap("final fits")
    return Segmentation(labels, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges, patches, scale)


def _split_along_axis(labels: np.ndarray, st: _State, normals: np.ndarray, params: SegmentationParams,
                      passes: int = 3) -> np.ndarray:
    """Cut curved patches along their axis where the radius changes.

    Under strong noise a pipe, its reducer and the next pipe (or a pipe and its elbow) join smoothly enough
    for one quadric to fit their union within the noise, and the curvature classes cannot tell a 5 deg cone
    from a cylinder. Along the axis of a cylinder fitted to the patch, the median distance of its points to
    the axis (per slice half a radius long) is constant over a pipe, linear over a reducer, and turns at a
    join: the patch is cut there (:func:`_axial_pieces`). Applied ``passes`` times, so that a piece holding
    a reducer and a pipe is cut again.
    """
    out = labels
    for _ in range(passes):
        nxt = int(out.max()) + 1
        changed = False
        big = [idx for idx in _groups(out).values() if idx.size >= params.axis_split_pixels]
        # curved: no plane fits it (the H-K classes are no guide: under strong noise a pipe's are mostly planar)
        samples = [_subsample(v, params.max_fit_points) for v in big]
        _, zp = _quick_fits(samples, np.ones(len(big), bool), st)
        curved = [k for k in range(len(big)) if not _rms(zp[k]) <= params.merge_k]
        _, zq = _quick_fits([samples[k] for k in curved], np.zeros(len(curved), bool), st)
        for k, z in zip(curved, zq, strict=True):
            idx = big[k]
            # one quadric fits the patch within noise: a sphere or a dome is not cut into pipes
            side = _axial_pieces(st.X[idx], st.S[idx], normals[idx], params.min_region_pixels,
                                 several_axes=not _rms(z) <= params.merge_k)
            if side is None:
                continue
            if out is labels:
                out = labels.copy()
            out.reshape(-1)[idx[side == 1]] = nxt
            nxt += 1
            changed = True
        if not changed:
            break
    return out


def _axial_pieces(x: np.ndarray, s: np.ndarray, n: np.ndarray, min_pixels: int, fit_points: int = 2000,
                  flat_fraction: float = 0.03, min_bins: int = 3, several_axes: bool = True) -> np.ndarray | None:
    """Two pieces (0 and 1 per point) of a curved patch along its axis, or None when it is one surface.

    The axis is the direction the normals turn about (shared by a pipe and its reducer); the patch is cut
    into slices half a radius long along it (longer on a far, thin pipe, so that they hold ``_SLICE_POINTS``
    points on average: its slices had 5-10, and none was used). A
    cylinder's slices keep one median distance to the axis, a cone's change it linearly (so does a cylinder's
    under a slightly tilted axis), so the profile of one surface is a line, within
    ``max(3 sigma of the median, flat_fraction * radius)`` per slice. A profile that is not is cut where two
    lines, fitted on either side, explain it best, or, when no two do, at the first cut of the three lines
    that do (a reducer between two pipes: on the default suite's Kinect-like frames, correct detection 0.554
    -> 0.594); each side needs ``min_bins`` slices and at least ``min_pixels`` points and a tenth of the
    patch. A patch whose profile about the axis of a cylinder fitted
    to it is one line is not cut (a pipe whose normals gave a slightly tilted axis).

    ``x`` points (N, 3), ``s`` their range sigmas (N,), ``n`` their unit normals (N, 3) (NaN where undefined).
    """
    ok = np.isfinite(n).all(axis=1)
    if ok.sum() < 20:
        return None
    w = np.linalg.eigvalsh(n[ok].T @ n[ok])
    if w[1] < 0.05 * w.sum():
        return None  # the normals barely turn (a plane)
    if w[0] > 0.05 * w.sum():
        # the normals do not turn about one axis: a doubly curved patch, or two pipes and their elbow
        return _dominant_cylinder(x, s, n, ok, min_pixels, fit_points) if several_axes else None
    # the axis: the direction on which the normals' projection is most nearly constant (zero on a cylinder,
    # the sine of the half-angle on a cone; the normals' scatter itself tilts on a partly seen cone)
    axis = np.linalg.eigh(np.cov(n[ok].T))[1][:, 0]
    e1, e2 = perpendicular_basis(axis)
    sub = _subsample(np.arange(len(x)), fit_points)
    P = np.stack([x[sub] @ e1, x[sub] @ e2], axis=1)  # the section: an algebraic circle across the axis
    sol = np.linalg.lstsq(np.column_stack([2.0 * P, np.ones(len(P))]), np.sum(P**2, axis=1), rcond=None)[0]
    r2 = sol[2] + sol[:2] @ sol[:2]
    if not r2 > 0:
        return None
    centre, radius = sol[0] * e1 + sol[1] * e2, float(np.sqrt(r2))
    side = _axial_cut(x, s, centre, axis, radius, min_bins, flat_fraction)
    if side is None or min(np.sum(side == 0), np.sum(side == 1)) < max(min_pixels, len(x) // 10):
        return None
    # the normals' axis of a noisy pipe may be a degree off, which bends its profile: a pipe whose fitted
    # cylinder's profile is one line is one surface
    cyl = fit_cylinder(x[sub], s[sub], init=(centre, axis, radius), max_points=600, huber=1.5, max_iter=10)
    if cyl.ok and _axial_cut(x, s, cyl.point, cyl.axis, cyl.radius, min_bins, flat_fraction) is None:
        return None
    return side


def _dominant_cylinder(x: np.ndarray, s: np.ndarray, n: np.ndarray, ok: np.ndarray, min_pixels: int,
                       fit_points: int, keep: float = 0.6, rounds: int = 4, k: float = 3.0) -> np.ndarray | None:
    """Two pieces (0 per point on the patch's dominant cylinder, 1 elsewhere) of a patch whose normals turn
    about more than one axis, or None.

    Two pipes joined by an elbow, merged under strong noise: the normals of each pipe lie on a great circle
    about its axis. The axis of the most populous circle comes from the normals' scatter, trimmed ``rounds``
    times to the ``keep`` fraction nearest the circle; the pipe's section across it from the points and
    normals (trimmed likewise), then a cylinder fitted from there, which takes the points within ``k`` sigma
    of it. None unless that axis holds a clean circle, the fit succeeds and both pieces hold at least
    ``min_pixels`` points and a tenth of the patch. ``ok``: the points whose normal is defined.
    """
    nn = n[ok]
    near = np.ones(len(nn), bool)
    for _ in range(rounds):
        axis = np.linalg.eigh(nn[near].T @ nn[near])[1][:, 0]
        r = np.abs(nn @ axis)
        near = r <= np.quantile(r, keep)
    w = np.linalg.eigvalsh(nn[near].T @ nn[near])
    if w[0] > 0.05 * w.sum() * keep or w[1] < 0.05 * w.sum():
        return None  # no pipe among the normals: a doubly curved surface (a tank's dome, an elbow alone)
    on = np.flatnonzero(ok)[near]
    sub = on[_subsample(np.arange(on.size), fit_points)]
    # the section across the axis: each point of the pipe lies its radius along its normal from the pipe's
    # centre (p = c + R n, linear in c and R; the other pipe's points, seen across, do not); trimmed
    # ``rounds`` times to the points that agree best, it starts the cylinder fit
    e1, e2 = perpendicular_basis(axis)
    P = np.stack([x[sub] @ e1, x[sub] @ e2], axis=1)
    N = np.stack([n[sub] @ e1, n[sub] @ e2], axis=1)
    use = np.ones(len(P), bool)
    for _ in range(rounds):
        m = int(use.sum())
        A = np.zeros((2 * m, 3))
        A[0::2, 0] = A[1::2, 1] = 1.0
        A[:, 2] = N[use].reshape(-1)
        cx, cy, radius = np.linalg.lstsq(A, P[use].reshape(-1), rcond=None)[0]
        off = np.linalg.norm(P - [cx, cy] - radius * N, axis=1)
        use = off <= max(np.quantile(off, keep), k * float(np.median(s[sub])))
    if not radius > 0:
        return None
    sub = sub[use]
    cyl = fit_cylinder(x[sub], s[sub], init=(cx * e1 + cy * e2, axis, float(radius)), max_points=600, huber=1.5,
                       max_iter=10)
    if not cyl.ok:
        return None
    q = x - cyl.point
    t = q @ cyl.axis
    dist = np.abs(np.linalg.norm(q - np.outer(t, cyl.axis), axis=1) - cyl.radius)
    side = (dist > k * s).astype(np.int64)
    if min(np.sum(side == 0), np.sum(side == 1)) < max(min_pixels, len(x) // 10):
        return None
    return side


_SLICE_POINTS = 25  # points per slice of an axial profile on average, at least (a slice counts with 20)


def _axial_cut(x: np.ndarray, s: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float, min_bins: int,
               flat_fraction: float) -> np.ndarray | None:
    """The cut of :func:`_axial_pieces` about the axis through ``point``: side (0 or 1) per point, or None."""
    q = x - point
    t = q @ axis
    rho = np.linalg.norm(q - np.outer(t, axis), axis=1)
    # slices half a radius long, or longer on a far thin pipe: _SLICE_POINTS points each on average
    step = max(radius / 2.0, (t.max() - t.min()) * _SLICE_POINTS / len(x))
    b = np.floor((t - t.min()) / step).astype(np.int64)
    nb = int(b.max()) + 1
    cnt = np.bincount(b, minlength=nb)
    full = np.flatnonzero(cnt >= 20)
    if full.size < 2 * min_bins:
        return None
    order = np.lexsort((rho, b))
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    med = rho[order[start[full] + cnt[full] // 2]]
    tol = np.maximum(3.0 * 1.25 * np.bincount(b, weights=s, minlength=nb)[full] / cnt[full] ** 1.5,
                     flat_fraction * radius)

    m = full.size
    whole = _line_misfit(full, med, cnt[full], tol, np.array([m]))[0]
    if whole <= 1.0:
        return None
    w = cnt[full]
    cuts = np.arange(min_bins, m - min_bins + 1)
    if cuts.size == 0:
        return None
    head = _line_misfit(full, med, w, tol, cuts)  # of the bins before each cut
    tail = _line_misfit(full[::-1], med[::-1], w[::-1], tol[::-1], m - cuts)  # of the bins from each cut on
    costs = np.maximum(head, tail)
    j = int(np.argmin(costs))
    if costs[j] < whole / 2:
        return (b >= full[cuts[j]]).astype(np.int64)
    # a pipe, its reducer and the next pipe: three lines (flat, ramp, flat) where no two do. Among the pairs
    # of cuts whose largest deviation is small enough, the one of least squared misfit (the largest deviation
    # alone does not place the joins: a kink within tolerance passes for a line); the first cut is returned,
    # the next pass of _split_along_axis cuts the rest
    sse = _line_sse(full, med, 1.0 / tol**2)
    best, at = np.inf, None
    for i, c1 in enumerate(cuts):
        c2 = cuts[cuts >= c1 + min_bins]
        if c2.size == 0:
            break
        mid = _line_misfit(full[c1:], med[c1:], w[c1:], tol[c1:], c2 - c1)
        ok = np.maximum(np.maximum(head[i], mid), tail[np.searchsorted(cuts, c2)]) < whole / 2
        if not ok.any():
            continue
        total = sse(0, c1) + sse(c1, c2[ok]) + sse(c2[ok], m)
        k = int(np.argmin(total))
        if total[k] < best:
            best, at = float(total[k]), c1
    return None if at is None else (b >= full[at]).astype(np.int64)


def _line_sums(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Cumulative weighted moments ``(w, w x, w y, w x², w x y, w y²)`` of the points, shape (6, N + 1) with a
    leading zero column: the sums over ``[i, j)`` are ``c[:, j] - c[:, i]``."""
    x = x.astype(np.float64)
    return np.concatenate([np.zeros((6, 1)), np.cumsum(np.stack([w, w * x, w * y, w * x * x, w * x * y, w * y * y]),
                                                        axis=1)], axis=1)


def _line_of_sums(s0, sx, sy, sxx, sxy):
    """``(slope, intercept)`` of the weighted least-squares line from its moments (arrays broadcast)."""
    slope = (s0 * sxy - sx * sy) / (s0 * sxx - sx * sx)
    return slope, (sy - slope * sx) / s0


def _line_sse(x: np.ndarray, y: np.ndarray, w: np.ndarray):
    """A function ``sse(i, j)`` (broadcasting over integer arrays): the weighted squared misfit of
    ``y[i:j]`` to its weighted least-squares line in ``x``, from cumulative sums."""
    c = _line_sums(x, y, w)

    def sse(i, j):
        i, j = np.broadcast_arrays(np.asarray(i), np.asarray(j))
        s0, sx, sy, sxx, sxy, syy = c[:, j] - c[:, i]
        slope, icpt = _line_of_sums(s0, sx, sy, sxx, sxy)
        return np.maximum(syy - icpt * sy - slope * sxy, 0.0)

    return sse


def _line_misfit(x: np.ndarray, y: np.ndarray, w: np.ndarray, tol: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """For each ``e`` in ``ends``: the largest deviation, in ``tol`` units, of ``y[:e]`` from its line fitted by
    least squares weighted by ``w`` (counts), all prefixes at once from cumulative sums."""
    x = x.astype(np.float64)
    slope, icpt = _line_of_sums(*_line_sums(x, y, w)[:5, ends])
    dev = np.abs(icpt[:, None] + slope[:, None] * x[None, :] - y[None, :]) / tol[None, :]
    return np.where(np.arange(len(x))[None, :] < ends[:, None], dev, -np.inf).max(axis=1)


def _split_disconnected(labels: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Give every piece of a patch that is not connected to the rest through returns its own label.

    Connectivity is 4-neighbour over pixels with a return, through pixels of the patch or unlabelled ones.
    Pieces of one surface seen apart (a wall on both sides of a pipe in front of it, limb samples beyond
    a row of dropouts) are separate regions of the image; one patch spanning them would count as an
    under-segmentation.
    """
    flat = labels.ravel()
    idx = np.flatnonzero(valid.ravel())
    if idx.size == 0 or not (flat >= 0).any():
        return labels
    node = np.full(flat.size, -1, np.int64)
    node[idx] = np.arange(idx.size)
    nd = node.reshape(labels.shape)
    rows, cols = [], []
    for a, b, la, lb in ((nd[:, :-1], nd[:, 1:], labels[:, :-1], labels[:, 1:]),
                         (nd[:-1, :], nd[1:, :], labels[:-1, :], labels[1:, :])):
        m = (a >= 0) & (b >= 0) & ((la == lb) | (la < 0) | (lb < 0))
        rows.append(a[m])
        cols.append(b[m])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(idx.size, idx.size))
    _, comp = connected_components(graph, directed=False)
    lab = flat[idx]
    sel = lab >= 0
    key = comp[sel].astype(np.int64) * (int(lab.max()) + 1) + lab[sel]
    if key.size and int(key.max()) < 4 * key.size:  # the rank of each key among the distinct keys, by counting
        present = np.zeros(int(key.max()) + 1, bool)
        present[key] = True
        new = (np.cumsum(present) - 1)[key]
    else:
        _, new = np.unique(key, return_inverse=True)
    out = np.full(flat.size, -1, np.int32)
    out[idx[sel]] = new
    return out.reshape(labels.shape)


def _peel_weak(labels: np.ndarray, min_pixels: int, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Unlabel pixels with at most two of their 4 neighbours in their own patch (convex corners, spurs,
    one-pixel lines, single pixels).

    Such pixels are where a patch meets another surface or a hole: mixed returns and slivers of the
    neighbouring surface, which the patch has no support to claim (a one-pixel sliver of another surface
    inside a patch counts as an under-segmentation in Hoover's metric). Pixels along a straight border
    and the pixels of strips two or more pixels wide (thin pipes) stay. Patches of fewer than ``min_pixels``
    pixels cut off by jumps from every other patch (a small object on its own) keep their border; small
    patches touching another patch are peeled too (a fragment of two or four pixels vanishes).

    A patch of ``min_pixels`` or more that the peel would thin by ``_THIN_PEEL_FRACTION`` or more, most of
    whose weak pixels close a 2 x 2 block of it, is a strip a few pixels wide along a steep diagonal (a thin
    pipe) with a staircase border: there such a pixel is the end of a row, not a corner or a spur, and stays
    (the factory scanner's diagonal pipes lost a fifth of their pixels and missed the 0.8 overlap).
    """
    pad = np.pad(labels, 1, constant_values=-1)
    H, W = labels.shape

    def same_as(dr: int, dc: int) -> np.ndarray:
        return pad[1 + dr:H + 1 + dr, 1 + dc:W + 1 + dc] == labels

    up, down, left, right = same_as(-1, 0), same_as(1, 0), same_as(0, -1), same_as(0, 1)
    same = up.astype(np.int8) + down + left + right
    sizes = np.bincount(labels[labels >= 0], minlength=1)
    pairs, _ = _border_pairs(labels, jump_h, jump_v)
    large = sizes >= min_pixels
    peel = large.copy()
    peel[pairs[:, 0]] = True
    lab = np.maximum(labels, 0)
    weak = (labels >= 0) & peel[lab] & (same <= 2)
    row_end = (same == 2) & ((up & left & same_as(-1, -1)) | (up & right & same_as(-1, 1))
                             | (down & left & same_as(1, -1)) | (down & right & same_as(1, 1)))
    n_weak = np.bincount(labels[weak], minlength=sizes.size)
    thin = (large & (n_weak >= _THIN_PEEL_FRACTION * sizes)
            & (np.bincount(labels[weak & row_end], minlength=sizes.size) >= _STAIR_FRACTION * n_weak))
    return np.where(weak & ~(thin[lab] & row_end), -1, labels).astype(np.int32)


# a patch is a thin strip when the peel would remove this share of its pixels or more, and at least
# _STAIR_FRACTION of those close a 2 x 2 block (a staircase; a ragged noisy border has spurs and single pixels
# too, and keeping its corners cost the Kinect-like frames). Chosen on the calibration suite: correct detection
# 0.811 -> 0.814 (0.816 without the staircase share, but 0.800 -> 0.792 on the default suite)
_THIN_PEEL_FRACTION = 0.1
_STAIR_FRACTION = 0.8


def _reassign(labels: np.ndarray, st: _State, links, jump_h: np.ndarray, jump_v: np.ndarray, rounds: int,
              margin: float, refit_pixels: int = 4000) -> np.ndarray:
    """Move border pixels to the neighbouring patch whose surface fits them clearly better (returns new labels).

    Tiles, blocks of the coarse grid and merges leave patches whose border runs a few pixels past the
    surface's own (a tile straddling a pipe and its reducer, a pipe strip that took a row of its elbow). A
    pixel linked (no jump) to another patch moves there when its range residual to that patch's surface is
    within ``2 grow_k`` sigma and ``margin`` sigma smaller than to its own; the patches that changed are
    refitted (those of more than ``refit_pixels`` pixels hardly move and are not) and the pixels next to the
    moved ones tested again, for at most ``rounds`` rounds. Pixels near a crease fit both faces within the
    margin and stay. ``links``: :func:`_neighbour_links` of the grid.

    A fragment (fewer than ``min_patch_pixels`` pixels: a strip of limb and mixed returns along a jump) has
    no residual of its own worth comparing, since its fit follows its few pixels: each of its pixels moves to
    a linked patch whose surface fits it within ``2 grow_k`` sigma. Hoover's metric counts a fragment lying
    inside a truth region as an over-segmentation of it (correct detection 0.758 -> 0.800 on the default
    suite, 0.740 -> 0.811 on the calibration suite).
    """
    H, W = labels.shape
    out = labels.copy()
    flat = out.ravel()
    n = int(flat.max()) + 1
    if n < 2:
        return out
    thr = 2.0 * st.params.grow_k
    groups = _groups(out)
    P = _fit_groups(groups, st, n, trim=thr)
    steps = np.array([dr * W + dc for dr, dc, _ in links])
    ok = np.stack([o.ravel() for _, _, o in links])  # (4, H*W) link allowed
    # first candidates: labelled pixels with a linked neighbour of another patch
    diff_h = (out[:, :-1] != out[:, 1:]) & ~jump_h & (out[:, :-1] >= 0) & (out[:, 1:] >= 0)
    diff_v = (out[:-1, :] != out[1:, :]) & ~jump_v & (out[:-1, :] >= 0) & (out[1:, :] >= 0)
    border = np.zeros((H, W), bool)
    border[:, :-1] |= diff_h
    border[:, 1:] |= diff_h
    border[:-1, :] |= diff_v
    border[1:, :] |= diff_v
    cand = np.flatnonzero(border)
    small = {k: v for k, v in groups.items() if v.size <= refit_pixels}
    fragment = np.zeros(n, bool)
    fragment[[k for k, v in groups.items() if v.size < st.params.min_patch_pixels]] = True
    for _ in range(rounds):
        if cand.size == 0:
            break
        nb = cand[None, :] + steps[:, None]
        nl = np.where(ok[:, cand], flat[np.clip(nb, 0, H * W - 1)], -1)
        own = flat[cand]
        x, u, s = st.X[cand], st.U[cand], st.S[cand]
        best_z = _pixel_residuals(P, own, x, u, s)
        best_z[fragment[own]] = np.inf
        best_l = own.copy()
        for k in range(len(steps)):
            m = (nl[k] >= 0) & (nl[k] != own)
            if not m.any():
                continue
            z = np.full(cand.size, np.inf)
            z[m] = _pixel_residuals(P, nl[k, m], x[m], u[m], s[m])
            b = (z + margin < best_z) & (z <= thr)
            best_z[b] = z[b]
            best_l[b] = nl[k, b]
        mv = best_l != own
        if not mv.any():
            break
        moved, src, dst = cand[mv], own[mv], best_l[mv]
        flat[moved] = dst
        # refit the small patches that lost or gained pixels (a large one hardly changes)
        redo = {}
        for lab in np.unique(np.concatenate([src, dst])).tolist():
            if lab in small:
                v = small[lab]
                v = np.concatenate([v[~np.isin(v, moved[src == lab])], moved[dst == lab]])
                small[lab] = redo[lab] = v
        redo = {k: v for k, v in redo.items() if v.size}
        if redo:
            Pc = _fit_groups(redo, st, n, trim=thr)
            keys = list(redo)
            P[keys] = Pc[keys]
        nxt = (moved[None, :] + steps[:, None])[ok[:, moved]]
        cand = np.union1d(cand, nxt[flat[nxt] >= 0])
    return out


def _edge_image(shape, jump_h, jump_v) -> np.ndarray:
    e = np.zeros(shape, bool)
    e[:, :-1] |= jump_h
    e[:, 1:] |= jump_h
    e[:-1, :] |= jump_v
    e[1:, :] |= jump_v
    edges = np.zeros(shape, np.uint8)
    edges[e] = np.uint8(EdgeType.JUMP)
    return edges


def _upsampler(shape: tuple[int, int], d: int):
    """Nearest-neighbour upsampling by ``d`` of a grid sampled at ``[::d, ::d]`` back to ``shape``."""
    H, W = shape

    def up(a: np.ndarray) -> np.ndarray:
        return a.repeat(d, axis=0).repeat(d, axis=1)[:H, :W]
    return up


def _curvature_only(pts, sig, valid, jump_h, jump_v, params) -> Segmentation:
    """An image without any patch (no defined curvature anywhere): curvature images and edges only."""
    cur = curvature_images(pts, sig, params, (jump_h, jump_v))
    hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    edges = _edge_image(sig.shape, jump_h, jump_v)
    return _empty(sig.shape, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges)


def _pixel_residuals(P: np.ndarray, lab: np.ndarray, X: np.ndarray, U: np.ndarray, S: np.ndarray) -> np.ndarray:
    """|range residual| in sigma of points X (N, 3) to the surfaces P[lab] (per point), as in _quick_fit."""
    return _ray_z(P.T.take(lab, axis=1), X.T.copy(), U, S)


def _ray_z(p: np.ndarray, x: np.ndarray, U: np.ndarray, S: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
    """|range residual| in sigma of points to quadrics, as in :func:`_quick_fit`: the quadric's value over its
    gradient's component along the ray (floored at ``_MIN_GRAZING`` of the gradient's norm), inf where undefined.

    Laid out by rows, so that the element-wise products run on contiguous memory: ``p`` (10, N) each point's
    quadric, or (10, 1) one for all; ``x`` (3, N) the points' coordinates; ``U`` (N, 3) unit rays; ``S`` (N,)
    sigmas; ``f`` (N,) the quadric's values at the points, when already at hand.
    """
    x0, x1, x2 = x
    g0 = 2 * (p[0] * x0 + p[3] * x1 + p[4] * x2) + p[6]
    g1 = 2 * (p[3] * x0 + p[1] * x1 + p[5] * x2) + p[7]
    g2 = 2 * (p[4] * x0 + p[5] * x1 + p[2] * x2) + p[8]
    if f is None:
        f = (p[0] * x0 * x0 + p[1] * x1 * x1 + p[2] * x2 * x2
             + 2 * (p[3] * x0 * x1 + p[4] * x0 * x2 + p[5] * x1 * x2)
             + p[6] * x0 + p[7] * x1 + p[8] * x2 + p[9])
    u0, u1, u2 = U.T
    gr = np.abs(g0 * u0 + g1 * u1 + g2 * u2)
    floor = _MIN_GRAZING * np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(f) / (np.maximum(gr, floor) * S)
    return np.where(np.isfinite(z), z, np.inf)


def _refine_full(labels: np.ndarray, valid: np.ndarray, st: _State, links, jump_h, jump_v, params,
                 d: int) -> np.ndarray:
    """Full-resolution labels from the upsampled coarse ones: each patch is refitted on its full-resolution
    pixels, pixels off their patch's surface (beyond ``2 grow_k`` sigma: block corners across an edge) are
    released and re-grown from their neighbours (``links``: :func:`_neighbour_links` of the grid)."""
    labels = np.where(valid, labels, -1).astype(np.int32)
    n_lab = int(labels.max()) + 1
    if n_lab == 0:
        return labels
    # fit on the coarse samples (the pixels the coarse segmentation saw), trimmed
    coarse = np.zeros(labels.shape, bool)
    coarse[::d, ::d] = True
    P = _fit_groups(_groups(np.where(coarse, labels, -1)), st, n_lab, trim=2.0 * params.grow_k)
    flat = labels.ravel()
    idx = np.flatnonzero(flat >= 0)
    # only pixels near a label change, a hole or a jump can belong to another patch than their block
    edge = (labels < 0)
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a != b) | j
        if a.shape[1] != labels.shape[1]:
            edge[:, :-1] |= m
            edge[:, 1:] |= m
        else:
            edge[:-1, :] |= m
            edge[1:, :] |= m
    near = ndi.binary_dilation(edge, structure=np.ones((3, 3), bool), iterations=d).ravel()
    idx = idx[near[idx]]
    z = _pixel_residuals(P, flat[idx], st.X[idx], st.U[idx], st.S[idx])
    flat[idx[~(z <= 2.0 * params.grow_k)]] = -1
    _grow(labels, P, st, links, 2 * d + 2, 2.0 * params.grow_k)
    return labels


def _segment_grid(pts, sig, valid, rng, rays, jump_h, jump_v, params: SegmentationParams, lap: _Laps):
    """The H-K segmentation proper on one grid: (labels, hk, curvature, crease pixels), None without classes.
    ``lap`` times its steps."""
    shape = sig.shape
    cur = curvature_images(pts, sig, params, (jump_h, jump_v))
    hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    crease_h, crease_v = _crease_pairs(cur.normals, cur.sigma_normal, params)
    crease = np.zeros(shape, bool)
    crease[:, :-1] |= crease_h
    crease[:, 1:] |= crease_h
    crease[:-1, :] |= crease_v
    crease[1:, :] |= crease_v
    wide = _wide_creases(cur.normals, valid, jump_h, jump_v, params)
    crease |= wide
    edges = _edge_image(shape, jump_h, jump_v)
    edges[crease] |= np.uint8(EdgeType.CREASE)
    lap("curvature")
    if not (hk > 0).any():
        return None

    st = _State(X=pts.reshape(-1, 3), U=rays.reshape(-1, 3), S=sig.ravel(), hk=hk.ravel().astype(np.int64),
                params=params)
    links = _neighbour_links(shape, valid, jump_h, jump_v)

    seeds = _seed_labels(hk, edges, params)
    seeds = _split_at_creases(seeds, wide, st, params)
    if params.split_seeds:
        seeds = _split_bad_seeds(seeds, st, params)
    lap("seeds")
    labels = seeds.copy()
    P = None
    n_lab = int(seeds.max()) + 1
    for _ in range(params.grow_rounds if n_lab > 0 else 0):
        # refit on the grown patches (trimmed), then grow again from the seeds: pixels that only fitted the
        # seed's extrapolated surface (an elbow next to a pipe seed) are released when the refit rejects them
        P = _fit_groups(_groups(labels), st, n_lab, trim=2.0 * params.grow_k)
        labels = seeds.copy()
        _grow(labels, P, st, links, params.max_grow_iterations, params.grow_k)
    if labels.max() >= 0 and P is not None:
        # last pass, relaxed: single returns beyond grow_k sigma of their own surface are expected in a
        # large patch (0.3 % at 3 sigma); only what fits no neighbour within 2 grow_k is left over
        _grow(labels, P, st, links, params.max_grow_iterations, 2.0 * params.grow_k)

    # leftover pixels with defined curvature: connected pieces of their own (never linked across a jump)
    left = valid & (labels < 0)
    if left.any():
        comp = _link_components(left, jump_h, jump_v)
        sizes = np.bincount(comp[comp >= 0])
        keep = sizes >= params.min_leftover_pixels
        remap = np.where(keep, np.cumsum(keep) - 1, -1)
        comp = np.where(comp >= 0, remap[np.maximum(comp, 0)], -1)
        # leftover pieces spanning several surfaces (a thin pipe run too narrow to seed: pipe, elbow, pipe)
        # are cut into tiles like bad seeds; merging reassembles them
        comp = _tile_small_leftovers(comp, st, params)
        base = int(labels.max()) + 1
        labels[comp >= 0] = (comp[comp >= 0] + base).astype(np.int32)
        if labels.max() >= 0:
            P = _fit_groups(_groups(labels), st, int(labels.max()) + 1)
            _grow(labels, P, st, links, params.max_grow_iterations, params.grow_k)

    lap("growing")
    labels = _merge_enclosed(labels, valid, jump_h, jump_v, params.min_patch_pixels)
    labels = _merge(labels, st, jump_h, jump_v)
    labels = _merge_enclosed(labels, valid, jump_h, jump_v, params.min_patch_pixels)
    labels = _attach_isolated(labels, st, jump_h, jump_v)
    labels = _absorb_fragments(labels, st, jump_h, jump_v, params.min_region_pixels, params.absorb_k)
    lap("merging")
    return labels, hk, cur, crease


def _finalise(labels: np.ndarray, st: _State, params: SegmentationParams, declared: np.ndarray):
    """Relabel 0..n-1 by decreasing size and fit the final plane / quadric of every patch.

    Fits (and so ``rms_sigma`` and the ``noisy`` flag) are in units of the *declared* sigma, not of the
    self-calibrated one: a sensor much noisier than its model says still gives noisy patches.
    """
    groups = _groups(labels)
    order = sorted(groups, key=lambda k: (-groups[k].size, int(groups[k][0])))
    out = np.full(labels.shape, -1, dtype=np.int32)
    flat = out.ravel()
    W = labels.shape[1]
    patches = []
    for new, old in enumerate(order):
        idx = groups[old]
        flat[idx] = new
        counts = np.bincount(st.hk[idx], minlength=5)
        stype = SurfaceType(int(np.argmax(counts[1:])) + 1) if counts[1:].sum() else SurfaceType.NONE
        sub = _subsample(idx, params.final_fit_points)
        x, s = st.X[sub], declared[sub]
        fit: PlaneFit | QuadricSurfaceFit
        if stype == SurfaceType.PLANAR or sub.size < 10:
            fit = fit_plane(x, s)
        else:
            fit = fit_quadric_lsq(x, s)
        noisy = (not fit.ok) or not (fit.rms_sigma <= params.noisy_k)
        r, c = np.divmod(idx, W)
        patches.append(
            Patch(
                id=new,
                pixels=np.stack([r, c], axis=1),
                n_pixels=int(idx.size),
                surface_type=stype,
                fit=fit,
                small=bool(idx.size < params.min_patch_pixels),
                noisy=bool(noisy),
                class_counts=tuple(int(v) for v in counts),
            )
        )
    return out, tuple(patches)
