"""The segmentation's parameters and results: H-K surface classes, edge bits, :class:`SegmentationParams`,
:class:`Patch`, :class:`Segmentation` and the curvature images (section 3 of Fillatreau & Fisher)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import IntEnum
from typing import Literal

import numpy as np

from recognition.fitting import PlaneFit, QuadricSurfaceFit
from recognition.tuning import AUTO, tuned

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
    crease_baseline : int, "auto" or None
        Half baseline ``k`` (pixels of the segmentation grid) of the wide-baseline crease test
        (:func:`_wide_creases`) and of the crease split of badly fitted seeds (:func:`_split_at_creases`);
        "auto": ``window``; None (default): both off. The windowed normal fits spread a crease over about
        ``window`` pixels, so on noisy (real) data no pair of neighbours crosses the neighbour test. Measured
        with "auto" on 10 scans per group of the first phase's simulated scenes (commit 24ce129; correct
        detection): Kinect-like 0.21 -> 0.43, mock-up 0.76 (same), factory scanner 0.63 -> 0.60; on the real
        scans it separates the box faces, the mug from the table and the tunnel floor from its wall, but the
        classifier then labels the box faces CYL (their plane residual is ~1.6x the declared sigma), so it
        stays off until the classifier's noise handles real data.
    crease_wide_k : float
        Its threshold in robust scales (MAD) of the statistic over the image (real noise is spatially
        correlated: the propagated sigma of independent pixels under-states it).
    crease_wide_min_angle : float, radians
        Floor of that threshold.
    sigma_floor_m : float, metres
        Floor applied to the input sigma (quantisation level; keeps noise-free images usable).
    seed_erosion : int or "auto"
        Erosion (pixels) that a class component must survive to seed a patch ("auto": ``window // 2``).
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
    max_tiled_leftover : int or None
        Leftover pieces (no seed: thin pipes, every window of which crosses a jump) below this size (pixels
        of the segmentation grid) that one surface does not fit are cut into tiles like bad seeds; None (default):
        whatever their size. A whole pipe run (pipe, reducer, pipe, elbow) is otherwise one patch: correct
        detection with the factory scanner 0.59 -> 0.66 on the first phase's default suite.
    class_min_pixels : int or None
        Classified pixels a patch needs for its dominant class to veto a merge across a cylindrical /
        doubly-curved class boundary (pixels of the segmentation grid); None (default): no veto. On
        the simulated suites tangent joins were lost before merging (one seed or leftover piece spanning
        both surfaces), and the veto cost two regions elsewhere.
    connectivity : int
        4 or 8: pixel connectivity of class components.
    decimation : int or "auto"
        Grid step of curvature, seeding, growing and merging (labels are refined at full resolution);
        "auto": 2 for images of at least 400 rows, else 1 (:meth:`step`).
    final_fit_points : int
        Points (deterministic stride subsample) of the final plane / quadric fit of each patch.
    split_seeds : bool or "auto"
        Cut seeds that one surface does not fit into tiles (:func:`_split_bad_seeds`); merging reassembles
        the tiles that share a surface. "auto" (default): on for decimated grids (VGA-class images). There it
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
        slices of ``axial_slice_points`` points on far pipes, on the first phase's ``calibration`` suite: pooled correct
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
    max_variance_ratio : float
        A masked derivative window whose second-derivative variance exceeds this multiple of the full window's
        is too ill-conditioned: its derivatives are NaN (:func:`quadratic_derivatives`).
    noise_block : int
        Side of the blocks of :func:`noise_scale`, in samples (every third pixel: ``3 noise_block`` pixels).
    absorb_rounds : int
        Rounds of :func:`_absorb_fragments` (fragments into the bordering patch that fits them).
    plane_pair_tol : float
        Relative tolerance of the plane-pair test (:func:`_is_plane_pair`: rank and constant of the quadric).
    kplanes_iterations, kplanes_inlier_k, kplanes_trials : int, float (sigma), int
        The face cut's k-planes (:func:`_k_planes`): alternations at most; inlier distance of its sequential
        RANSAC start, along the ray in sigmas; RANSAC triples per plane.
    face_broad_ratio : float
        A face of the face cut must spread across its plane over this many median sigmas (:func:`_broad`).
    face_keep : float
        Share of a face's pixels whose RMS must be within ``1.5 merge_k`` (the rest are mixed at the creases).
    face_min_angle_deg : float, degrees
        Faces cut apart by :func:`_faces` meet at this angle or more.
    axis_split_passes : int
        Passes of the axial cut (:func:`_split_along_axis`: a piece holding a reducer and a pipe is cut again).
    axial_fit_points, axial_flat_fraction, axial_min_bins, axial_slice_points : int, float, int, int
        The axial cut's profile (:func:`_axial_pieces`): points of its section fit; a profile is one line within
        ``max(3 sigma, axial_flat_fraction * radius)`` per slice; slices each side of a cut at least; points
        per slice on average (slices are longer than half a radius on a far, thin pipe).
    axial_partial_fraction : float
        A slice takes part in the axial profile when it holds at least this fraction of the median slice's
        points (and 20): a slice the patch's border crosses (its end, cut obliquely or by an occluder) holds
        part of the pipe's circumference and mixed pixels, and its median distance to the axis is off the
        line; one such slice at the end of a pipe, reducer and pipe kept any three lines from fitting.
    elbow_cut_keep, elbow_cut_rounds, elbow_cut_k : float, int, float (sigma)
        The cut of two pipes merged with their elbow (:func:`_dominant_cylinder`): the fraction of normals (and
        of section points) kept nearest the dominant pipe, over this many trimming rounds; the pipe takes the
        points within ``elbow_cut_k`` sigma of its fitted cylinder.
    torus_join_k, torus_join_cylinder_ratio, torus_join_max_bend : float (sigma) or None, float, float
        Elbow joins (:func:`._join_elbow_pieces`, step 9b): two adjacent patches join when a ring torus fits their
        union within ``torus_join_k`` sigma (None: off), bending no wider than ``torus_join_max_bend`` tube radii,
        and a cylinder fits it ``torus_join_cylinder_ratio`` times worse.
    torus_join_min_pixels, torus_join_min_border, torus_join_fit_points : int
        ... of patches of at least ``torus_join_min_pixels`` pixels sharing ``torus_join_min_border`` border pixels;
        the fits use a regular sample of ``torus_join_fit_points`` of the union's pixels.
    reassign_refit_pixels : int
        Patches of more pixels are not refitted between rounds of :func:`_reassign` (they hardly move).
    complete_k, complete_rounds : float (sigma) or None, int
        Border completion (:func:`_complete_borders`, after the hygiene): an unlabelled pixel with a return
        joins the linked patch whose surface fits it within ``complete_k`` sigma (None: off), for at most
        ``complete_rounds`` rounds of one ring of pixels.
    min_kept_pixels : int or None
        Step 10 leaves unlabelled the patches of fewer pixels (full-resolution pixels) that merging and the
        fragment absorption left on their own (:func:`_drop_fragments`); None keeps every patch.
    thin_peel_fraction, stair_fraction : float
        :func:`_peel_weak` keeps the row ends of a patch (of ``min_region_pixels`` or more) that the peel would
        thin by ``thin_peel_fraction`` or more when at least ``stair_fraction`` of its weak pixels close a 2 x 2
        block of it (a staircase border; a ragged noisy border has spurs and single pixels too, and keeping
        its corners cost the Kinect-like frames).

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    window: int = tuned(7, unit="px", chosen="not tuned: the first segmenter's window (b65f74f)")
    zero_k: float = tuned(3.0, unit="sigma", chosen="not tuned: a 3-sigma test, set in b65f74f")
    jump_k: float = tuned(4.0, unit="sigma", chosen="not tuned: set in b65f74f")
    jump_tan: float = tuned(5.0, unit="tan", chosen="not tuned: set in b65f74f (5.0 ~ 79 deg incidence)")
    crease_k: float = tuned(4.0, unit="sigma", chosen="not tuned: set in b65f74f")
    crease_min_angle: float = tuned(float(np.deg2rad(12.0)), unit="rad", chosen="not tuned: set in b65f74f")
    crease_baseline: int | Literal["auto"] | None = tuned(
        None, unit="px (grid)", chosen="off: on 10 simulated scans per group of the first phase (24ce129) it "
        "doubled Kinect-like correct detection (0.21 -> 0.43) but cost the factory scanner 0.03, and on real box "
        "scans the separated faces fail the classifier's fit test")
    crease_wide_k: float = tuned(3.0, unit="MAD", chosen="not tuned: set with the wide-baseline test (24ce129), "
                                 "which is off")
    crease_wide_min_angle: float = tuned(float(np.deg2rad(30.0)), unit="rad",
                                         chosen="not tuned: set with the wide-baseline test (24ce129), which is off")
    sigma_floor_m: float = tuned(1e-5, unit="m", chosen="not tuned: a quantisation floor (b65f74f)")
    seed_erosion: int | Literal["auto"] = tuned("auto", unit="px", chosen="not tuned: window // 2 since b65f74f")
    min_seed_pixels: int = tuned(8, unit="px", chosen="not tuned: set in b65f74f")
    grow_k: float = tuned(3.0, unit="sigma", chosen="not tuned: set in b65f74f")
    grow_rounds: int = tuned(2, unit="count", chosen="not tuned: set in b65f74f")
    max_grow_iterations: int = tuned(100, unit="count", chosen="not tuned: a bound, set in b65f74f")
    merge_k: float = tuned(2.0, unit="sigma", chosen="not tuned: set in b65f74f")
    min_patch_pixels: int = tuned(50, unit="px", chosen="not tuned: set in b65f74f")
    noisy_k: float = tuned(3.0, unit="sigma", chosen="not tuned: a flag only, set in b65f74f")
    min_leftover_pixels: int = tuned(3, unit="px", chosen="not tuned: set in b65f74f")
    max_fit_points: int = tuned(1500, unit="points", chosen="not tuned: a speed bound, set in b65f74f")
    merge_fit_points: int = tuned(400, unit="points", chosen="not tuned: a speed bound, set in 84acd52")
    class_min_pixels: int | None = tuned(
        None, unit="px (grid)", chosen="off: on the first phase's simulated suites the veto cost two regions and "
        "tangent joins were lost before merging anyway (84acd52)")
    max_tiled_leftover: int | None = tuned(
        None, unit="px (grid)", chosen="no limit since 217c790 (formerly spelled 1_000_000): tiling every leftover "
        "took factory-scanner correct detection 0.59 -> 0.66 on the first phase's default (now classic)")
    connectivity: int = tuned(4, unit="-", chosen="not tuned: 4-connectivity since b65f74f")
    calibrate_noise: bool = tuned(
        True, unit="-", chosen="on since 84acd52, whose changes together (with the coarse grid, trimmed refits, "
        "peeling, fragment merging) took correct detection on 10 simulated scans per group 0.49 -> 0.76 (mock-up), "
        "0.44 -> 0.63 (factory scanner); its own share not measured")
    min_region_pixels: int = tuned(200, unit="px",
                                   chosen="not tuned: the 200-pixel floor of the scored regions (84acd52)")
    decimation: int | Literal["auto"] = tuned(
        "auto", unit="px", chosen="not tuned: 2 for images of >= 400 rows since 84acd52 (with the noise calibration: "
        "the figures of calibrate_noise)")
    split_seeds: bool | Literal["auto"] = tuned(
        "auto", unit="-", chosen="on for decimated grids since 217c790, whose changes together (with the Taubin quick "
        "fits and the plane-pair guard) took correct detection 0.52 -> 0.61 on the first phase's default (now "
        "classic); off at full resolution for the real box scans")
    seed_tile: int = tuned(12, unit="px (grid)", chosen="not tuned: set in 84acd52")
    split_k: float = tuned(4.0, unit="sigma", chosen="not tuned: set in 84acd52")
    final_fit_points: int = tuned(5000, unit="points", chosen="not tuned: a speed bound, set in 84acd52")
    absorb_k: float = tuned(4.0, unit="sigma", chosen="not tuned: set in 84acd52")
    max_noise_scale: float = tuned(10.0, unit="ratio", chosen="not tuned: a bound, set in 84acd52")
    curved_planar_merge: bool = tuned(
        True, unit="-", chosen="on since 329aaa5: Kinect-like correct detection 0.38 -> 0.42, select accuracy 0.63 "
        "-> 0.71 on the first phase's default (now classic)")
    axis_split_pixels: int | None = tuned(
        400, unit="px", chosen="calibration (phase 1): pooled correct detection 0.730 -> 0.739 (1500 before; "
        "062236b)")
    reassign_rounds: int = tuned(
        16, unit="count", chosen="set in c398b05 with the reassignment (correct detection 0.705 -> 0.724 on the "
        "first phase's default, now classic); the count itself not varied")
    reassign_margin: float = tuned(1.0, unit="sigma", chosen="set in c398b05 with the reassignment; not varied")
    max_variance_ratio: float = tuned(
        25.0, unit="ratio", chosen="not tuned: set with the masked derivatives in b65f74f")
    noise_block: int = tuned(8, unit="samples", chosen="not tuned: set with the noise calibration in 84acd52")
    absorb_rounds: int = tuned(3, unit="count", chosen="not tuned: set with the fragment merge in 84acd52")
    plane_pair_tol: float = tuned(
        0.05, unit="relative", chosen="the first phase's default (now classic): 0.05 and 0.15 gave the same "
        "segmentations (8f5f095)")
    kplanes_iterations: int = tuned(10, unit="count", chosen="not tuned: set with the face cut in d264951")
    kplanes_inlier_k: float = tuned(3.0, unit="sigma", chosen="not tuned: set with the RANSAC start in e9db788")
    kplanes_trials: int = tuned(100, unit="count", chosen="not tuned: set with the RANSAC start in e9db788")
    face_broad_ratio: float = tuned(10.0, unit="sigma", chosen="not tuned: set with the face cut in d264951")
    face_keep: float = tuned(0.9, unit="fraction", chosen="not tuned: set with the face cut in d264951")
    face_min_angle_deg: float = tuned(30.0, unit="deg", chosen="not tuned: set with the face cut in d264951")
    axis_split_passes: int = tuned(3, unit="count", chosen="not tuned: set with the axial cut in 5efb356")
    axial_fit_points: int = tuned(2000, unit="points", chosen="not tuned: set with the axial cut in 5efb356")
    axial_flat_fraction: float = tuned(0.03, unit="fraction", chosen="not tuned: set with the axial cut in 5efb356")
    axial_min_bins: int = tuned(3, unit="count", chosen="not tuned: set with the axial cut in 5efb356")
    axial_slice_points: int = tuned(
        25, unit="points", chosen="calibration (phase 1), with axis_split_pixels 400: pooled correct detection "
        "0.730 -> 0.739 (half a radius held 5-10 points on far thin pipes; 062236b)")
    axial_partial_fraction: float = tuned(
        0.5, unit="fraction", chosen="calibration: correct detection of the Kinect-like group 0.692 -> 0.707 / 0.707 / "
        "0.723 / 0.713 at 0.25 / 0.35 / 0.5 / 0.75 (factory scanner 0.770 -> 0.770 / 0.770 / 0.769 / 0.773, mock-up "
        "0.880 throughout; the segmenter's labels on the 96 frames)")
    elbow_cut_keep: float = tuned(0.6, unit="fraction", chosen="not tuned: set with the elbow cut in 336d4d7")
    elbow_cut_rounds: int = tuned(4, unit="count", chosen="not tuned: set with the elbow cut in 336d4d7")
    elbow_cut_k: float = tuned(3.0, unit="sigma", chosen="not tuned: set with the elbow cut in 336d4d7")
    torus_join_k: float | None = tuned(
        1.2, unit="sigma", chosen="calibration (issue 35), the segmenter's labels on its 96 frames: correct detection "
        "0.769 -> 0.769 (factory scanner), 0.723 -> 0.747 (Kinect-like), 0.880 -> 0.892 (mock-up); 1.0 gave the same, "
        "1.5 0.772 / 0.747 / 0.889")
    torus_join_cylinder_ratio: float = tuned(
        1.5, unit="ratio", chosen="calibration (issue 35), with torus_join_k: 1.2 gave the same labels' scores")
    torus_join_max_bend: float = tuned(
        5.0, unit="tube radii", chosen="calibration (issue 35), with torus_join_k: at 8 a Kinect-like pipe joined the "
        "piece of its elbow it bordered (torus R = 7.2 r; the elbow's own pieces fit R = 3.1 r), at 4 the Kinect-like "
        "group lost 0.008 and the mock-up 0.003; standard elbows bend at 2-3 tube radii (ASME B16.9 short and long "
        "radius)")
    torus_join_min_pixels: int = tuned(
        200, unit="px", chosen="calibration (issue 35), with torus_join_k: 100 and 200 gave the same labels' scores, "
        "400 cost the mock-up 0.003; 200 is the smallest scored region (the fits of smaller pieces tell a pipe from "
        "its elbow less well)")
    torus_join_min_border: int = tuned(20, unit="px", chosen="not tuned: set with the elbow joins")
    torus_join_fit_points: int = tuned(150, unit="points", chosen="not tuned: a speed bound, set with the elbow joins")
    reassign_refit_pixels: int = tuned(
        4000, unit="px", chosen="not tuned: a speed bound, set with the reassignment in c398b05")
    complete_k: float | None = tuned(
        6.0, unit="sigma", chosen="calibration (issue 35), after min_kept_pixels, segmenter's labels: correct "
        "detection 0.727 -> 0.768 (factory scanner), 0.642 -> 0.680 (Kinect-like), 0.871 -> 0.892 (mock-up) with 6 "
        "rounds; 3 and 10 sigma gave 0.764 / 0.680 / 0.884 and 0.774 / 0.680 / 0.886")
    complete_rounds: int = tuned(
        2, unit="count", chosen="calibration (issue 35), the core's figures (harness bench, three methods on the "
        "same scans): 2 rounds kept the segmentation of 6 (correct detection 0.793 against 0.792) and the "
        "classification of no completion (accuracy 0.943 / Brier 0.109, 6 rounds 0.939 / 0.114, none 0.944 / "
        "0.107): wider bands give small patches the limb and grazing pixels that mislead their fits. Then, on "
        "the default suite (not tuned on), classification still lost 0.02 of factory-scanner accuracy: patches "
        "grown past 200 pixels were scored, and grown patches classified on their limb pixels; completing only "
        "patches of min_region_pixels or more, fitted and classified on their own pixels (Segmentation.support), "
        "gave on calibration correct detection 0.791, accuracy 0.943, Brier 0.109 (before issue 35: 0.724 / "
        "0.941 / 0.111)")
    min_kept_pixels: int | None = tuned(
        100, unit="px", chosen="calibration (issue 35): correct detection 0.687 -> 0.727 (factory scanner), 0.620 -> "
        "0.642 (Kinect-like), 0.827 -> 0.871 (mock-up); dropping every small patch (small objects in front of "
        "their surroundings too) gave 50: 0.720 / 0.639 / 0.863, 100-160 the same within 0.005, 200 cost the "
        "mock-up 0.012 (a patch of 160-199 pixels can match a 200-pixel region)")
    thin_peel_fraction: float = tuned(
        0.1, unit="fraction", chosen="calibration (phase 1): correct detection 0.811 -> 0.814 with stair_fraction "
        "(e9416d7)")
    stair_fraction: float = tuned(
        0.8, unit="fraction", chosen="calibration (phase 1): 0.816 without it against 0.814, but the first phase's "
        "default (now classic) 0.800 -> 0.792 without it (e9416d7)")

    def __post_init__(self) -> None:
        if not isinstance(self.window, int | np.integer) or self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"window must be an odd integer >= 3, got {self.window!r}")
        if self.crease_baseline not in (None, AUTO) and not (
                isinstance(self.crease_baseline, int | np.integer) and self.crease_baseline >= 1):
            raise ValueError(f"crease_baseline must be an integer >= 1, 'auto' or None, got {self.crease_baseline!r}")
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
        if self.seed_erosion != AUTO and not (isinstance(self.seed_erosion, int | np.integer)
                                              and self.seed_erosion >= 0):
            raise ValueError(f"seed_erosion must be an integer >= 0 or 'auto', got {self.seed_erosion!r}")
        for name in ("min_seed_pixels", "grow_rounds", "max_grow_iterations", "min_patch_pixels",
                     "min_leftover_pixels", "min_region_pixels", "seed_tile", "final_fit_points"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        for name in ("max_fit_points", "merge_fit_points", "torus_join_fit_points"):
            if getattr(self, name) < 10:
                raise ValueError(f"{name} must be >= 10, got {getattr(self, name)!r}")
        if self.decimation != AUTO and not (isinstance(self.decimation, int | np.integer) and self.decimation >= 1):
            raise ValueError(f"decimation must be an integer >= 1 or 'auto', got {self.decimation!r}")
        if self.split_seeds != AUTO and not isinstance(self.split_seeds, bool):
            raise ValueError(f"split_seeds must be true, false or 'auto', got {self.split_seeds!r}")
        for name in ("class_min_pixels", "max_tiled_leftover", "axis_split_pixels", "min_kept_pixels", "complete_k"):
            v = getattr(self, name)
            if v is not None and not v >= 1:
                raise ValueError(f"{name} must be >= 1 or None (off), got {v!r}")
        for name in ("absorb_rounds", "kplanes_iterations", "kplanes_trials", "axis_split_passes", "axial_min_bins",
                     "axial_slice_points", "elbow_cut_rounds", "reassign_refit_pixels", "noise_block",
                     "complete_rounds", "torus_join_min_pixels", "torus_join_min_border"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.torus_join_k is not None and not (np.isfinite(self.torus_join_k) and self.torus_join_k > 0):
            raise ValueError(f"torus_join_k must be a positive finite number or None (off), got {self.torus_join_k!r}")
        if not (self.torus_join_cylinder_ratio >= 1 and self.torus_join_max_bend > 1):
            raise ValueError("torus_join_cylinder_ratio must be >= 1 and torus_join_max_bend > 1, got "
                             f"{self.torus_join_cylinder_ratio!r} and {self.torus_join_max_bend!r}")
        if self.axial_fit_points < 10:
            raise ValueError(f"axial_fit_points must be >= 10, got {self.axial_fit_points!r}")
        for name in ("max_variance_ratio", "plane_pair_tol", "kplanes_inlier_k", "face_broad_ratio", "elbow_cut_k",
                     "axial_flat_fraction"):
            v = getattr(self, name)
            if not v > 0:
                raise ValueError(f"{name} must be > 0, got {v!r}")
        for name in ("face_keep", "elbow_cut_keep", "thin_peel_fraction", "stair_fraction", "axial_partial_fraction"):
            v = getattr(self, name)
            if not 0 < v <= 1:
                raise ValueError(f"{name} must be in (0, 1], got {v!r}")
        if not 0 <= self.face_min_angle_deg <= 90:
            raise ValueError(f"face_min_angle_deg must be in [0, 90] degrees, got {self.face_min_angle_deg!r}")
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
        if self.decimation != AUTO:
            return int(self.decimation)
        return 2 if min(shape) >= 400 else 1

    def scaled(self, d: int) -> SegmentationParams:
        """Parameters for a grid subsampled by ``d``: pixel counts divided by ``d²``."""
        if d == 1:
            return self
        a = d * d
        return replace(self, min_seed_pixels=max(2, self.min_seed_pixels // a),
                       class_min_pixels=None if self.class_min_pixels is None else max(4, self.class_min_pixels // a),
                       min_patch_pixels=max(2, self.min_patch_pixels // a),
                       min_region_pixels=max(2, self.min_region_pixels // a),
                       min_leftover_pixels=max(2, self.min_leftover_pixels // a), decimation=1)

    @property
    def baseline(self) -> int:
        """Effective half baseline of the wide-baseline crease test (0 when it is off)."""
        if self.crease_baseline is None:
            return 0
        return self.window if self.crease_baseline == AUTO else int(self.crease_baseline)

    @property
    def erosion(self) -> int:
        """Effective seed erosion in pixels."""
        return self.window // 2 if self.seed_erosion == AUTO else int(self.seed_erosion)


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
    support : ndarray of shape (H, W), bool, or None
        The labelled pixels a patch's fit and classification rest on; a patch's other pixels (those the border
        completion gave it, step 11) are its extent only: admitted by a looser test at its limbs and grazing
        borders, they would mislead its fit. None: every labelled pixel.
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
    support: np.ndarray | None = None

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
