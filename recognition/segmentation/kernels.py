"""Compiled kernels (numba) of the segmentation's per-pixel loops, each the exact equal of a numpy reference.

Issue 35: a frame spent its time in some 126 k small numpy calls (region growing one front at a time, the
residual of every candidate pixel to every neighbouring patch, pixel groups by label). These kernels do the
same arithmetic in the same order as their references, operation by operation (numba does not contract
``a * b + c`` into a fused multiply-add without ``fastmath``), so they return the same bits and the
segmenter's labels stay the same (``labels sha1`` of ``python -m harness.bench_segmentation``). The references
stay beside them and the tests hold the two equal on random inputs (``tests/recognition/test_kernels.py``).

Compiled once per machine: ``cache=True`` keeps the machine code in ``__pycache__``, so a new process (a forked
trial, a benchmark worker) loads it instead of compiling again; :func:`warm_up` compiles them all at once, on
a tiny input, for the callers that time frames.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from recognition.fitting import MIN_GRAZING

__all__ = ["curvatures", "grow", "group_order", "jump_pairs", "ray_z_by_label", "warm_up"]


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
    if z != z or z == np.inf or z == -np.inf:
        return np.inf
    return z


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
    flat : ndarray of shape (N,), int
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
def _dot3(a0, a1, a2, b0, b1, b2):
    """``a . b`` summed as numpy's ``einsum("...k,...k->...")`` sums a contiguous 3-vector on x86-64 (two SIMD
    lanes: ``(a0 b0 + a2 b2) + a1 b1``), so that the kernels return its bits."""
    return (a0 * b0 + a2 * b2) + a1 * b1


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
        for j in range(W):
            ra, sa = rng[i, j], sigma[i, j]
            if j + 1 < W:
                jump_h[i, j] = _is_jump(ra, rng[i, j + 1], sa, sigma[i, j + 1], rays[i, j, 0] - rays[i, j + 1, 0],
                                        rays[i, j, 1] - rays[i, j + 1, 1], rays[i, j, 2] - rays[i, j + 1, 2],
                                        k_sigma, tan_max_incidence)
            if i + 1 < H:
                jump_v[i, j] = _is_jump(ra, rng[i + 1, j], sa, sigma[i + 1, j], rays[i, j, 0] - rays[i + 1, j, 0],
                                        rays[i, j, 1] - rays[i + 1, j, 1], rays[i, j, 2] - rays[i + 1, j, 2],
                                        k_sigma, tan_max_incidence)
    return jump_h, jump_v


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


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny input, so that no first call is timed."""
    P = np.zeros((1, 10))
    P[0, 8], P[0, 9] = 1.0, -1.0
    X = np.zeros((4, 3))
    X[:, 2] = 1.0
    U = X.copy()
    S = np.full(4, 0.01)
    lab = np.zeros(4, np.int64)
    ray_z_by_label(P, lab, X, U, S)
    group_order(np.array([0, -1, 0, 0], np.int64), 1)
    flat = np.array([0, -1, -1, -1], np.int64)
    steps = np.array([-1, 1, -2, 2], np.int64)
    ok = np.zeros((4, 4), np.bool_)
    ok[0, 1:] = True
    grow(flat, P, X, U, S, steps, ok, 2, 2, 3, 3.0)
    jump_pairs(np.ones((2, 2)), np.ones((2, 2)), np.ones((2, 2, 3)), 3.0, 2.0)
    one, three = np.ones((1, 1)), np.ones((1, 1, 3))
    curvatures(three, one, three, three, three, three, three, one, one, np.ones((1, 1, 6)))
