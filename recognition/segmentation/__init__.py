"""Segmentation: H-K segmentation of organised range images into surface patches (section 3 of Fillatreau &
Fisher).

The paper follows Besl & Jain ("Segmentation through variable-order surface fitting", IEEE PAMI 10(2),
1988, doi:10.1109/34.3881): a patch is a maximal connected set of pixels whose mean (H) and Gaussian (K)
curvature signs do not change; patches are grown and merged by surface fitting, and a plane or a quadric is
fitted to each. The steps here:

1. **Derivatives** of the parametric surface ``P(u, v)`` (the point image; ``u`` column, ``v`` row) by local
   quadratic fits whose windows exclude neighbours across depth jumps (:mod:`.derivatives`:
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
   **Edges**: jump pairs (range difference beyond :func:`.derivatives.jump_threshold`) and crease
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
   across the jump whose surface fits them. Small and noisy patches are kept and flagged (step 10 drops
   the small fragments that are left at the end).

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
   Then the **elbow joins** (:func:`._join_elbow_pieces`, :mod:`.elbows`): adjacent curved patches that one ring
   torus fits, and no cylinder, become one (an elbow's inner and outer sides differ in H-K class and no quadric
   joins them: close Kinect-like elbows were left in two to four pieces).
10. **Hoover-literal hygiene**: fragments under ``min_region_pixels`` join a bordering patch whose surface
   fits them; pixels with at most two 4-neighbours in their own patch are left unlabelled (mixed pixels
   and one-pixel slivers of other surfaces at corners: the metric counts a patch that wholly covers a
   one-pixel truth region as an under-segmentation); patches still under ``min_kept_pixels`` (100) are
   left unlabelled too, but small objects in front of their surroundings: fragments that fit no neighbour,
   which the metric counts as over-segmentations of the surface they lie on.
11. **Border completion** (:func:`_complete_borders`): an unlabelled pixel with a return joins the linked patch
   (of ``min_region_pixels`` or more) whose surface fits it within ``complete_k`` sigma and whose normal
   agrees with its own, for two rings of pixels: the limb bands of thin pipes and the borders the coarse grid
   did not reach. The pixels given are the patch's extent, not its support: its fit and classification rest on
   the others (:attr:`Segmentation.support`). On the calibration suite, correct detection 0.761 -> 0.791 with
   the classification unchanged.

The segmenter reads only the point image and the per-pixel sigma; never any ground truth.

Layout: one module per step, run in this order by :func:`segment` (:mod:`.pipeline`, whose step list says
which steps run for which image size): :mod:`.edges` (returns, jump pairs, the noise self-calibration; 4, 6),
:mod:`.curvature` with :mod:`.derivatives` (1-4), :mod:`.seeds` and :mod:`.growing` (5, 8), :mod:`.merging` (5),
then on decimated grids only :mod:`.refinement` (7), :mod:`.merging` again, :mod:`.splits` (8), :mod:`.reassignment`
(9) and :mod:`.elbows` (9b); finally :mod:`.peel` (10), the border completion of :mod:`.reassignment` (11) and
:mod:`.final_fits`. :mod:`.grid` and :mod:`.quick_fits`
hold what the steps share (pixel groups, adjacency; the batched plane and quadric fits that test growth, merges
and splits), :mod:`.types` the parameters and results, :mod:`.kernels` the compiled (numba) inner loops that
the steps call: growing, residuals, pixel groups, jump pairs, the derivatives and curvatures, the quick fits,
each beside its numpy reference (``*_reference``) and held equal to it by the tests. Settings travel one way: the frozen
:class:`SegmentationParams`, passed explicitly to every step (those on the segmentation grid get
``params.scaled(d)``); helpers on plain point sets take values.
"""

from .curvature import classify_hk, curvature_images
from .edges import noise_scale
from .pipeline import segment
from .types import CurvatureImages, EdgeType, Patch, Segmentation, SegmentationParams, SurfaceType

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
    "noise_scale",
]
