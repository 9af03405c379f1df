"""The segmentation's parameters and results: H-K surface classes, edge bits, :class:`SegmentationParams`,
:class:`Patch`, :class:`Segmentation` and the curvature images (section 3 of Fillatreau & Fisher)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np

from recognition.fitting import PlaneFit, QuadricSurfaceFit

__all__ = ["SurfaceType", "EdgeType", "SegmentationParams", "Patch", "Segmentation", "CurvatureImages"]


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
        Plane ``n . x = offset`` (n facing the sensor; :func:`recognition.fitting.fit_plane_lsq`) for planar
        patches, a general quadric otherwise (:func:`recognition.fitting.fit_quadric_lsq`); with covariance
        and RMS residuals (``rms_sigma``: along the ray, in sigma units). A failed fit is falsy.
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
