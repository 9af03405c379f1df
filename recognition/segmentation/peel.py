"""Segmentation step 10, Hoover-literal hygiene: pixels with at most two 4-neighbours in their own patch are
left unlabelled (mixed returns and one-pixel slivers where a patch meets another surface; the paper's patches
are the maximal sets one surface fits, section 3 of Fillatreau & Fisher), and so are the fragments too small to
be a surface of their own (:func:`_drop_fragments`)."""

from __future__ import annotations

import numpy as np

from . import kernels
from .grid import _border_pairs, _kernel_labels
from .types import SegmentationParams


def _peel_weak(labels: np.ndarray, params: SegmentationParams, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Unlabel pixels with at most two of their 4 neighbours in their own patch (convex corners, spurs,
    one-pixel lines, single pixels).

    Such pixels are where a patch meets another surface or a hole: mixed returns and slivers of the
    neighbouring surface, which the patch has no support to claim (a one-pixel sliver of another surface
    inside a patch counts as an under-segmentation in Hoover's metric). Pixels along a straight border
    and the pixels of strips two or more pixels wide (thin pipes) stay. Patches of fewer than ``min_region_pixels``
    pixels cut off by jumps from every other patch (a small object on its own) keep their border; small
    patches touching another patch are peeled too (a fragment of two or four pixels vanishes).

    A patch of ``min_region_pixels`` or more that the peel would thin by ``thin_peel_fraction`` or more, most
    (``stair_fraction``) of whose weak pixels close a 2 x 2 block of it, is a strip a few pixels wide along a
    steep diagonal (a thin pipe) with a staircase border: there such a pixel is the end of a row, not a corner
    or a spur, and stays (the factory scanner's diagonal pipes lost a fifth of their pixels and missed the 0.8
    overlap).
    """
    if labels.size == 0 or labels.max() < 0:
        return labels.astype(np.int32)
    return kernels.peel_weak(_kernel_labels(labels), jump_h, jump_v, int(labels.max()) + 1,
                             int(params.min_region_pixels), float(params.thin_peel_fraction),
                             float(params.stair_fraction))


def _peel_weak_reference(labels: np.ndarray, params: SegmentationParams, jump_h: np.ndarray,
                         jump_v: np.ndarray) -> np.ndarray:
    """:func:`_peel_weak` in numpy (the reference of :func:`.kernels.peel_weak`)."""
    min_pixels = params.min_region_pixels
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
    thin = (large & (n_weak >= params.thin_peel_fraction * sizes)
            & (np.bincount(labels[weak & row_end], minlength=sizes.size) >= params.stair_fraction * n_weak))
    return np.where(weak & ~(thin[lab] & row_end), -1, labels).astype(np.int32)


def _drop_fragments(labels: np.ndarray, params: SegmentationParams, ranges: np.ndarray, jump_h: np.ndarray,
                    jump_v: np.ndarray) -> np.ndarray:
    """Unlabel the patches of fewer than ``min_kept_pixels`` pixels, but small objects on their own (none when
    ``min_kept_pixels`` is None).

    What is left of that size after merging and the fragment absorption (:func:`._absorb_fragments`) fits
    none of its neighbours: flecks of misclassified curvature among a wall's grazing dropouts, the transition
    band along a crease, mixed pixels at a limb. Too few pixels to tell a surface from noise, they are no
    region: Hoover's metric counts a fragment lying in a surface's region as an over-segmentation of it, and a
    patch of this size can be no scored region's (200 pixels or more). A small patch in front of everything
    around it (every neighbour with a return across a jump and farther) is a small object, not a fragment of a
    surface, and stays.

    ``ranges``: (H, W) range of each pixel (NaN where no return).
    """
    if params.min_kept_pixels is None:
        return labels
    sizes = np.bincount(labels[labels >= 0], minlength=1)
    small = sizes < params.min_kept_pixels
    if not small.any():
        return labels
    drop = small & _fragment_flags(labels, ranges, jump_h, jump_v, sizes.size)
    return np.where((labels >= 0) & drop[np.maximum(labels, 0)], -1, labels).astype(np.int32)


def _fragment_flags(labels: np.ndarray, ranges: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                    n_labels: int) -> np.ndarray:
    """(n_labels,) bool: whether a patch has a neighbour with a return (not its own) on its surface (no jump)
    or nearer; ``labels`` (H, W) < ``n_labels``, ``ranges`` (H, W) NaN where no return. The compiled
    :func:`.kernels.fragment_flags`, whose reference is :func:`_fragment_flags_reference`."""
    return kernels.fragment_flags(_kernel_labels(labels), np.asarray(ranges, np.float64), jump_h, jump_v, int(n_labels))


def _fragment_flags_reference(labels: np.ndarray, ranges: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                              n_labels: int) -> np.ndarray:
    """:func:`_fragment_flags` in numpy, one direction at a time."""
    fragment = np.zeros(n_labels, bool)
    for a, b, ra, rb, j in ((labels[:, :-1], labels[:, 1:], ranges[:, :-1], ranges[:, 1:], jump_h),
                            (labels[:-1, :], labels[1:, :], ranges[:-1, :], ranges[1:, :], jump_v)):
        m = (a != b) & np.isfinite(ra) & np.isfinite(rb)
        fragment[a[m & (a >= 0) & (~j | (rb < ra))]] = True
        fragment[b[m & (b >= 0) & (~j | (ra < rb))]] = True
    return fragment
