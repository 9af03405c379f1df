"""Segmentation step 5, seeds (section 3 of Fillatreau & Fisher: a patch is a maximal connected set of
pixels of one H-K class, after Besl & Jain): class components that survive an erosion, cut along wide-baseline
creases or into tiles when one surface does not fit them (step 8)."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from .grid import _groups, _is_planar_counts, _rms, _split_disconnected, _State, _structure, _subsample
from .quick_fits import _fit_groups, _group_sums, _pixel_residuals, _quick_fits
from .types import SegmentationParams, SurfaceType


def _seeds(hk: np.ndarray, edges: np.ndarray, wide: np.ndarray, st: _State, params: SegmentationParams) -> np.ndarray:
    """Step 5: the seeds of one grid, labelled 0..n-1 (-1 elsewhere), cut along creases (and, with
    ``split_seeds``, into tiles) where one surface does not fit them."""
    seeds = _seed_labels(hk, edges, params)
    seeds = _split_at_creases(seeds, wide, st, params)
    if params.split_seeds is True:  # ("auto" is resolved by segment())
        seeds = _split_bad_seeds(seeds, st, params)
    return seeds


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
    P = _fit_groups(groups, st, params, n, trim=2.0 * params.grow_k)
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
        sub = _subsample(idx, params.max_fit_points)
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
    P = _fit_groups(groups, st, params, n, trim=2.0 * params.grow_k)
    W = seeds.shape[1]
    t = params.seed_tile
    out = seeds.copy().ravel()
    labs = [lab for lab, idx in groups.items() if idx.size >= 2 * params.min_seed_pixels]
    bad = []
    if labs:  # the seeds' RMS residuals to their fits, in one batch
        subs = [_subsample(groups[lab], params.max_fit_points) for lab in labs]
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
