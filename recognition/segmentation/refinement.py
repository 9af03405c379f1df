"""Segmentation step 7 (decimated grids only): the coarse grid's labels brought back to full resolution
(section 3 of Fillatreau & Fisher segments at full resolution; the coarse grid is this implementation's
speed-up): patches refitted on their coarse samples, pixels off their surface released and regrown."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from .grid import _groups, _State
from .growing import _grow
from .quick_fits import _fit_groups, _pixel_residuals
from .types import SegmentationParams


def _refine_full(labels: np.ndarray, st: _State, params: SegmentationParams, valid: np.ndarray, links, jump_h,
                 jump_v, d: int) -> np.ndarray:
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
    P = _fit_groups(_groups(np.where(coarse, labels, -1)), st, params, n_lab, trim=2.0 * params.grow_k)
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
    # within d pixels (Chebyshev) of one: d dilations by the 3 x 3 square are one by the (2d + 1) square
    near = ndi.maximum_filter(edge, size=2 * d + 1, mode="constant", cval=False).ravel()
    idx = idx[near[idx]]
    z = _pixel_residuals(P, flat[idx], st.X[idx], st.U[idx], st.S[idx])
    flat[idx[~(z <= 2.0 * params.grow_k)]] = -1
    _grow(labels, P, st, links, 2 * d + 2, 2.0 * params.grow_k)
    return labels
