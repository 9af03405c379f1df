"""Segmentation step 1, edges, and the noise self-calibration (section 3 of Fillatreau & Fisher: patches do
not cross depth discontinuities): the image's returns and rays, its jump pairs
(:func:`.derivatives.jump_pairs`), the range noise the image shows beyond the declared one (:func:`noise_scale`),
and the edge image."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from . import kernels
from .derivatives import clean_windows, jump_pairs, savgol_kernels
from .grid import _bin_medians, _Grid
from .types import EdgeType, SegmentationParams


def _image_grid(points: np.ndarray, sigma: np.ndarray,
                params: SegmentationParams) -> tuple[_Grid, np.ndarray, np.ndarray | None] | None:
    """The full-resolution grid of checked inputs: returns, floored sigma, rays, jump pairs, with the sigma
    scaled by the measured noise (``calibrate_noise``); ``(grid, declared sigma (H, W), noise scale or None)``,
    or None for an image without returns."""
    valid, pts, sig, rng, rays = checked_returns(points, sigma, params.sigma_floor_m)
    if not valid.any():
        return None
    declared = sig
    scale = None
    jump_h, jump_v = jump_pairs(rng, sig, rays, params.jump_k, params.jump_tan)
    if params.calibrate_noise:
        scale = noise_scale(rng, sig, valid, jump_h, jump_v, params.window, params.max_noise_scale,
                            params.noise_block)
        sig = sig * scale
        # the scale is >= 1: a larger sigma only raises the thresholds, so the jumps are among the first ones
        jump_h, jump_v = kernels.jump_pairs_among(rng, sig, rays, float(params.jump_k),
                                                  float(params.jump_tan), jump_h, jump_v)
    return _Grid(pts, sig, valid, rng, rays, jump_h, jump_v), declared, scale


def checked_returns(points: np.ndarray, sigma: np.ndarray, sigma_floor: float):
    """``(valid (H, W), points (H, W, 3), sigma floored at sigma_floor (H, W), range (H, W), unit rays
    (H, W, 3))`` of checked inputs, NaN where there is no return: a return where every coordinate is finite
    and one is not 0 (a range beyond 1e154 m, whose square overflows, counts as none) and sigma is finite.
    The compiled :func:`.kernels.checked_returns`; :func:`checked_returns_reference` is the same in numpy."""
    return kernels.checked_returns(np.asarray(points, np.float64), np.asarray(sigma, np.float64), float(sigma_floor))


def checked_returns_reference(points: np.ndarray, sigma: np.ndarray, sigma_floor: float):
    """:func:`checked_returns` in numpy (its reference)."""
    r2 = np.einsum("ijk,ijk->ij", points, points)
    valid = np.isfinite(r2) & (r2 > 0) & np.isfinite(sigma)
    sig = np.where(valid, np.maximum(sigma, sigma_floor), np.nan)
    pts = np.where(valid[..., None], points, np.nan)
    rng = np.where(valid, np.sqrt(r2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        rays = pts / rng[..., None]
    return valid, pts, sig, rng, rays


def noise_scale(rng: np.ndarray, sigma: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                window: int, max_scale: float, block: int) -> np.ndarray:
    """Ratio of the range noise measured in the image to the declared sigma, per pixel, clipped to
    ``[1, max_scale]`` (an (H, W) array).

    The range image is fitted by the same local quadratic as the derivatives (a Savitzky-Golay
    value-at-centre kernel ``k``) on windows free of holes and jumps, centred on every third pixel; the
    centre's residual then has variance ``sigma² (1 - k_00)`` (``k_00`` the centre weight: the fit's
    leverage), so the robust (median-based) scale of ``(r - fit) / (sigma sqrt(1 - k_00))`` estimates the
    ratio. It is taken per block of ``block x block`` samples (``3 block`` pixels; the noise of a sensor grows
    with incidence, so one wall at grazing incidence is much noisier than the rest), blocks with fewer than
    16 samples take the image-wide median, and the block values are smoothed (3x3 block median) and spread
    to their pixels. Windows across creases inflate a few residuals; the medians ignore them. All ones when
    fewer than 100 windows qualify.
    """
    H, W = rng.shape
    ones = np.ones((H, W))
    if H < window or W < window:
        return ones
    k = savgol_kernels(window)
    h = window // 2
    c = float(np.mean(np.arange(-h, h + 1.0) ** 2))
    # value at the centre of the 2D total-degree-2 fit: box (x) box - c (d2 (x) box + box (x) d2)
    K2 = np.outer(k["box"], k["box"]) - c * (np.outer(k["d2"], k["box"]) + np.outer(k["box"], k["d2"]))
    lev = float(K2[h, h])
    full = clean_windows(valid, jump_h, jump_v, window)
    step = 3
    rs = np.arange(1, H, step)
    cs = np.arange(1, W, step)
    fs = full[np.ix_(rs, cs)]
    if fs.sum() < 100:
        return ones
    r0 = np.where(valid, rng, 0.0)
    si, sj = np.nonzero(fs)
    rows, cols = rs[si], cs[sj]
    offs = np.arange(-h, h + 1)
    patch = r0.ravel().take((rows * W + cols)[:, None, None] + (offs[:, None] * W + offs[None, :])[None])
    fit = np.einsum("nij,ij->n", patch, K2)
    az = np.abs(rng[rows, cols] - fit) / (sigma[rows, cols] * np.sqrt(max(1.0 - lev, 1e-6)) * 0.6745)
    glob = float(np.median(az))
    if not np.isfinite(glob):
        return ones
    # per-block medians (the middle element of each block's sorted values)
    nbr, nbc = -(-len(rs) // block), -(-len(cs) // block)
    b = (si // block) * nbc + (sj // block)
    cnt = np.bincount(b, minlength=nbr * nbc)
    med = np.full(nbr * nbc, glob)
    ok = cnt >= 16
    med[ok] = _bin_medians(az, b, nbr * nbc, np.flatnonzero(ok))
    med = ndi.median_filter(med.reshape(nbr, nbc), size=3, mode="nearest")
    med = np.clip(med, 1.0, max_scale)
    pix_r = np.minimum(np.arange(H) // (step * block), nbr - 1)
    pix_c = np.minimum(np.arange(W) // (step * block), nbc - 1)
    return med[pix_r[:, None], pix_c[None, :]]


def _edge_image(shape, jump_h, jump_v) -> np.ndarray:
    e = np.zeros(shape, bool)
    e[:, :-1] |= jump_h
    e[:, 1:] |= jump_h
    e[:-1, :] |= jump_v
    e[1:, :] |= jump_v
    edges = np.zeros(shape, np.uint8)
    edges[e] = np.uint8(EdgeType.JUMP)
    return edges
