"""What the segmentation's steps share: the arrays of one sampling grid (:class:`_Grid`), the flattened
points of the fits (:class:`_State`), pixel groups, neighbour links, adjacency and connected pieces."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from . import kernels
from .derivatives import jump_pairs
from .types import SegmentationParams


@dataclass(frozen=True)
class _Grid:
    """The arrays of one sampling grid of the image: the image itself, or every ``d``-th pixel of it.

    ``points`` (H, W, 3) and ``rays`` (H, W, 3) NaN where no return, ``sigma`` (H, W) the range sigma the
    thresholds use (self-calibrated, NaN where no return), ``valid`` (H, W) returns, ``ranges`` (H, W),
    ``jump_h`` (H, W - 1) and ``jump_v`` (H - 1, W) the jump pairs along rows and columns.
    """

    points: np.ndarray
    sigma: np.ndarray
    valid: np.ndarray
    ranges: np.ndarray
    rays: np.ndarray
    jump_h: np.ndarray
    jump_v: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.sigma.shape

    def decimated(self, d: int, params: SegmentationParams) -> _Grid:
        """Every ``d``-th pixel along rows and columns, with its own jump pairs."""
        sl = (slice(0, None, d), slice(0, None, d))
        pts, sig, rng, rays = self.points[sl], self.sigma[sl], self.ranges[sl], self.rays[sl]
        jump_h, jump_v = jump_pairs(rng, sig, rays, params.jump_k, params.jump_tan)
        return _Grid(pts, sig, self.valid[sl], rng, rays, jump_h, jump_v)

    def state(self, hk: np.ndarray) -> _State:
        """The flattened points, rays, sigmas and H-K classes ``hk`` (H, W) of the fits."""
        return _State(X=self.points.reshape(-1, 3), U=self.rays.reshape(-1, 3), S=self.sigma.ravel(),
                      hk=hk.ravel().astype(np.int64))


@dataclass(frozen=True)
class _State:
    """The flattened arrays of one grid that the fits of growing, merging and splitting read (private; the
    arrays are not changed while it is in use).

    ``fits`` holds the quick fits already made on these arrays (:func:`.quick_fits._quick_fits`): a group of
    pixels fitted again, by another step or another round, gets the same fit without the work.
    """

    X: np.ndarray  # (H*W, 3) points
    U: np.ndarray  # (H*W, 3) unit rays
    S: np.ndarray  # (H*W,) sigma
    hk: np.ndarray  # (H*W,) class
    fits: dict = field(default_factory=dict, init=False, compare=False, repr=False)


# ------------------------------------------------------------------------------------- pixel groups


def _kernel_labels(labels: np.ndarray) -> np.ndarray:
    """A label image as the kernels take it: int32 or int64 as it is (they are compiled for both), else int64."""
    return labels if labels.dtype in (np.int32, np.int64) else labels.astype(np.int64)


def _groups(labels: np.ndarray) -> dict[int, np.ndarray]:
    """Flat pixel indices of each label >= 0 (increasing), by counting (:func:`.kernels.group_order`; the
    reference is :func:`_groups_reference`)."""
    flat = labels.ravel()
    top = int(flat.max()) if flat.size else -1
    if top < 0:
        return {}
    order, starts, counts = kernels.group_order(_kernel_labels(flat), top + 1)
    return {k: order[s:s + c] for k, s, c in zip(np.flatnonzero(counts).tolist(), starts[counts > 0].tolist(),
                                                  counts[counts > 0].tolist(), strict=True)}


def _groups_reference(labels: np.ndarray) -> dict[int, np.ndarray]:
    """:func:`_groups` by ``scipy.ndimage.value_indices``."""
    flat = labels.ravel()
    if flat.size == 0 or flat.max() < 0:
        return {}
    found = ndi.value_indices(np.maximum(flat, -1), ignore_value=-1)
    return {int(k): found[k][0] for k in sorted(found)}


def _subsample(idx: np.ndarray, n_max: int) -> np.ndarray:
    if idx.size <= n_max:
        return idx
    return idx[np.linspace(0, idx.size - 1, n_max).astype(np.int64)]


def _bin_medians(values: np.ndarray, bins: np.ndarray, n_bins: int, which: np.ndarray) -> np.ndarray:
    """The upper median (the element of rank ``count // 2``) of the ``values`` (N,) in each bin ``which`` (M,)
    of ``bins`` (N,), int 0..n_bins-1: the bins' pixels by counting (:func:`.kernels.group_order`), then a
    selection in each, in place of one sort of all values by bin and value."""
    order, starts, counts = kernels.group_order(bins, n_bins)
    out = np.empty(which.size)
    for j, k in enumerate(which.tolist()):
        c = int(counts[k])
        out[j] = np.partition(values[order[starts[k]:starts[k] + c]], c // 2)[c // 2]
    return out


def _rms(z: np.ndarray) -> float:
    return float(np.sqrt(z @ z / z.size)) if z.size else float("inf")


def _class_counts(groups: list[np.ndarray], hk: np.ndarray) -> np.ndarray:
    """(G, 5) int: each group's pixels (flat indices) per curvature class ``hk`` (flat, int64, 0..4), in one
    compiled count (:func:`.kernels.class_counts`); at least one group."""
    sizes = np.fromiter((g.size for g in groups), np.int64, len(groups))
    return kernels.class_counts(hk, np.concatenate(groups).astype(np.int64, copy=False), sizes)


def _planar_groups(groups: list[np.ndarray], hk: np.ndarray) -> np.ndarray:
    """(G,) bool: :func:`_is_planar_counts` of each group's curvature classes ``hk`` (flat, int64, 0..4), in one
    count (:func:`_class_counts`; the reference is :func:`_planar_groups_reference`)."""
    if not groups:
        return np.zeros(0, bool)
    c = _class_counts(groups, hk)
    return c[:, 1] >= c[:, 1:].max(axis=1)


def _planar_groups_reference(groups: list[np.ndarray], hk: np.ndarray) -> np.ndarray:
    """:func:`_planar_groups` by one ``np.bincount``."""
    if not groups:
        return np.zeros(0, bool)
    sizes = np.fromiter((g.size for g in groups), np.int64, len(groups))
    gid = np.repeat(np.arange(len(groups)), sizes)
    c = np.bincount(gid * 5 + hk[np.concatenate(groups)], minlength=5 * len(groups)).reshape(-1, 5)
    return c[:, 1] >= c[:, 1:].max(axis=1)


def _is_planar_counts(counts: np.ndarray) -> bool:
    """Whether planar pixels (class 1) are the patch's most common curvature class (or it has none)."""
    c = counts.tolist()
    return c[1] >= max(c[1:])


# ------------------------------------------------------------------------------ links and adjacency


def _structure(connectivity: int) -> np.ndarray:
    return ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)


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


def _upsampler(shape: tuple[int, int], d: int):
    """Nearest-neighbour upsampling by ``d`` of a grid sampled at ``[::d, ::d]`` back to ``shape``."""
    H, W = shape

    def up(a: np.ndarray) -> np.ndarray:
        return a.repeat(d, axis=0).repeat(d, axis=1)[:H, :W]
    return up
