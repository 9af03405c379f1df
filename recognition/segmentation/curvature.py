"""Segmentation steps 2-4 (section 3 of Fillatreau & Fisher, after Besl & Jain): mean and Gaussian curvature
from the fundamental forms with their propagated noise, the H-K classes with noise-derived zero thresholds,
and the crease edges (neighbour and wide-baseline tests)."""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi

from . import kernels
from .derivatives import norm3, quadratic_derivatives
from .edges import _edge_image
from .grid import _Grid
from .types import CurvatureImages, EdgeType, SegmentationParams, SurfaceType


def curvature_images(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams,
                     jumps: tuple[np.ndarray, np.ndarray] | None = None) -> CurvatureImages:
    """Mean and Gaussian curvature of a perspective point image, with propagated noise.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame, NaN where no return
    sigma : ndarray of shape (H, W), metres, range sigma along the ray (already floored)
    params : SegmentationParams
    jumps : (ndarray, ndarray), optional
        The image's :func:`~recognition.segmentation.derivatives.jump_pairs` (``params.jump_k``,
        ``params.jump_tan``), when already at hand.

    Returns
    -------
    CurvatureImages
        ``H`` (1/m) with the normal facing the sensor, ``K`` (1/m²), their sigmas, unit normals (H, W, 3),
        and ``sigma_normal`` (H, W), radians, the propagated angular sigma of the normal.
    """
    der = quadratic_derivatives(points, sigma, params.window, params.jump_k, params.jump_tan,
                                max_variance_ratio=params.max_variance_ratio, jumps=jumps)
    f64 = np.float64
    return CurvatureImages(*kernels.curvatures(
        np.asarray(points, f64), np.asarray(sigma, f64), der.Pu, der.Pv, der.Puu, der.Puv, der.Pvv, der.var_u,
        der.var_v, der.cov2))


def curvatures_reference(points: np.ndarray, sigma: np.ndarray, der) -> CurvatureImages:
    """The curvature images of :func:`curvature_images` from its derivatives ``der``
    (:class:`~recognition.segmentation.derivatives.SurfaceDerivatives`), in numpy: the reference of the
    compiled :func:`.kernels.curvatures`."""
    Pu, Pv = der.Pu, der.Pv
    E = np.einsum("ijk,ijk->ij", Pu, Pu)
    F = np.einsum("ijk,ijk->ij", Pu, Pv)
    G = np.einsum("ijk,ijk->ij", Pv, Pv)
    cr = np.cross(Pu, Pv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = cr / norm3(cr)[..., None]
        flip = np.einsum("ijk,ijk->ij", n, points) > 0
        n[flip] *= -1.0
        L = np.einsum("ijk,ijk->ij", der.Puu, n)
        M = np.einsum("ijk,ijk->ij", der.Puv, n)
        N = np.einsum("ijk,ijk->ij", der.Pvv, n)
        det = E * G - F * F
        K = (L * N - M * M) / det
        Hc = (E * N - 2.0 * F * M + G * L) / (2.0 * det)
        rays = points / norm3(points)[..., None]
        cos2 = np.einsum("ijk,ijk->ij", rays, n) ** 2
        s2 = sigma**2 * cos2
        c = der.cov2  # (H, W, 6): LL, MM, NN, LM, LN, MN per unit variance
        cLL, cMM, cNN, cLM, cLN, cMN = (c[..., i] * s2 for i in range(6))
        hL, hM, hN = G / (2.0 * det), -F / det, E / (2.0 * det)
        var_H = (hL * hL * cLL + hM * hM * cMM + hN * hN * cNN
                 + 2.0 * (hL * hM * cLM + hL * hN * cLN + hM * hN * cMN))
        kL, kM, kN = N / det, -2.0 * M / det, L / det
        var_K = (kL * kL * cLL + kM * kM * cMM + kN * kN * cNN
                 + 2.0 * (kL * kM * cLM + kL * kN * cLN + kM * kN * cMN))
        var_K += (cLL * cNN + 2.0 * cMM * cMM) / det**2
        sig_n = np.sqrt(s2 * (der.var_u / E + der.var_v / G))
    return CurvatureImages(Hc, K, np.sqrt(var_H), np.sqrt(var_K), n, sig_n)


def classify_hk(H: np.ndarray, K: np.ndarray, sigma_H: np.ndarray, sigma_K: np.ndarray, k: float) -> np.ndarray:
    """H-K sign classes with noise-derived zero thresholds.

    Parameters
    ----------
    H, K, sigma_H, sigma_K : ndarray of shape (H, W)
    k : float
        A value is zero when within ``k`` of its sigma.

    Returns
    -------
    ndarray of shape (H, W), int8
        :class:`SurfaceType` values; NONE where H or K is undefined.
    """
    with np.errstate(invalid="ignore"):
        defined = np.isfinite(H) & np.isfinite(K) & np.isfinite(sigma_H) & np.isfinite(sigma_K)
        h0 = np.abs(H) <= k * sigma_H
        k0 = np.abs(K) <= k * sigma_K
        out = np.zeros(H.shape, dtype=np.int8)
        out[k0 & h0] = SurfaceType.PLANAR
        out[k0 & ~h0] = SurfaceType.CYLINDRICAL
        out[~k0 & (K > 0) & ~h0] = SurfaceType.ELLIPTIC
        out[~k0 & (K > 0) & h0] = SurfaceType.PLANAR  # K > 0 with H = 0 cannot happen (K <= H²): noise
        out[~k0 & (K < 0)] = SurfaceType.HYPERBOLIC
    out[~defined] = SurfaceType.NONE
    return out


def _curvature_step(grid: _Grid, params: SegmentationParams):
    """Steps 2-4 on one grid: ``(curvature images, H-K classes (H, W), crease pixels (H, W), wide-baseline
    crease pixels (H, W), edge image (H, W) of jumps and creases)``."""
    shape = grid.shape
    cur = curvature_images(grid.points, grid.sigma, params, (grid.jump_h, grid.jump_v))
    hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    crease_h, crease_v = _crease_pairs(cur.normals, cur.sigma_normal, params)
    crease = np.zeros(shape, bool)
    crease[:, :-1] |= crease_h
    crease[:, 1:] |= crease_h
    crease[:-1, :] |= crease_v
    crease[1:, :] |= crease_v
    wide = _wide_creases(cur.normals, grid.valid, grid.jump_h, grid.jump_v, params)
    crease |= wide
    edges = _edge_image(shape, grid.jump_h, grid.jump_v)
    edges[crease] |= np.uint8(EdgeType.CREASE)
    return cur, hk, crease, wide, edges


# ------------------------------------------------------------------------------------------ creases


def _crease_pairs(normals, sig_n, params) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for sl_a, sl_b in (
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        dot = np.clip(np.einsum("ijk,ijk->ij", normals[sl_a], normals[sl_b]), -1.0, 1.0)
        with np.errstate(invalid="ignore"):
            ang = np.arccos(dot)
            thr = np.maximum(params.crease_k * np.hypot(sig_n[sl_a], sig_n[sl_b]), params.crease_min_angle)
            out.append(ang > thr)
    return out[0], out[1]


def _shift(a: np.ndarray, dr: int, dc: int, fill: float = np.nan) -> np.ndarray:
    """``out[r, c] = a[r + dr, c + dc]`` (``fill`` outside the image), as float."""
    out = np.full(a.shape, fill, dtype=np.result_type(a.dtype, np.float64))
    H, W = a.shape[:2]
    if abs(dr) >= H or abs(dc) >= W:
        return out
    ro, ri = (slice(0, H - dr), slice(dr, H)) if dr >= 0 else (slice(-dr, H), slice(0, H + dr))
    co, ci = (slice(0, W - dc), slice(dc, W)) if dc >= 0 else (slice(-dc, W), slice(0, W + dc))
    out[ro, co] = a[ri, ci]
    return out


def _smooth_normals(n: np.ndarray, b: int) -> np.ndarray:
    """Box-filtered unit normals (``b x b``, NaN-aware; NaN where undefined or under half the box defined)."""
    ok = np.isfinite(n[..., 0])
    w = ndi.uniform_filter(ok.astype(np.float64), b, mode="constant")
    s = np.stack([ndi.uniform_filter(np.where(ok, n[..., i], 0.0), b, mode="constant") for i in range(3)], -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s /= norm3(s)[..., None]
    s[~ok | (w < 0.5)] = np.nan
    return s


def _wide_creases(normals: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                  params: SegmentationParams) -> np.ndarray:
    """Crease pixels from the change of the normal across a wide baseline (an (H, W) bool mask).

    Along rows and along columns, with ``k`` the half baseline and ``n`` the normals box-smoothed over
    ``window`` pixels, ``D(i) = angle(n[i-k], n[i+k]) - (angle(n[i-3k], n[i-k]) + angle(n[i+k], n[i+3k])) / 2``:
    the normal turns at a constant rate on a cylinder (D ~ 0) but all at once at a crease (D ~ the crease
    angle). Segments crossing a jump or a hole do not count. A pixel is a crease where D is a local maximum
    (within 2 pixels along the direction) above half the threshold, in a connected line that somewhere
    exceeds the threshold ``max(crease_wide_min_angle, median + crease_wide_k * 1.4826 MAD)`` (robust statistics
    of D over the image: the noise of real sensors is spatially correlated and quantised, so the
    propagated sigma of independent pixels is no guide at this scale).
    """
    k = params.baseline
    H, W = valid.shape
    out = np.zeros((H, W), bool)
    if k <= 0 or min(H, W) <= 2 * k:
        return out
    n = _smooth_normals(normals, params.window)
    for axis, jp in ((1, jump_h), (0, jump_v)):
        dr, dc = (0, 1) if axis == 1 else (1, 0)
        if axis == 1:
            brk = jp | ~valid[:, :-1] | ~valid[:, 1:]
            cum = np.concatenate([np.zeros((H, 1)), np.cumsum(brk, axis=1, dtype=np.float64)], axis=1)
        else:
            brk = jp | ~valid[:-1, :] | ~valid[1:, :]
            cum = np.concatenate([np.zeros((1, W)), np.cumsum(brk, axis=0, dtype=np.float64)], axis=0)

        def ang(o1: int, o2: int, dr=dr, dc=dc, cum=cum) -> np.ndarray:
            a, b = _shift(n, o1 * dr, o1 * dc), _shift(n, o2 * dr, o2 * dc)
            with np.errstate(invalid="ignore"):
                t = np.arccos(np.clip(np.einsum("ijk,ijk->ij", a, b), -1.0, 1.0))
                free = (_shift(cum, o2 * dr, o2 * dc) - _shift(cum, o1 * dr, o1 * dc)) == 0
            return np.where(free, t, np.nan)

        D = ang(-k, k) - 0.5 * (np.nan_to_num(ang(-3 * k, -k)) + np.nan_to_num(ang(k, 3 * k)))
        fin = np.isfinite(D)
        if fin.sum() < 100:
            continue
        med = float(np.median(D[fin]))
        scale = 1.4826 * float(np.median(np.abs(D[fin] - med)))
        thr = max(params.crease_wide_min_angle, med + params.crease_wide_k * scale)
        Dz = np.where(fin, D, -np.inf)
        m = Dz > 0.5 * thr
        for o in (1, 2):
            m &= (Dz >= _shift(Dz, o * dr, o * dc, -np.inf)) & (Dz >= _shift(Dz, -o * dr, -o * dc, -np.inf))
        lab, nl = ndi.label(m, structure=np.ones((3, 3), bool))
        keep = np.zeros(nl + 1, bool)
        keep[lab[m & (Dz > thr)]] = True
        keep[0] = False
        out |= keep[lab]
    return out
