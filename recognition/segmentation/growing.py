"""Segmentation step 5, growing (section 3 of Fillatreau & Fisher: patches are grown by surface fitting):
seeds grow into adjacent unlabelled pixels within ``grow_k`` sigma of their fitted surface, restarting from the
seeds after every refit (step 8); leftover connected pieces become patches of their own."""

from __future__ import annotations

import numpy as np

from . import kernels
from .grid import _groups, _link_components, _State
from .quick_fits import _fit_groups, _ray_z
from .seeds import _split_bad_seeds
from .types import SegmentationParams


def _grow_patches(seeds: np.ndarray, st: _State, params: SegmentationParams, valid: np.ndarray, links,
                  jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Step 5: grow the seeds of one grid (``links``: :func:`.grid._neighbour_links` of the grid) and give the
    leftover pixels patches of their own; returns the labels."""
    labels = seeds.copy()
    P = None
    n_lab = int(seeds.max()) + 1
    for _ in range(params.grow_rounds if n_lab > 0 else 0):
        # refit on the grown patches (trimmed), then grow again from the seeds: pixels that only fitted the
        # seed's extrapolated surface (an elbow next to a pipe seed) are released when the refit rejects them
        P = _fit_groups(_groups(labels), st, params, n_lab, trim=2.0 * params.grow_k)
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
            P = _fit_groups(_groups(labels), st, params, int(labels.max()) + 1)
            _grow(labels, P, st, links, params.max_grow_iterations, params.grow_k)
    return labels


def _grow(labels: np.ndarray, P: np.ndarray, st: _State, links, max_iter: int, thr: float) -> None:
    """Grow labelled patches into unlabelled valid pixels whose residual fits (in place): the compiled
    :func:`.kernels.grow`, round for round :func:`_grow_reference`."""
    H, W = labels.shape
    flat = labels.reshape(-1).astype(np.int64)
    steps = np.array([dr * W + dc for dr, dc, _ in links], np.int64)
    link_ok = np.stack([ok.ravel() for _, _, ok in links])
    kernels.grow(flat, np.ascontiguousarray(P, np.float64), st.X, st.U, st.S, steps, link_ok, H, W, max_iter,
                 float(thr))
    labels[...] = flat.reshape(H, W)


def _grow_reference(labels: np.ndarray, P: np.ndarray, st: _State, links, max_iter: int, thr: float) -> None:
    """Grow labelled patches into unlabelled valid pixels whose residual fits (in place); numpy, the reference
    of :func:`.kernels.grow`."""
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
                z[k, m] = _ray_z(P.T.take(nl[k, m], axis=1), x[sel].T.copy(), u[sel], s[sel])
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


def _tile_small_leftovers(comp: np.ndarray, st: _State, params: SegmentationParams) -> np.ndarray:
    """Leftover components below ``max_tiled_leftover`` pixels (all of them when it is None) go through
    :func:`_split_bad_seeds` (pieces under ``min_seed_pixels`` are released); labels stay 0..n-1, -1 elsewhere."""
    if not (comp >= 0).any():
        return comp
    sizes = np.bincount(comp[comp >= 0])
    small = comp >= 0
    if params.max_tiled_leftover is not None:
        small &= sizes[np.maximum(comp, 0)] < params.max_tiled_leftover
    if not small.any():
        return comp
    tiled = _split_bad_seeds(np.where(small, comp, -1).astype(np.int32), st, params)
    n_t = int(tiled.max()) + 1
    out = np.where(small, tiled, np.where(comp >= 0, comp + n_t, -1))
    used = np.unique(out[out >= 0])
    remap = np.full(int(out.max()) + 1 if used.size else 1, -1, np.int64)
    remap[used] = np.arange(used.size)
    return np.where(out >= 0, remap[np.maximum(out, 0)], -1)
