"""Compiled kernels (numba) of the segmentation's per-pixel loops, each the exact equal of a numpy reference.

Issue 35: a frame spent its time in some 126 k small numpy calls (region growing one front at a time, the
residual of every candidate pixel to every neighbouring patch, pixel groups by label). Most kernels here do the
same arithmetic in the same order as their references, operation by operation (numba does not contract
``a * b + c`` into a fused multiply-add without ``fastmath``), so they return the same bits. Two sum in another
order than the BLAS products of their references: the masked quadratic fits (:func:`masked_fits`) and the quick
fits' moments (:func:`quick_fits`); they agree to the rounding (the tests), and the segmenter's labels stayed the
same on all 96 ``default`` frames (``labels sha1`` of ``python -m harness.bench_segmentation --against``), but
the curvature images at masked-window pixels differ in their last bits, and so may a later stage's decision that
sits on a threshold (one ``full`` trial's not-ok pose changed its reason). The references stay beside the kernels
and the tests hold the two equal on random inputs (``tests/recognition/test_kernels.py``).

Compiled once per machine: ``cache=True`` keeps the machine code in ``__pycache__``, so a new process (a forked
trial, a benchmark worker) loads it instead of compiling again; :func:`warm_up` compiles them all at once, on
a tiny input, for the callers that time frames.
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from recognition.fitting import MIN_GRAZING

__all__ = [
    "blank_outside", "checked_returns", "class_counts", "completion_targets", "curvatures", "enclosed_targets",
    "fragment_flags", "grow", "group_order", "jump_pairs", "jump_pairs_among", "masked_fits", "next_candidates",
    "peel_weak", "quick_fits", "ray_z_by_label", "reassign_targets", "savgol_derivatives", "warm_up",
    "window_inputs",
]


@njit(cache=True, nogil=True, error_model="numpy")
def _z_one(P, g, x0, x1, x2, u0, u1, u2, s):
    """|range residual| in sigma of one point to quadric ``P[g]``, with the operations of
    :func:`recognition.segmentation.quick_fits._ray_z` in its order; inf where undefined."""
    p0, p1, p2, p3, p4 = P[g, 0], P[g, 1], P[g, 2], P[g, 3], P[g, 4]
    p5, p6, p7, p8, p9 = P[g, 5], P[g, 6], P[g, 7], P[g, 8], P[g, 9]
    g0 = 2 * (p0 * x0 + p3 * x1 + p4 * x2) + p6
    g1 = 2 * (p3 * x0 + p1 * x1 + p5 * x2) + p7
    g2 = 2 * (p4 * x0 + p5 * x1 + p2 * x2) + p8
    f = (p0 * x0 * x0 + p1 * x1 * x1 + p2 * x2 * x2
         + 2 * (p3 * x0 * x1 + p4 * x0 * x2 + p5 * x1 * x2)
         + p6 * x0 + p7 * x1 + p8 * x2 + p9)
    gr = abs(g0 * u0 + g1 * u1 + g2 * u2)
    floor = MIN_GRAZING * np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    if gr != gr or floor != floor:  # np.maximum propagates NaN
        return np.inf
    z = abs(f) / (max(gr, floor) * s)
    return z if np.isfinite(z) else np.inf


@njit(cache=True, nogil=True, error_model="numpy")
def ray_z_by_label(P, lab, X, U, S):
    """|range residual| in sigma of points to the quadrics ``P[lab]``: ``_ray_z(P.T[:, lab], X.T, U, S)``.

    Parameters
    ----------
    P : ndarray of shape (G, 10)
        Quadrics in the monomial basis of :mod:`recognition.fitting.algebra`.
    lab : ndarray of shape (N,), int
        Each point's quadric.
    X, U : ndarray of shape (N, 3)
        Points (metres) and unit rays.
    S : ndarray of shape (N,)
        Range sigma (metres).

    Returns
    -------
    ndarray of shape (N,), inf where undefined
    """
    n = lab.shape[0]
    out = np.empty(n)
    for i in range(n):
        out[i] = _z_one(P, lab[i], X[i, 0], X[i, 1], X[i, 2], U[i, 0], U[i, 1], U[i, 2], S[i])
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def group_order(flat, n_labels):
    """Pixels grouped by label, by counting: ``(order, starts, counts)`` with the pixels of label ``k`` at
    ``order[starts[k]:starts[k] + counts[k]]``, increasing; labels < 0 are left out.

    Parameters
    ----------
    flat : ndarray of shape (N,), int (any width: compiled once per integer type)
        Labels, all < ``n_labels``.
    n_labels : int
    """
    counts = np.zeros(n_labels, np.int64)
    for v in flat:
        if v >= 0:
            counts[v] += 1
    starts = np.zeros(n_labels, np.int64)
    total = 0
    for k in range(n_labels):
        starts[k] = total
        total += counts[k]
    fill = starts.copy()
    order = np.empty(total, np.int64)
    for i in range(flat.shape[0]):
        v = flat[i]
        if v >= 0:
            order[fill[v]] = i
            fill[v] += 1
    return order, starts, counts


@njit(cache=True, nogil=True, error_model="numpy")
def class_counts(hk, ix, sizes):
    """How many points of each group fall in each curvature class: the kernel of
    :func:`recognition.segmentation.grid._planar_groups_reference`'s count.

    Parameters
    ----------
    hk : ndarray of shape (N,), int
        Each pixel's H-K class, 0..4.
    ix : ndarray of shape (M,), int
        The groups' flat pixel indices, one group after the other.
    sizes : ndarray of shape (G,), int
        Each group's number of pixels (summing to M).

    Returns
    -------
    ndarray of shape (G, 5), int64
    """
    out = np.zeros((sizes.shape[0], 5), np.int64)
    t = 0
    for g in range(sizes.shape[0]):
        for _ in range(sizes[g]):
            out[g, hk[ix[t]]] += 1
            t += 1
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def fragment_flags(labels, ranges, jump_h, jump_v, n_labels):
    """Which patches have a neighbour with a return (not their own) on their surface or nearer: the kernel of
    :func:`recognition.segmentation.peel._fragment_flags_reference` (its arguments and result).

    A 4-neighbour pair of pixels with returns and different labels flags the labelled one of them when no jump
    separates them or the other is nearer (NaN ranges are no returns).

    Parameters
    ----------
    labels : ndarray of shape (H, W), int
        Labels < ``n_labels``, -1 unlabelled.
    ranges : ndarray of shape (H, W), metres
    jump_h : ndarray of shape (H, W - 1), bool; jump_v : ndarray of shape (H - 1, W), bool
    n_labels : int

    Returns
    -------
    ndarray of shape (n_labels,), bool
    """
    H, W = labels.shape
    out = np.zeros(n_labels, np.bool_)
    for i in range(H):
        for j in range(W):
            a, ra = labels[i, j], ranges[i, j]
            if not np.isfinite(ra):
                continue
            if j + 1 < W:
                _flag_pair(out, a, labels[i, j + 1], ra, ranges[i, j + 1], jump_h[i, j])
            if i + 1 < H:
                _flag_pair(out, a, labels[i + 1, j], ra, ranges[i + 1, j], jump_v[i, j])
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _flag_pair(out, a, b, ra, rb, jump):
    """:func:`fragment_flags`' test of one pair of neighbours (labels ``a``, ``b``, ranges ``ra`` finite, ``rb``)."""
    if a == b or not np.isfinite(rb):
        return
    if a >= 0 and (not jump or rb < ra):
        out[a] = True
    if b >= 0 and (not jump or ra < rb):
        out[b] = True


@njit(cache=True, nogil=True, error_model="numpy")
def peel_weak(labels, jump_h, jump_v, n_labels, min_pixels, thin_fraction, stair_fraction):
    """The labels without their weak pixels: the kernel of
    :func:`recognition.segmentation.peel._peel_weak_reference` (its rules; ``labels`` (H, W) int < ``n_labels``,
    -1 unlabelled, ``jump_h`` (H, W - 1) and ``jump_v`` (H - 1, W) bool; returns (H, W) int32)."""
    H, W = labels.shape
    sizes = np.zeros(n_labels, np.int64)
    bordered = np.zeros(n_labels, np.bool_)  # sharing a border without a jump with another patch
    same = np.zeros((H, W), np.int8)  # 4-neighbours in the pixel's own patch
    row_end = np.zeros((H, W), np.bool_)  # two of them, closing a 2 x 2 block of it
    for i in range(H):
        for j in range(W):
            a = labels[i, j]
            if a < 0:
                continue
            up = i > 0 and labels[i - 1, j] == a
            down = i < H - 1 and labels[i + 1, j] == a
            left = j > 0 and labels[i, j - 1] == a
            right = j < W - 1 and labels[i, j + 1] == a
            k = int(up) + int(down) + int(left) + int(right)
            same[i, j] = k
            if k == 2:
                row_end[i, j] = ((up and left and labels[i - 1, j - 1] == a)
                                 or (up and right and labels[i - 1, j + 1] == a)
                                 or (down and left and labels[i + 1, j - 1] == a)
                                 or (down and right and labels[i + 1, j + 1] == a))
            sizes[a] += 1
            if j + 1 < W:
                b = labels[i, j + 1]
                if b >= 0 and b != a and not jump_h[i, j]:
                    bordered[a] = True
                    bordered[b] = True
            if i + 1 < H:
                b = labels[i + 1, j]
                if b >= 0 and b != a and not jump_v[i, j]:
                    bordered[a] = True
                    bordered[b] = True
    n_weak = np.zeros(n_labels, np.int64)
    n_stair = np.zeros(n_labels, np.int64)
    for i in range(H):
        for j in range(W):
            a = labels[i, j]
            if a >= 0 and (sizes[a] >= min_pixels or bordered[a]) and same[i, j] <= 2:
                n_weak[a] += 1
                if row_end[i, j]:
                    n_stair[a] += 1
    out = np.empty((H, W), np.int32)
    for i in range(H):
        for j in range(W):
            a = labels[i, j]
            out[i, j] = a
            if a >= 0 and (sizes[a] >= min_pixels or bordered[a]) and same[i, j] <= 2:
                thin = (sizes[a] >= min_pixels and n_weak[a] >= thin_fraction * sizes[a]
                        and n_stair[a] >= stair_fraction * n_weak[a])
                if not (thin and row_end[i, j]):
                    out[i, j] = -1
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def enclosed_targets(labels, valid, jump_h, jump_v, n_labels, min_pixels):
    """One round of the enclosed-fragment merge: the label each patch joins (``remap`` (n_labels,), itself when
    it stays), the kernel of :func:`recognition.segmentation.merging._enclosed_targets_reference`.

    A patch's neighbours across its 4-borders are other patches, -2 (the image border or a pixel without a
    return) or transparent (an unlabelled return, or across a jump: not counted). A patch of fewer than
    ``min_pixels`` pixels whose only neighbour is one larger patch joins it, unless that one joins another
    itself (patches taken by increasing label).

    Parameters
    ----------
    labels : ndarray of shape (H, W), int
        Labels < ``n_labels``, -1 unlabelled.
    valid : ndarray of shape (H, W), bool
        Returns.
    jump_h : ndarray of shape (H, W - 1), bool; jump_v : ndarray of shape (H - 1, W), bool
    n_labels, min_pixels : int
    """
    H, W = labels.shape
    sizes = np.zeros(n_labels, np.int64)
    first = np.full(n_labels, -4, np.int64)  # a patch's neighbour (-4: none seen)
    several = np.zeros(n_labels, np.bool_)  # more than one distinct neighbour
    for i in range(H):
        for j in range(W):
            a = labels[i, j]
            if a >= 0:
                sizes[a] += 1
            if a < 0 or not valid[i, j]:
                continue
            for k in range(4):
                if k == 0:
                    ii, jj, jump = i, j - 1, j > 0 and jump_h[i, j - 1]
                elif k == 1:
                    ii, jj, jump = i, j + 1, j < W - 1 and jump_h[i, j]
                elif k == 2:
                    ii, jj, jump = i - 1, j, i > 0 and jump_v[i - 1, j]
                else:
                    ii, jj, jump = i + 1, j, i < H - 1 and jump_v[i, j]
                if jump:
                    continue
                if ii < 0 or ii >= H or jj < 0 or jj >= W or not valid[ii, jj]:
                    b = -2
                else:
                    b = labels[ii, jj]
                    if b == -1:
                        continue  # an unlabelled return: transparent
                if b == a:
                    continue
                if first[a] == -4:
                    first[a] = b
                elif first[a] != b:
                    several[a] = True
    remap = np.arange(n_labels)
    for p in range(n_labels):
        q = first[p]
        if q >= 0 and not several[p] and sizes[p] < min_pixels and sizes[q] > sizes[p] and remap[q] == q:
            remap[p] = q
    return remap


@njit(cache=True, nogil=True, error_model="numpy")
def grow(flat, P, X, U, S, steps, link_ok, H, W, max_iter, thr):
    """Grow labelled patches into unlabelled pixels whose residual fits, in place: the kernel of
    :func:`recognition.segmentation.growing._grow_reference`, round for round.

    Every round, each front pixel (unlabelled, with a finite sigma, linked to a labelled neighbour) takes the
    label of the linked neighbour whose surface fits it best (the first of the four directions on a tie), when
    that residual is within ``thr``; all of a round's pixels are labelled at once, and the next front is the
    unlabelled candidates 4-adjacent to them.

    Parameters
    ----------
    flat : ndarray of shape (H*W,), int
        Labels, -1 unlabelled; updated in place.
    P : ndarray of shape (G, 10)
        Each label's quadric.
    X, U : ndarray of shape (H*W, 3); S : ndarray of shape (H*W,)
        Points, unit rays and sigma of the grid.
    steps : ndarray of shape (4,), int
        Flat offset of each link direction (left, right, up, down).
    link_ok : ndarray of shape (4, H*W), bool
        Whether the link from a pixel in each direction is allowed.
    H, W, max_iter : int
    thr : float
        Largest residual (sigma) a pixel joins with.
    """
    N = H * W
    cand = np.zeros(N, np.bool_)
    for i in range(N):
        cand[i] = flat[i] < 0 and np.isfinite(S[i])
    front = np.empty(N, np.int64)
    nf = 0
    for i in range(N):
        if cand[i]:
            for k in range(4):
                if link_ok[k, i] and flat[i + steps[k]] >= 0:
                    front[nf] = i
                    nf += 1
                    break
    new_pix = np.empty(N, np.int64)
    new_lab = np.empty(N, np.int64)
    mark = np.zeros(N, np.bool_)
    for _ in range(max_iter):
        if nf == 0:
            break
        nn = 0
        for j in range(nf):
            i = front[j]
            best_z = np.inf
            best_l = -1
            for k in range(4):
                if not link_ok[k, i]:
                    continue
                lab = flat[i + steps[k]]
                if lab < 0:
                    continue
                z = _z_one(P, lab, X[i, 0], X[i, 1], X[i, 2], U[i, 0], U[i, 1], U[i, 2], S[i])
                if z < best_z:
                    best_z = z
                    best_l = lab
            if best_l >= 0 and best_z <= thr:
                new_pix[nn] = i
                new_lab[nn] = best_l
                nn += 1
        if nn == 0:
            break
        for j in range(nn):
            flat[new_pix[j]] = new_lab[j]
        nf = 0
        for j in range(nn):
            i = new_pix[j]
            r = i // W
            c = i - r * W
            for a in (i - 1 if c > 0 else -1, i + 1 if c < W - 1 else -1,
                      i - W if r > 0 else -1, i + W if r < H - 1 else -1):
                if a >= 0 and cand[a] and flat[a] < 0 and not mark[a]:
                    mark[a] = True
                    front[nf] = a
                    nf += 1
        for j in range(nf):
            mark[front[j]] = False
    return flat


@njit(cache=True, nogil=True, error_model="numpy")
def reassign_targets(flat, P, X, U, S, cand, steps, link_ok, fragment, margin, thr):
    """One round of the border reassignment's choice: the kernel of
    :func:`recognition.segmentation.reassignment._targets_reference` (its arguments and result).

    Each candidate pixel keeps its label unless a linked neighbour's patch (of another label) fits it within
    ``thr`` and ``margin`` better than its own (a fragment's own residual counts as inf); of several, the
    first direction that beats the best so far by the margin.

    Parameters
    ----------
    flat : ndarray of shape (H*W,), int
        Labels (every candidate's >= 0).
    P : ndarray of shape (G, 10)
        Each label's quadric.
    X, U : ndarray of shape (H*W, 3); S : ndarray of shape (H*W,)
        Points, unit rays and sigma of the image.
    cand : ndarray of shape (N,), int
        Candidate pixels (flat indices).
    steps : ndarray of shape (4,), int; link_ok : ndarray of shape (4, H*W), bool
        Flat offset of each link direction and whether each pixel's link that way is allowed.
    fragment : ndarray of shape (G,), bool
    margin, thr : float
        Sigma.

    Returns
    -------
    ndarray of shape (N,), int64: each candidate's label after the round
    """
    n = cand.shape[0]
    last = flat.shape[0] - 1
    out = np.empty(n, np.int64)
    for j in range(n):
        i = cand[j]
        own = flat[i]
        x0, x1, x2, u0, u1, u2, s = X[i, 0], X[i, 1], X[i, 2], U[i, 0], U[i, 1], U[i, 2], S[i]
        best_z = np.inf if fragment[own] else _z_one(P, own, x0, x1, x2, u0, u1, u2, s)
        best_l = own
        for k in range(4):
            if not link_ok[k, i]:
                continue
            q = flat[min(max(i + steps[k], 0), last)]
            if q < 0 or q == own:
                continue
            z = _z_one(P, q, x0, x1, x2, u0, u1, u2, s)
            if z + margin < best_z and z <= thr:
                best_z = z
                best_l = q
        out[j] = best_l
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def completion_targets(flat, P, X, U, S, cand, steps, link_ok):
    """One round of the border completion's choice: the kernel of
    :func:`recognition.segmentation.reassignment._completion_targets_reference` (its arguments and results).

    Each candidate pixel's linked neighbours' patches, the one whose surface leaves it the smallest residual
    (a tie goes to the lower label); -1 and inf without a labelled linked neighbour.

    Parameters
    ----------
    flat : ndarray of shape (H*W,), int
        Labels, -1 unlabelled.
    P : ndarray of shape (G, 10)
        Each label's quadric.
    X, U : ndarray of shape (H*W, 3); S : ndarray of shape (H*W,)
        Points, unit rays and sigma of the image.
    cand : ndarray of shape (N,), int
        Candidate pixels (flat indices).
    steps : ndarray of shape (4,), int; link_ok : ndarray of shape (4, H*W), bool
        Flat offset of each link direction and whether each pixel's link that way is allowed.

    Returns
    -------
    best_l : ndarray of shape (N,), int64
    best_z : ndarray of shape (N,), sigma
    """
    n = cand.shape[0]
    last = flat.shape[0] - 1
    best_l = np.full(n, -1, np.int64)
    best_z = np.full(n, np.inf)
    for j in range(n):
        i = cand[j]
        bz, bl = np.inf, -1
        for k in range(4):
            if not link_ok[k, i]:
                continue
            q = flat[min(max(i + steps[k], 0), last)]
            if q < 0:
                continue
            z = _z_one(P, q, X[i, 0], X[i, 1], X[i, 2], U[i, 0], U[i, 1], U[i, 2], S[i])
            if z < bz or (z == bz and q < bl):
                bz, bl = z, q
        best_l[j], best_z[j] = bl, bz
    return best_l, best_z


@njit(cache=True, nogil=True, error_model="numpy")
def next_candidates(flat, cand, moved, steps, link_ok):
    """The border reassignment's next candidates: the kernel of
    :func:`recognition.segmentation.reassignment._next_candidates_reference` (its arguments and result: the
    sorted union of ``cand`` and the labelled pixels linked to a ``moved`` one)."""
    mark = np.zeros(flat.shape[0], np.bool_)
    for i in cand:
        mark[i] = True
    for i in moved:
        for k in range(4):
            if link_ok[k, i]:
                a = i + steps[k]
                if flat[a] >= 0:
                    mark[a] = True
    return np.flatnonzero(mark)


@njit(cache=True, nogil=True, error_model="numpy")
def _dot3(a0, a1, a2, b0, b1, b2):
    """``a . b`` summed as numpy's ``einsum("...k,...k->...")`` sums a contiguous 3-vector on x86-64 (two SIMD
    lanes: ``(a0 b0 + a2 b2) + a1 b1``), so that the kernels return its bits."""
    return (a0 * b0 + a2 * b2) + a1 * b1


@njit(cache=True, nogil=True, error_model="numpy")
def checked_returns(points, sigma, sigma_floor):
    """The returns of a point image and what the segmentation reads of them: the kernel of
    :func:`recognition.segmentation.edges.checked_returns_reference` (its arguments and results).

    A pixel is a return where its squared range is finite and positive and its sigma finite (a range beyond
    1e154 m, whose square overflows, is none).

    Returns
    -------
    valid : (H, W) bool; pts : (H, W, 3), NaN where no return; sigma : (H, W), floored at ``sigma_floor``, NaN
    where no return; rng : (H, W) metres, NaN where no return; rays : (H, W, 3) unit, NaN where no return
    """
    H, W = sigma.shape
    valid = np.zeros((H, W), np.bool_)
    pts = np.full((H, W, 3), np.nan)
    sig = np.full((H, W), np.nan)
    rng = np.full((H, W), np.nan)
    rays = np.full((H, W, 3), np.nan)
    for i in range(H):
        for j in range(W):
            x0, x1, x2 = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            r2 = _dot3(x0, x1, x2, x0, x1, x2)
            s = sigma[i, j]
            if not (np.isfinite(r2) and r2 > 0 and np.isfinite(s)):
                continue
            valid[i, j] = True
            sig[i, j] = max(s, sigma_floor)
            r = np.sqrt(r2)
            rng[i, j] = r
            pts[i, j, 0], pts[i, j, 1], pts[i, j, 2] = x0, x1, x2
            rays[i, j, 0], rays[i, j, 1], rays[i, j, 2] = x0 / r, x1 / r, x2 / r
    return valid, pts, sig, rng, rays


@njit(cache=True, nogil=True, error_model="numpy")
def _is_jump(ra, rb, sa, sb, d0, d1, d2, k_sigma, tan_max_incidence):
    ang = np.sqrt(_dot3(d0, d1, d2, d0, d1, d2))
    thr = k_sigma * np.sqrt(sa * sa + sb * sb) + tan_max_incidence * 0.5 * (ra + rb) * ang
    return abs(ra - rb) > thr  # NaN compares False: no jump next to a hole


@njit(cache=True, nogil=True, error_model="numpy")
def jump_pairs(rng, sigma, rays, k_sigma, tan_max_incidence):
    """Jump flags between horizontally (H, W - 1) and vertically (H - 1, W) adjacent pixels: the kernel of
    :func:`recognition.segmentation.derivatives.jump_pairs_reference` (its arguments; the angle between two
    rays is the chord ``|a - b|`` of :func:`~recognition.segmentation.derivatives.ray_angles`)."""
    H, W = rng.shape
    jump_h = np.zeros((H, max(W - 1, 0)), np.bool_)
    jump_v = np.zeros((max(H - 1, 0), W), np.bool_)
    for i in range(H):
        for j in range(W - 1):
            jump_h[i, j] = _is_jump(rng[i, j], rng[i, j + 1], sigma[i, j], sigma[i, j + 1],
                                    rays[i, j, 0] - rays[i, j + 1, 0], rays[i, j, 1] - rays[i, j + 1, 1],
                                    rays[i, j, 2] - rays[i, j + 1, 2], k_sigma, tan_max_incidence)
    for i in range(H - 1):
        for j in range(W):
            jump_v[i, j] = _is_jump(rng[i, j], rng[i + 1, j], sigma[i, j], sigma[i + 1, j],
                                    rays[i, j, 0] - rays[i + 1, j, 0], rays[i, j, 1] - rays[i + 1, j, 1],
                                    rays[i, j, 2] - rays[i + 1, j, 2], k_sigma, tan_max_incidence)
    return jump_h, jump_v


@njit(cache=True, nogil=True, error_model="numpy")
def jump_pairs_among(rng, sigma, rays, k_sigma, tan_max_incidence, among_h, among_v):
    """:func:`jump_pairs` tested only at the pairs flagged in ``among_h`` (H, W - 1) and ``among_v`` (H - 1, W):
    ``jump_pairs(...) & among``, the same test at each, the others False. With a sigma nowhere smaller than
    the one ``among`` was found with, those are all the jumps (a larger sigma only raises the threshold: in
    floating point too, every operation of it being monotonic)."""
    H, W = rng.shape
    jump_h = np.zeros((H, max(W - 1, 0)), np.bool_)
    jump_v = np.zeros((max(H - 1, 0), W), np.bool_)
    for i in range(H):
        for j in range(W - 1):
            if among_h[i, j]:
                jump_h[i, j] = _is_jump(rng[i, j], rng[i, j + 1], sigma[i, j], sigma[i, j + 1],
                                        rays[i, j, 0] - rays[i, j + 1, 0], rays[i, j, 1] - rays[i, j + 1, 1],
                                        rays[i, j, 2] - rays[i, j + 1, 2], k_sigma, tan_max_incidence)
    for i in range(H - 1):
        for j in range(W):
            if among_v[i, j]:
                jump_v[i, j] = _is_jump(rng[i, j], rng[i + 1, j], sigma[i, j], sigma[i + 1, j],
                                        rays[i, j, 0] - rays[i + 1, j, 0], rays[i, j, 1] - rays[i + 1, j, 1],
                                        rays[i, j, 2] - rays[i + 1, j, 2], k_sigma, tan_max_incidence)
    return jump_h, jump_v

@njit(cache=True, nogil=True, error_model="numpy")
def window_inputs(points, sigma):
    """The pixels with a return and the point image with 0 elsewhere, for the derivatives: the kernel of
    :func:`recognition.segmentation.derivatives._window_inputs_reference` (``points`` (H, W, 3), ``sigma``
    (H, W); returns ``valid`` (H, W) bool, where every coordinate and sigma are finite, and the points
    (H, W, 3))."""
    H, W = sigma.shape
    valid = np.zeros((H, W), np.bool_)
    pts0 = np.zeros((H, W, 3))
    for i in range(H):
        for j in range(W):
            x0, x1, x2 = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            if np.isfinite(x0) and np.isfinite(x1) and np.isfinite(x2) and np.isfinite(sigma[i, j]):
                valid[i, j] = True
                pts0[i, j, 0], pts0[i, j, 1], pts0[i, j, 2] = x0, x1, x2
    return valid, pts0


@njit(cache=True, nogil=True, error_model="numpy")
def blank_outside(full, images):
    """NaN in each (H, W, 3) image of ``images`` where ``full`` (H, W) is False, in place: ``a[~full] = np.nan``
    for each ``a`` (its numpy reference)."""
    H, W = full.shape
    for a in images:
        for i in range(H):
            for j in range(W):
                if not full[i, j]:
                    a[i, j, 0] = a[i, j, 1] = a[i, j, 2] = np.nan


@njit(cache=True, nogil=True, error_model="numpy")
def curvatures(points, sigma, Pu, Pv, Puu, Puv, Pvv, var_u, var_v, cov2):
    """Mean and Gaussian curvature with their propagated sigmas, the unit normal facing the sensor and its
    angular sigma, per pixel: the kernel of
    :func:`recognition.segmentation.curvature.curvatures_reference` (its arguments and results, its formulas
    operation by operation)."""
    Hn, Wn = sigma.shape
    Hc = np.empty((Hn, Wn))
    K = np.empty((Hn, Wn))
    sH = np.empty((Hn, Wn))
    sK = np.empty((Hn, Wn))
    nrm = np.empty((Hn, Wn, 3))
    sn = np.empty((Hn, Wn))
    for i in range(Hn):
        for j in range(Wn):
            a0, a1, a2 = Pu[i, j, 0], Pu[i, j, 1], Pu[i, j, 2]
            b0, b1, b2 = Pv[i, j, 0], Pv[i, j, 1], Pv[i, j, 2]
            E = _dot3(a0, a1, a2, a0, a1, a2)
            F = _dot3(a0, a1, a2, b0, b1, b2)
            G = _dot3(b0, b1, b2, b0, b1, b2)
            c0 = a1 * b2 - a2 * b1
            c1 = a2 * b0 - a0 * b2
            c2 = a0 * b1 - a1 * b0
            cn = np.sqrt(_dot3(c0, c1, c2, c0, c1, c2))
            n0, n1, n2 = c0 / cn, c1 / cn, c2 / cn
            x0, x1, x2 = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            if _dot3(n0, n1, n2, x0, x1, x2) > 0:
                n0, n1, n2 = -n0, -n1, -n2
            nrm[i, j, 0], nrm[i, j, 1], nrm[i, j, 2] = n0, n1, n2
            L = _dot3(Puu[i, j, 0], Puu[i, j, 1], Puu[i, j, 2], n0, n1, n2)
            M = _dot3(Puv[i, j, 0], Puv[i, j, 1], Puv[i, j, 2], n0, n1, n2)
            N = _dot3(Pvv[i, j, 0], Pvv[i, j, 1], Pvv[i, j, 2], n0, n1, n2)
            det = E * G - F * F
            K[i, j] = (L * N - M * M) / det
            Hc[i, j] = (E * N - 2.0 * F * M + G * L) / (2.0 * det)
            r = np.sqrt(_dot3(x0, x1, x2, x0, x1, x2))
            cs = _dot3(x0 / r, x1 / r, x2 / r, n0, n1, n2)
            s = sigma[i, j]
            s2 = s * s * (cs * cs)
            cLL, cMM, cNN = cov2[i, j, 0] * s2, cov2[i, j, 1] * s2, cov2[i, j, 2] * s2
            cLM, cLN, cMN = cov2[i, j, 3] * s2, cov2[i, j, 4] * s2, cov2[i, j, 5] * s2
            hL, hM, hN = G / (2.0 * det), -F / det, E / (2.0 * det)
            vH = (hL * hL * cLL + hM * hM * cMM + hN * hN * cNN
                  + 2.0 * (hL * hM * cLM + hL * hN * cLN + hM * hN * cMN))
            kL, kM, kN = N / det, -2.0 * M / det, L / det
            vK = (kL * kL * cLL + kM * kM * cMM + kN * kN * cNN
                  + 2.0 * (kL * kM * cLM + kL * kN * cLN + kM * kN * cMN))
            vK += (cLL * cNN + 2.0 * cMM * cMM) / (det * det)
            sH[i, j] = np.sqrt(vH)
            sK[i, j] = np.sqrt(vK)
            sn[i, j] = np.sqrt(s2 * (var_u[i, j] / E + var_v[i, j] / G))
    return Hc, K, sH, sK, nrm, sn


@njit(cache=True, nogil=True, error_model="numpy")
def _group_mean(X, ix, lo, hi):
    """Mean (3 floats) of the points ``X[ix[lo:hi]]``, summed in index order."""
    m0 = m1 = m2 = 0.0
    for t in range(lo, hi):
        i = ix[t]
        m0 += X[i, 0]
        m1 += X[i, 1]
        m2 += X[i, 2]
    c = hi - lo
    return m0 / c, m1 / c, m2 / c


@njit(cache=True, nogil=True, error_model="numpy")
def _plane_fit(X, U, S, ix, P, z, g, lo, hi):
    """Total-least-squares plane of the points ``X[ix[lo:hi]]`` into ``P[g]``, their ray residuals (sigma) into
    ``z[lo:hi]``; NaN / inf under 3 points."""
    c = hi - lo
    if c < 3:
        P[g, :] = np.nan
        z[lo:hi] = np.inf
        return
    m0, m1, m2 = _group_mean(X, ix, lo, hi)
    C = np.zeros((3, 3))
    for t in range(lo, hi):
        i = ix[t]
        d0, d1, d2 = X[i, 0] - m0, X[i, 1] - m1, X[i, 2] - m2
        C[0, 0] += d0 * d0
        C[0, 1] += d0 * d1
        C[0, 2] += d0 * d2
        C[1, 1] += d1 * d1
        C[1, 2] += d1 * d2
        C[2, 2] += d2 * d2
    C[1, 0], C[2, 0], C[2, 1] = C[0, 1], C[0, 2], C[1, 2]
    _, V = np.linalg.eigh(C)
    n0, n1, n2 = V[0, 0], V[1, 0], V[2, 0]
    P[g, :] = 0.0
    P[g, 6], P[g, 7], P[g, 8] = n0, n1, n2
    P[g, 9] = -(n0 * m0 + n1 * m1 + n2 * m2)
    for t in range(lo, hi):
        i = ix[t]
        f = (X[i, 0] - m0) * n0 + (X[i, 1] - m1) * n1 + (X[i, 2] - m2) * n2
        gr = max(abs(U[i, 0] * n0 + U[i, 1] * n1 + U[i, 2] * n2), MIN_GRAZING)
        v = abs(f) / (gr * S[i])
        z[t] = v if np.isfinite(v) else np.inf


@njit(cache=True, nogil=True, error_model="numpy")
def _monomials(y0, y1, y2, m):
    m[0], m[1], m[2] = y0 * y0, y1 * y1, y2 * y2
    m[3], m[4], m[5] = 2 * y0 * y1, 2 * y0 * y2, 2 * y1 * y2
    m[6], m[7], m[8], m[9] = y0, y1, y2, 1.0


@njit(cache=True, nogil=True, error_model="numpy")
def _quadric_fit(X, U, S, ix, P, z, g, lo, hi, taubin_map, undetermined_below):
    """Taubin quadric of the points ``X[ix[lo:hi]]`` (unit-norm algebraic fit where Taubin's is undefined) into
    ``P[g]`` (metres), their ray residuals (sigma) into ``z[lo:hi]``. Returns 0, or 1 when the points determine
    no quadric (the caller fits a plane), or 2 when the Taubin system is numerically singular."""
    c = hi - lo
    m0, m1, m2 = _group_mean(X, ix, lo, hi)
    ss = 0.0
    for t in range(lo, hi):
        i = ix[t]
        d0, d1, d2 = X[i, 0] - m0, X[i, 1] - m1, X[i, 2] - m2
        ss += d0 * d0 + d1 * d1 + d2 * d2
    scale = np.sqrt(ss / c)
    if not scale > 0:
        scale = 1.0
    M = np.zeros((10, 10))
    mono = np.empty(10)
    for t in range(lo, hi):
        i = ix[t]
        _monomials((X[i, 0] - m0) / scale, (X[i, 1] - m1) / scale, (X[i, 2] - m2) / scale, mono)
        for a in range(10):
            ma = mono[a]
            for b in range(a, 10):
                M[a, b] += ma * mono[b]
    for a in range(10):
        for b in range(a):
            M[a, b] = M[b, a]
    tr = 0.0
    for a in range(10):
        tr += M[a, a]
    if not tr > 0:
        return 1
    if np.linalg.eigvalsh(M / tr)[1] < undetermined_below:
        return 1
    N9 = (M[6:, 6:].copy().reshape(16) @ taubin_map).reshape(9, 9)
    evn = np.linalg.eigvalsh(N9)
    m99 = M[9, 9]
    pn = np.empty(10)
    if evn[0] > 1e-12 * max(evn[8], 1e-300) and m99 > 0:
        Sg = M[:9, :9] - np.outer(M[:9, 9], M[9, :9]) / m99
        try:
            L = np.linalg.cholesky(N9)
        except Exception:  # noqa: BLE001 - numba catches no narrower class; only LinAlgError can come here
            return 2
        A = np.linalg.solve(L, Sg)
        A = np.linalg.solve(L, A.T.copy())
        _, W = np.linalg.eigh(0.5 * (A + A.T))
        q = np.linalg.solve(L.T.copy(), W[:, 0].copy())
        pn[:9] = q
        pn[9] = -(M[9, :9] @ q) / m99
    else:
        _, V = np.linalg.eigh(M)
        pn[:] = V[:, 0]
    pn /= np.linalg.norm(pn)
    for t in range(lo, hi):
        i = ix[t]
        y0, y1, y2 = (X[i, 0] - m0) / scale, (X[i, 1] - m1) / scale, (X[i, 2] - m2) / scale
        _monomials(y0, y1, y2, mono)
        f = 0.0
        for a in range(10):
            f += mono[a] * pn[a]
        g0 = 2 * (pn[0] * y0 + pn[3] * y1 + pn[4] * y2) + pn[6]
        g1 = 2 * (pn[3] * y0 + pn[1] * y1 + pn[5] * y2) + pn[7]
        g2 = 2 * (pn[4] * y0 + pn[5] * y1 + pn[2] * y2) + pn[8]
        gr = abs(g0 * U[i, 0] + g1 * U[i, 1] + g2 * U[i, 2])
        floor = MIN_GRAZING * np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        v = scale * abs(f) / (max(gr, floor) * S[i])
        z[t] = v if np.isfinite(v) else np.inf
    # back to metres: A / s², b / s - 2 A m / s², m'Am / s² - b'm / s + c
    is2 = 1.0 / (scale * scale)
    a0 = pn[0] * m0 + pn[3] * m1 + pn[4] * m2
    a1 = pn[3] * m0 + pn[1] * m1 + pn[5] * m2
    a2 = pn[4] * m0 + pn[5] * m1 + pn[2] * m2
    for a in range(6):
        P[g, a] = pn[a] * is2
    P[g, 6] = pn[6] / scale - 2.0 * a0 * is2
    P[g, 7] = pn[7] / scale - 2.0 * a1 * is2
    P[g, 8] = pn[8] / scale - 2.0 * a2 * is2
    P[g, 9] = (m0 * a0 + m1 * a1 + m2 * a2) * is2 - (pn[6] * m0 + pn[7] * m1 + pn[8] * m2) / scale + pn[9]
    nrm = 0.0
    for a in range(10):
        nrm += P[g, a] * P[g, a]
    nrm = np.sqrt(nrm)
    for a in range(10):
        P[g, a] /= nrm
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def quick_fits(X, U, S, ix, starts, counts, planar, taubin_map, undetermined_below):
    """The quick fits of many groups of points: the kernel of
    :func:`recognition.segmentation.quick_fits._quick_fits_reference`.

    Group ``g`` is the points ``X[ix[starts[g]:starts[g] + counts[g]]]``; it gets a total-least-squares plane
    when ``planar[g]``, when it has fewer than 10 points or when they determine no quadric (the second-smallest
    eigenvalue of their normalised moments under ``undetermined_below``), a Taubin quadric otherwise.

    Returns
    -------
    P : ndarray of shape (G, 10)
        Each group's surface, metres, unit norm (NaN under 3 points).
    z : ndarray of shape (len(ix),)
        Each point's ray residual to its group's surface, in its sigmas (inf where undefined).
    singular : ndarray of shape (G,), bool
        Groups whose Taubin system was numerically singular (their P and z are not set: fit them otherwise).
    """
    G = starts.shape[0]
    P = np.full((G, 10), np.nan)
    z = np.full(ix.shape[0], np.inf)
    singular = np.zeros(G, np.bool_)
    for g in range(G):
        lo, hi = starts[g], starts[g] + counts[g]
        if hi == lo:
            continue
        if planar[g] or hi - lo < 10:
            _plane_fit(X, U, S, ix, P, z, g, lo, hi)
            continue
        status = _quadric_fit(X, U, S, ix, P, z, g, lo, hi, taubin_map, undetermined_below)
        if status == 1:
            _plane_fit(X, U, S, ix, P, z, g, lo, hi)
        elif status == 2:
            singular[g] = True
    return P, z, singular


@njit(cache=True, nogil=True, error_model="numpy")
def _spd_inverse6(M, out, L, Li):
    """Inverse of a symmetric positive-definite 6 x 6 matrix by Cholesky, the operations of
    :func:`recognition.segmentation.derivatives.spd_inverse` (sums in index order) for one matrix; ``L`` and
    ``Li`` (6, 6) are work space (the factor and its inverse)."""
    k = 6
    L[:, :] = 0.0
    for j in range(k):
        s = 0.0
        for t in range(j):
            s = s + L[j, t] ** 2 if t else L[j, t] ** 2
        L[j, j] = np.sqrt(M[j, j] - s)
        for i in range(j + 1, k):
            s = 0.0
            for t in range(j):
                s = s + L[i, t] * L[j, t] if t else L[i, t] * L[j, t]
            L[i, j] = (M[i, j] - s) / L[j, j]
    Li[:, :] = 0.0
    for i in range(k):
        Li[i, i] = 1.0 / L[i, i]
        for j in range(i):
            s = 0.0
            for t in range(j, i):
                s = s + L[i, t] * Li[t, j] if t > j else L[i, t] * Li[t, j]
            Li[i, j] = -s / L[i, i]
    for i in range(k):
        for j in range(i + 1):
            s = 0.0
            for t in range(i, k):
                s = s + Li[t, i] * Li[t, j] if t > i else Li[t, i] * Li[t, j]
            out[i, j] = s
            out[j, i] = s


@njit(cache=True, nogil=True, error_model="numpy")
def masked_fits(points, sigma, rng, rows, cols, window, jump_k, jump_tan, alpha, min_support, max_var_uu,
                Pu, Pv, Puu, Puv, Pvv, var_u, var_v, cov2):
    """Per-pixel masked quadratic fits of ``P(u, v)`` at the pixels ``(rows, cols)``, written into the outputs
    in place: the kernel of :func:`recognition.segmentation.derivatives._masked_fits_reference`.

    Each window pixel takes part when its range is within the jump allowance of the centre's
    (``jump_k sqrt(sigma_c² + sigma²) + jump_tan r_c alpha |offset|``, ``alpha`` the image's adjacent-ray
    angle); with at least ``min_support`` of them on at least 3 rows and 3 columns, the 6 x 6 normal equations
    (a 1e-12 ridge) give the derivatives and their unit-noise covariances, kept where the second derivatives'
    variances are within ``max_var_uu``. ``rng`` is NaN where there is no return.
    """
    H, W = rng.shape
    h = window // 2
    nw = window * window
    du = np.empty(nw, np.int64)
    dv = np.empty(nw, np.int64)
    for w in range(nw):
        dv[w] = w // window - h
        du[w] = w % window - h
    Xd = np.empty((nw, 6))
    ang = np.empty(nw)  # each window pixel's ray angle to the centre
    for w in range(nw):
        a, b = float(du[w]), float(dv[w])
        Xd[w, 0], Xd[w, 1], Xd[w, 2], Xd[w, 3], Xd[w, 4], Xd[w, 5] = 1.0, a, b, a * a, a * b, b * b
        ang[w] = alpha * np.hypot(du[w], dv[w])
    # the products of the design's columns, upper triangle (a <= b) in row order: M is their masked sum, and
    # its lower triangle (the same products, commuted) the mirror of the upper
    XX = np.empty((nw, 21))
    for w in range(nw):
        t = 0
        for a in range(6):
            for b in range(a, 6):
                XX[w, t] = Xd[w, a] * Xd[w, b]
                t += 1
    M = np.empty((6, 6))
    Mu = np.empty(21)
    inv = np.empty((6, 6))
    work_l, work_li = np.empty((6, 6)), np.empty((6, 6))
    rhs = np.empty((6, 3))
    mf = np.zeros(nw, np.bool_)
    row_hit = np.zeros(window, np.bool_)
    col_hit = np.zeros(window, np.bool_)
    J = (2.0, 1.0, 2.0)
    for p in range(rows.shape[0]):
        r, c = rows[p], cols[p]
        rc = rng[r, c]
        sc2 = sigma[r, c] ** 2
        tan_r = jump_tan * rc
        count = 0
        row_hit[:] = False
        col_hit[:] = False
        for w in range(nw):
            rr, cc = r + dv[w], c + du[w]
            mf[w] = False
            if rr < 0 or rr >= H or cc < 0 or cc >= W:
                continue
            thr = jump_k * np.sqrt(sc2 + sigma[rr, cc] ** 2) + tan_r * ang[w]
            if abs(rng[rr, cc] - rc) <= thr:
                mf[w] = True
                count += 1
                row_hit[dv[w] + h] = True
                col_hit[du[w] + h] = True
        if count < min_support or row_hit.sum() < 3 or col_hit.sum() < 3:
            continue
        Mu[:] = 0.0
        rhs[:, :] = 0.0
        x0, x1, x2 = points[r, c, 0], points[r, c, 1], points[r, c, 2]
        for w in range(nw):
            if not mf[w]:
                continue
            rr, cc = r + dv[w], c + du[w]
            e0, e1, e2 = points[rr, cc, 0] - x0, points[rr, cc, 1] - x1, points[rr, cc, 2] - x2
            for t in range(21):
                Mu[t] += XX[w, t]
            for a in range(6):
                xa = Xd[w, a]
                rhs[a, 0] += e0 * xa
                rhs[a, 1] += e1 * xa
                rhs[a, 2] += e2 * xa
        t = 0
        for a in range(6):
            for b in range(a, 6):
                M[a, b] = M[b, a] = Mu[t]
                t += 1
        tr = 0.0
        for a in range(6):
            tr += M[a, a]
        for a in range(6):
            M[a, a] += 1e-12 * tr
        _spd_inverse6(M, inv, work_l, work_li)
        c00 = inv[3, 3] * J[0] * J[0]
        c22 = inv[5, 5] * J[2] * J[2]
        if not (c00 <= max_var_uu and c22 <= max_var_uu):
            continue
        for k in range(3):
            b1 = b2 = b3 = b4 = b5 = 0.0
            for t in range(6):
                b1 += inv[1, t] * rhs[t, k]
                b2 += inv[2, t] * rhs[t, k]
                b3 += inv[3, t] * rhs[t, k]
                b4 += inv[4, t] * rhs[t, k]
                b5 += inv[5, t] * rhs[t, k]
            Pu[r, c, k] = b1
            Pv[r, c, k] = b2
            Puu[r, c, k] = 2.0 * b3
            Puv[r, c, k] = b4
            Pvv[r, c, k] = 2.0 * b5
        var_u[r, c] = inv[1, 1]
        var_v[r, c] = inv[2, 2]
        cov2[r, c, 0] = c00
        cov2[r, c, 1] = inv[4, 4] * J[1] * J[1]
        cov2[r, c, 2] = c22
        cov2[r, c, 3] = inv[3, 4] * J[0] * J[1]
        cov2[r, c, 4] = inv[3, 5] * J[0] * J[2]
        cov2[r, c, 5] = inv[4, 5] * J[1] * J[2]


@njit(cache=True, nogil=True, error_model="numpy")
def _correlate_nearest(line, n, h, w, kind, out):
    """``scipy.ndimage.correlate1d(x, w, mode="nearest")`` of the ``n`` values ``x = line[h:h + n]`` (``line``
    already extended by ``h`` copies of its end values on both sides) into ``out[:n]``, summed as ndimage sums
    an odd kernel: ``kind`` 1 symmetric (``x[i] w[h] + sum (x[i + j] + x[i - j]) w[h + j]``), -1 antisymmetric
    (``x[i] w[h] + sum (x[i + j] - x[i - j]) w[h + j]``), 0 in index order; ``j`` from ``-h`` to -1."""
    for i in range(n):
        c = i + h
        acc = line[c] * w[h]
        if kind > 0:
            for jj in range(-h, 0):
                acc += (line[c + jj] + line[c - jj]) * w[h + jj]
        elif kind < 0:
            for jj in range(-h, 0):
                acc += (line[c + jj] - line[c - jj]) * w[h + jj]
        else:
            acc = line[c + h] * w[2 * h]
            for jj in range(-h, h):
                acc += line[c + jj] * w[h + jj]
        out[i] = acc


@njit(cache=True, nogil=True, error_model="numpy")
def _extend(line, n, h):
    """Extend ``line[h:h + n]`` by ``h`` copies of its end values on both sides (ndimage's ``nearest``)."""
    for k in range(h):
        line[k] = line[h]
        line[h + n + k] = line[h + n - 1]


@njit(cache=True, nogil=True, error_model="numpy")
def savgol_derivatives(points0, box, d1, d2, kinds):
    """Separable Savitzky-Golay derivatives ``(Pu, Pv, Puu, Puv, Pvv)``, each (H, W, 3), of a NaN-free point
    image: the kernel of :func:`recognition.segmentation.derivatives._full_window_derivatives_reference`
    (rows filtered with ``box``, ``d1``, ``d2``, then columns; ``kinds`` the symmetry of each kernel, as
    ``scipy.ndimage`` finds it)."""
    H, W = points0.shape[0], points0.shape[1]
    h = box.shape[0] // 2
    rows = np.empty((3, 3, H, W))  # (box, d1, d2 along the rows, coordinate, row, column)
    line = np.empty(W + 2 * h)
    out = np.empty(W)
    kernels = (box, d1, d2)
    for c in range(3):
        for i in range(H):
            for j in range(W):
                line[h + j] = points0[i, j, c]
            _extend(line, W, h)
            for k in range(3):
                _correlate_nearest(line, W, h, kernels[k], kinds[k], out)
                rows[k, c, i, :] = out[:W]
    Pu = np.empty((H, W, 3))
    Pv = np.empty((H, W, 3))
    Puu = np.empty((H, W, 3))
    Puv = np.empty((H, W, 3))
    Pvv = np.empty((H, W, 3))
    # (source along the rows, kernel down the columns, target, factor)
    plan = ((1, 0, 0, 1.0), (0, 1, 1, 1.0), (2, 0, 2, 2.0), (1, 1, 3, 1.0), (0, 2, 4, 2.0))
    targets = (Pu, Pv, Puu, Puv, Pvv)
    acc = np.empty(W)
    for src, ker, tgt, factor in plan:
        T, w, kind = targets[tgt], kernels[ker], kinds[ker]
        for c in range(3):
            R = rows[src, c]
            for i in range(H):  # down the columns, a row of outputs at a time (contiguous)
                for j in range(W):
                    acc[j] = R[i, j] * w[h]
                for jj in range(-h, 0):
                    a, b = R[max(i + jj, 0)], R[min(i - jj, H - 1)]
                    wj = w[h + jj]
                    if kind > 0:
                        for j in range(W):
                            acc[j] += (a[j] + b[j]) * wj
                    else:
                        for j in range(W):
                            acc[j] += (a[j] - b[j]) * wj
                for j in range(W):
                    T[i, j, c] = factor * acc[j]
    return Pu, Pv, Puu, Puv, Pvv


@functools.cache
def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny input, so that no first call is timed; once per
    process (later calls return at once)."""
    P = np.zeros((1, 10))
    P[0, 8], P[0, 9] = 1.0, -1.0
    X = np.zeros((4, 3))
    X[:, 2] = 1.0
    U = X.copy()
    S = np.full(4, 0.01)
    lab = np.zeros(4, np.int64)
    ray_z_by_label(P, lab, X, U, S)
    for dtype in (np.int32, np.int64):  # label images of both widths
        group_order(np.array([0, -1, 0, 0], dtype), 1)
        fragment_flags(np.array([[0, -1], [0, 0]], dtype), np.ones((2, 2)), np.zeros((2, 1), np.bool_),
                       np.zeros((1, 2), np.bool_), 1)
        for valid in (np.ones((2, 2), np.bool_), np.ones((4, 4), np.bool_)[::2, ::2]):  # a coarse grid's: strided
            enclosed_targets(np.array([[0, -1], [0, 0]], dtype), valid, np.zeros((2, 1), np.bool_),
                             np.zeros((1, 2), np.bool_), 1, 10)
        peel_weak(np.array([[0, -1], [0, 0]], dtype), np.zeros((2, 1), np.bool_), np.zeros((1, 2), np.bool_), 1,
                  200, 0.1, 0.5)
    class_counts(lab, lab, np.array([2, 2], np.int64))
    flat = np.array([0, -1, -1, -1], np.int64)
    steps = np.array([-1, 1, -2, 2], np.int64)
    ok = np.zeros((4, 4), np.bool_)
    ok[0, 1:] = True
    grow(flat, P, X, U, S, steps, ok, 2, 2, 3, 3.0)
    reassign_targets(flat, P, X, U, S, lab, steps, ok, np.zeros(1, np.bool_), 1.0, 3.0)
    next_candidates(flat, lab, lab, steps, ok)
    completion_targets(flat, P, X, U, S, lab, steps, ok)
    jump_pairs(np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2, 3)), 3.0, 2.0)
    jump_pairs_among(np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2, 3)), 3.0, 2.0, *jump_pairs(
        np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2, 3)), 3.0, 2.0))
    one, three = np.ones((1, 1)), np.ones((1, 1, 3))
    checked_returns(three, one, 1e-4)
    window_inputs(three, one)
    window_inputs(np.ones((2, 2, 3))[::2, ::2], np.ones((2, 2))[::2, ::2])  # a coarse grid's strided views
    blank_outside(np.zeros((1, 1), np.bool_), (three.copy(),) * 5)
    w = np.array([1.0, 1.0, 1.0]) / 3
    savgol_derivatives(np.ones((3, 3, 3)), w, np.array([-0.5, 0.0, 0.5]), w, np.array([1, -1, 1]))
    curvatures(three, one, three, three, three, three, three, one, one, np.ones((1, 1, 6)))
    o3, o1, o6 = np.zeros((5, 5, 3)), np.zeros((5, 5)), np.zeros((5, 5, 6))
    masked_fits(np.ones((5, 5, 3)), o1 + 0.01, o1 + 1.0, np.array([2]), np.array([2]), 3, 3.0, 2.0, 0.01, 9, 1e3,
                o3, o3.copy(), o3.copy(), o3.copy(), o3.copy(), o1.copy(), o1.copy(), o6)
    from .quick_fits import _TAUBIN_MAP, UNDETERMINED_QUADRIC

    gen = np.random.default_rng(0)
    Xq = gen.normal(size=(12, 3))
    Xq[:, 2] += 3.0
    quick_fits(Xq, Xq / np.linalg.norm(Xq, axis=1)[:, None], np.full(12, 0.01), np.arange(12), np.zeros(2, np.int64),
               np.array([12, 0]), np.zeros(2, np.bool_), _TAUBIN_MAP, UNDETERMINED_QUADRIC)
