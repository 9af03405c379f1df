"""Segmentation step 1 (section 3 of Fillatreau & Fisher, after Besl & Jain): masked local quadratic fits of
an organised point image, P and its first and second derivatives; the jump test between neighbours.

The surface of a perspective range image is the parametric surface ``P(u, v)`` (``u`` the column index,
``v`` the row index, ``P`` the 3D point in the sensor frame). Each coordinate of ``P`` is fitted, in a
``w x w`` window centred on every pixel, by a quadratic in the pixel offsets::

    P(u0 + du, v0 + dv) ~ a0 + a1 du + a2 dv + a3 du² + a4 du dv + a5 dv²

so that ``P_u = a1, P_v = a2, P_uu = 2 a3, P_uv = a4, P_vv = 2 a5`` at the centre (Savitzky-Golay
smoothing differentiation; Besl & Jain, "Segmentation through variable-order surface fitting", IEEE PAMI
10(2), 1988, doi:10.1109/34.3881, use the same separable operators).

Windows must not cross depth discontinuities. The choice made here is a *per-window support mask*: a
neighbour belongs to the fit of a centre pixel when it has a return and passes the jump test of
:func:`jump_threshold` against the centre (range difference below a few sigma plus the change a smooth
surface at a steep incidence can show over that angular distance). Two paths compute the same estimator:

- pixels whose whole window is valid and free of jump pairs use fixed separable Savitzky-Golay kernels
  (``scipy.ndimage.correlate1d``; milliseconds per VGA frame);
- the others (near jumps, holes and the image border) solve their own masked 6x6 normal equations, batched
  over pixels with numpy (no per-pixel Python loop).

The estimator is linear in the data, so the variance of each coefficient for unit, independent noise is the
diagonal of ``(X' X)^-1`` for the window's design matrix ``X``: it is returned per pixel so that callers can
propagate the per-pixel range sigma (:mod:`recognition.segmentation.curvature`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from . import kernels
from .types import SegmentationParams

__all__ = [
    "SurfaceDerivatives",
    "jump_threshold",
    "jump_pairs",
    "jump_pairs_reference",
    "ray_angles",
    "norm3",
    "savgol_kernels",
    "window_design",
    "quadratic_derivatives",
]


@dataclass(frozen=True)
class SurfaceDerivatives:
    """First and second derivatives of ``P(u, v)`` and their unit-noise variances.

    Attributes
    ----------
    Pu, Pv, Puu, Puv, Pvv : ndarray of shape (H, W, 3), metres per pixel (per pixel²)
        Derivatives of the point image with respect to the column (``u``) and row (``v``) index.
        NaN where the fit is undefined (no return, too little support, ill-conditioned window).
    var_u, var_v : ndarray of shape (H, W)
        Variance of ``Pu``/``Pv`` per unit variance of the data along one coordinate.
    cov2 : ndarray of shape (H, W, 6)
        Covariance of ``(Puu, Puv, Pvv)`` per unit data variance (same scaling), as its entries
        ``(uu.uu, uv.uv, vv.vv, uu.uv, uu.vv, uv.vv)``.
    full : ndarray of shape (H, W), bool
        True where the fixed (unmasked) Savitzky-Golay kernels were used.
    """

    Pu: np.ndarray
    Pv: np.ndarray
    Puu: np.ndarray
    Puv: np.ndarray
    Pvv: np.ndarray
    var_u: np.ndarray
    var_v: np.ndarray
    cov2: np.ndarray
    full: np.ndarray


def norm3(a: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (length 3), faster than ``np.linalg.norm`` on images."""
    return np.sqrt(np.einsum("...k,...k->...", a, a))


def jump_threshold(
    range_a: np.ndarray,
    range_b: np.ndarray,
    sigma_a: np.ndarray,
    sigma_b: np.ndarray,
    angle: np.ndarray,
    k_sigma: float,
    tan_max_incidence: float,
) -> np.ndarray:
    """Largest range difference between two returns that still counts as one continuous surface.

    ``k_sigma * sqrt(sigma_a² + sigma_b²) + tan_max_incidence * mean_range * angle``: the noise allowance
    plus the range change of a smooth surface seen at the steepest accepted incidence over the angular
    separation ``angle`` of the two rays (``r * dtheta * tan(incidence)``).

    Parameters
    ----------
    range_a, range_b : ndarray, metres
    sigma_a, sigma_b : ndarray, metres (range noise along the ray)
    angle : ndarray, radians, angle between the two rays
    k_sigma : float
    tan_max_incidence : float

    Returns
    -------
    ndarray, metres
    """
    return k_sigma * np.sqrt(sigma_a**2 + sigma_b**2) + tan_max_incidence * 0.5 * (range_a + range_b) * angle


def ray_angles(rays: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles (radians, chord approximation ``|a - b|``) between the rays of horizontally (H, W - 1) and
    vertically (H - 1, W) adjacent pixels; NaN next to a hole."""
    return norm3(rays[:, :-1] - rays[:, 1:]), norm3(rays[:-1] - rays[1:])


def jump_pairs(
    rng: np.ndarray, sigma: np.ndarray, rays: np.ndarray, k_sigma: float, tan_max_incidence: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Jump (depth discontinuity) flags between horizontally and vertically adjacent pixels.

    Parameters
    ----------
    rng : ndarray of shape (H, W), metres, NaN where no return
    sigma : ndarray of shape (H, W), metres
    rays : ndarray of shape (H, W, 3), unit ray directions (NaN where no return)
    k_sigma, tan_max_incidence : float
        See :func:`jump_threshold`; the angle between two rays is the chord of :func:`ray_angles`.

    Returns
    -------
    jump_h : ndarray of shape (H, W - 1), bool
        True when pixel (i, j) and (i, j + 1) both have returns and are on different sides of a jump.
    jump_v : ndarray of shape (H - 1, W), bool
        The same for (i, j) and (i + 1, j).

    Notes
    -----
    The compiled :func:`.kernels.jump_pairs`; :func:`jump_pairs_reference` is the same in numpy.
    """
    f64 = np.float64
    return kernels.jump_pairs(np.asarray(rng, f64), np.asarray(sigma, f64), np.asarray(rays, f64),
                              float(k_sigma), float(tan_max_incidence))


def jump_pairs_reference(
    rng: np.ndarray, sigma: np.ndarray, rays: np.ndarray, k_sigma: float, tan_max_incidence: float,
    angles: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`jump_pairs` in numpy (its reference; the same arguments and results), from the :func:`ray_angles`
    of ``rays`` when ``angles`` holds them."""
    angles = ray_angles(rays) if angles is None else angles
    out = []
    for (sl_a, sl_b), ang in zip((
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ), angles, strict=True):
        ra, rb = rng[sl_a], rng[sl_b]
        thr = jump_threshold(ra, rb, sigma[sl_a], sigma[sl_b], ang, k_sigma, tan_max_incidence)
        with np.errstate(invalid="ignore"):
            out.append(np.abs(ra - rb) > thr)  # NaN compares False: no jump next to a hole
    return out[0], out[1]


def savgol_kernels(window: int) -> dict[str, np.ndarray]:
    """1D kernels of the separable quadratic Savitzky-Golay estimator on a full square window.

    In the orthogonal basis ``{1, t, t² - c}`` (``c`` the mean of ``t²`` over the window) of each axis, the
    quadratic fit of total degree 2 decouples, and every coefficient is a product of 1D kernels.

    Parameters
    ----------
    window : int
        Odd window size ``w >= 3``.

    Returns
    -------
    dict
        ``box`` (mean), ``d1`` (first derivative, per pixel), ``d2`` (coefficient of ``t²``: half the second
        derivative), and the unit-noise variances ``var_d1``, ``var_d2``, ``var_d11`` of ``a1`` (first
        derivative), ``a3`` (``t²`` coefficient) and ``a4`` (mixed coefficient) of the 2D fit.
    """
    h = window // 2
    t = np.arange(-h, h + 1, dtype=np.float64)
    s2 = float(np.sum(t**2))
    p2 = t**2 - s2 / window
    sp2 = float(np.sum(p2**2))
    return {
        "box": np.full(window, 1.0 / window),
        "d1": t / s2,
        "d2": p2 / sp2,
        "var_d1": np.array(1.0 / (window * s2)),
        "var_d2": np.array(1.0 / (window * sp2)),
        "var_d11": np.array(1.0 / s2**2),
    }


def window_design(window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Design matrix of the quadratic fit over a square window, in raster order of the offsets.

    Returns
    -------
    X : ndarray of shape (w², 6)
        Columns ``1, du, dv, du², du dv, dv²``.
    du, dv : ndarray of shape (w²,), int
        Column and row offsets.
    """
    h = window // 2
    dv, du = np.meshgrid(np.arange(-h, h + 1), np.arange(-h, h + 1), indexing="ij")
    du = du.ravel()
    dv = dv.ravel()
    X = np.stack([np.ones_like(du), du, dv, du**2, du * dv, dv**2], axis=1).astype(np.float64)
    return X, du, dv


def _full_window_derivatives(points0: np.ndarray, window: int) -> tuple[np.ndarray, ...]:
    """Separable Savitzky-Golay derivatives of a NaN-free point image (values outside ``full`` are junk): the
    compiled :func:`.kernels.savgol_derivatives`, which sums as ``scipy.ndimage.correlate1d`` does
    (:func:`_full_window_derivatives_reference`)."""
    k = savgol_kernels(window)
    kinds = np.array([_symmetry(k[name]) for name in ("box", "d1", "d2")])
    return kernels.savgol_derivatives(np.asarray(points0, np.float64), k["box"], k["d1"], k["d2"], kinds)


def _symmetry(w: np.ndarray) -> int:
    """1 for a symmetric odd kernel, -1 for an antisymmetric one, as ``scipy.ndimage`` tells them apart (to
    ``DBL_EPSILON``); the Savitzky-Golay kernels are one or the other."""
    h = len(w) // 2
    eps = np.finfo(np.float64).eps
    if all(abs(w[h + i] - w[h - i]) <= eps for i in range(1, h + 1)):
        return 1
    if all(abs(w[h + i] + w[h - i]) <= eps for i in range(1, h + 1)):
        return -1
    raise ValueError("a Savitzky-Golay kernel is symmetric or antisymmetric")


def _full_window_derivatives_reference(points0: np.ndarray, window: int) -> tuple[np.ndarray, ...]:
    """:func:`_full_window_derivatives` by ``scipy.ndimage.correlate1d`` (its reference)."""
    k = savgol_kernels(window)
    row = {name: ndi.correlate1d(points0, k[name], axis=1, mode="nearest") for name in ("box", "d1", "d2")}
    Pu = ndi.correlate1d(row["d1"], k["box"], axis=0, mode="nearest")
    Pv = ndi.correlate1d(row["box"], k["d1"], axis=0, mode="nearest")
    Puu = 2.0 * ndi.correlate1d(row["d2"], k["box"], axis=0, mode="nearest")
    Puv = ndi.correlate1d(row["d1"], k["d1"], axis=0, mode="nearest")
    Pvv = 2.0 * ndi.correlate1d(row["box"], k["d2"], axis=0, mode="nearest")
    return Pu, Pv, Puu, Puv, Pvv


def clean_windows(valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray, window: int) -> np.ndarray:
    """(H, W) bool: pixels whose ``window x window`` neighbourhood has no hole and crosses no jump (where the
    fixed Savitzky-Golay kernels apply). ``jump_h`` (H, W-1) and ``jump_v`` (H-1, W) mark jumps between
    horizontal and vertical neighbours; both pixels of a jump count as bad."""
    bad = ~valid
    bad[:, :-1] |= jump_h
    bad[:, 1:] |= jump_h
    bad[:-1, :] |= jump_v
    bad[1:, :] |= jump_v
    return ~ndi.maximum_filter(bad, size=window, mode="constant", cval=True)


def quadratic_derivatives(
    points: np.ndarray,
    sigma: np.ndarray,
    window: int,
    jump_k: float,
    jump_tan: float,
    min_support: int | None = None,
    max_variance_ratio: float = SegmentationParams.max_variance_ratio,
    chunk: int = 8192,
    jumps: tuple[np.ndarray, np.ndarray] | None = None,
) -> SurfaceDerivatives:
    """Masked local quadratic fits of ``P(u, v)``: first and second derivatives that do not cross jumps.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame, NaN where no return
    sigma : ndarray of shape (H, W), metres, range noise along the ray (finite where ``points`` is)
    window : int
        Odd window size (5, 7, 9 ...).
    jump_k, jump_tan : float
        Parameters of :func:`jump_threshold` deciding which neighbours share the centre's surface.
    min_support : int, optional
        Fewest window pixels for a fit (default ``max(9, w² // 3)``).
    max_variance_ratio : float
        A masked window whose second-derivative variance exceeds this multiple of the full window's is
        too ill-conditioned: its derivatives are NaN (default: the segmentation's,
        :attr:`SegmentationParams.max_variance_ratio`).
    chunk : int
        Pixels per batch of the masked path (bounds memory).
    jumps : (ndarray, ndarray), optional
        :func:`jump_pairs` of the image with ``jump_k`` and ``jump_tan``, when already at hand.

    Returns
    -------
    SurfaceDerivatives
    """
    H, W = points.shape[:2]
    valid, points0 = _window_inputs(points, sigma)
    rng = norm3(points)
    with np.errstate(invalid="ignore", divide="ignore"):
        rays = points / rng[..., None]
    k = savgol_kernels(window)
    v2 = 4.0 * float(k["var_d2"])
    full_cov2 = np.array([v2, float(k["var_d11"]), v2, 0.0, 0.0, 0.0])

    if H < window or W < window:
        full = np.zeros((H, W), dtype=bool)
    else:
        jump_h, jump_v = jump_pairs(rng, sigma, rays, jump_k, jump_tan) if jumps is None else jumps
        full = clean_windows(valid, jump_h, jump_v, window)
    if full.any():
        Pu, Pv, Puu, Puv, Pvv = _full_window_derivatives(points0, window)
        kernels.blank_outside(full, (Pu, Pv, Puu, Puv, Pvv))
    else:
        Pu, Pv, Puu, Puv, Pvv = (np.full((H, W, 3), np.nan) for _ in range(5))
    var_u = np.where(full, float(k["var_d1"]), np.nan)
    var_v = var_u.copy()
    cov2 = np.where(full[..., None], full_cov2, np.nan)

    masked = valid & ~full
    if masked.any():
        _masked_fits(
            points, sigma, rng, rays, valid, masked, window, jump_k, jump_tan,
            min_support if min_support is not None else max(9, window * window // 3),
            max_variance_ratio * v2, chunk,
            (Pu, Pv, Puu, Puv, Pvv, var_u, var_v, cov2),
        )
    return SurfaceDerivatives(Pu, Pv, Puu, Puv, Pvv, var_u, var_v, cov2, full)


def _window_inputs(points: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(valid (H, W), points with 0 where not valid (H, W, 3))`` of a point image (H, W, 3) and its sigma
    (H, W): valid where every coordinate and sigma are finite. The compiled :func:`.kernels.window_inputs`;
    :func:`_window_inputs_reference` is the same in numpy."""
    return kernels.window_inputs(np.asarray(points, np.float64), np.asarray(sigma, np.float64))


def _window_inputs_reference(points: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_window_inputs` in numpy (its reference)."""
    valid = np.isfinite(points).all(axis=-1) & np.isfinite(sigma)
    return valid, np.where(valid[..., None], points, 0.0)


def spd_inverse(M: np.ndarray) -> np.ndarray:
    """Inverse of a batch of small symmetric positive-definite matrices by an unrolled Cholesky.

    The loops run over the (small) matrix indices; every operation is vectorised over the batch, which is
    much faster than LAPACK's per-matrix calls for millions of 6x6 systems.

    Parameters
    ----------
    M : ndarray of shape (n, k, k)

    Returns
    -------
    ndarray of shape (n, k, k)
    """
    k = M.shape[-1]
    A = np.moveaxis(M, 0, -1)  # (k, k, n): contiguous vectors per entry after the copy below
    A = np.ascontiguousarray(A)
    L = np.zeros_like(A)
    for j in range(k):
        s = A[j, j] - np.sum(L[j, :j] ** 2, axis=0)
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, k):
            L[i, j] = (A[i, j] - np.sum(L[i, :j] * L[j, :j], axis=0)) / L[j, j]
    # inverse of the lower-triangular factor
    Li = np.zeros_like(A)
    for i in range(k):
        Li[i, i] = 1.0 / L[i, i]
        for j in range(i):
            Li[i, j] = -np.sum(L[i, j:i] * Li[j:i, j], axis=0) / L[i, i]
    out = np.empty(M.shape)
    for i in range(k):
        for j in range(i + 1):
            v = np.sum(Li[i:, i] * Li[i:, j], axis=0)
            out[:, i, j] = v
            out[:, j, i] = v
    return out


def _pixel_angle(rays: np.ndarray) -> float:
    """Median angle (radians) between the rays of horizontally / vertically adjacent returns (subsampled)."""
    a = norm3(rays[::7, 1:] - rays[::7, :-1]).ravel()
    b = norm3(rays[1:, ::7] - rays[:-1, ::7]).ravel()
    ab = np.concatenate([a, b])
    ab = ab[np.isfinite(ab) & (ab > 0)]
    return float(np.median(ab)) if ab.size else 0.0


def _masked_fits(points, sigma, rng, rays, valid, masked, window, jump_k, jump_tan, min_support,
                 max_var_uu, chunk, outputs) -> None:
    """Per-pixel masked quadratic fits for the pixels in ``masked``, written into ``outputs`` in place: the
    compiled :func:`.kernels.masked_fits`, whose reference is :func:`_masked_fits_reference` (``chunk`` is
    the reference's; the kernel needs no batches)."""
    rows, cols = np.nonzero(masked)
    f64 = np.float64
    kernels.masked_fits(np.asarray(points, f64), np.asarray(sigma, f64), np.where(valid, rng, np.nan),
                        rows.astype(np.int64), cols.astype(np.int64), int(window), float(jump_k), float(jump_tan),
                        _pixel_angle(rays), int(min_support), float(max_var_uu), *outputs)


def _masked_fits_reference(points, sigma, rng, rays, valid, masked, window, jump_k, jump_tan, min_support,
                 max_var_uu, chunk, outputs) -> None:
    """Per-pixel masked quadratic fits for the pixels in ``masked``, written into ``outputs`` in place, in
    batched numpy (the reference of :func:`.kernels.masked_fits`).

    The angle between the centre ray and a neighbour's ray is taken as the pixel distance times the
    image's median adjacent-ray angle (exact enough for the jump allowance, and it avoids gathering rays).
    """
    Pu, Pv, Puu, Puv, Pvv, var_u, var_v, cov2 = outputs
    H, W = rng.shape
    h = window // 2
    Wp = W + 2 * h
    X, du, dv = window_design(window)
    XX = (X[:, :, None] * X[:, None, :]).reshape(len(X), 36)
    pad = ((h, h), (h, h))
    rng_p = np.pad(np.where(valid, rng, np.nan), pad, constant_values=np.nan).ravel()
    sig2_p = np.pad(sigma, pad, constant_values=np.nan).ravel() ** 2
    # coordinates with 0 for no return: a window's pixels outside its mask are multiplied by 0
    pts_p = [np.pad(np.where(valid, points[..., k], 0.0), pad).ravel() for k in range(3)]
    alpha = _pixel_angle(rays)
    ang = alpha * np.hypot(du, dv)[None, :]
    offs = (dv * Wp + du)[None, :]
    # window pixel -> its row (first ``window`` columns) and column (last ``window``): support counts by gemm
    lines = np.zeros((window * window, 2 * window))
    lines[np.arange(window * window), dv + h] = 1.0
    lines[np.arange(window * window), window + du + h] = 1.0
    rows, cols = np.nonzero(masked)
    centre_all = (rows + h) * Wp + (cols + h)
    J = np.array([2.0, 1.0, 2.0])
    for start in range(0, len(rows), chunk):
        r = rows[start:start + chunk]
        c = cols[start:start + chunk]
        flat = centre_all[start:start + chunk][:, None] + offs
        rc = rng[r, c][:, None]
        rng_w = rng_p.take(flat)
        thr = jump_k * np.sqrt(sigma[r, c][:, None] ** 2 + sig2_p.take(flat)) + jump_tan * rc * ang
        with np.errstate(invalid="ignore"):
            mf = (np.abs(rng_w - rc) <= thr).astype(np.float64)  # NaN (no return) compares False
        per_line = (mf @ lines) > 0
        enough = (
            (mf.sum(axis=1) >= min_support)
            & (per_line[:, :window].sum(axis=1) >= 3)
            & (per_line[:, window:].sum(axis=1) >= 3)
        )
        if not enough.any():
            continue
        r, c, mf, flat = r[enough], c[enough], mf[enough], flat[enough]
        M = (mf @ XX).reshape(len(r), 6, 6)
        M += np.eye(6) * (1e-12 * np.trace(M, axis1=1, axis2=2))[:, None, None]
        inv = spd_inverse(M)
        # fit P - P(centre): the constant stays ~0, so the tiny ridge does not bias the slopes
        centre = points[r, c]
        rhs = np.stack(
            [((pts_p[k].take(flat) - centre[:, k:k + 1]) * mf) @ X for k in range(3)], axis=-1
        )  # (n, 6, 3)
        beta = inv @ rhs  # (n, 6, 3)
        c2 = inv[:, 3:6, 3:6] * J[None, :, None] * J[None, None, :]
        c2 = np.stack([c2[:, 0, 0], c2[:, 1, 1], c2[:, 2, 2], c2[:, 0, 1], c2[:, 0, 2], c2[:, 1, 2]], axis=1)
        good = (c2[:, 0] <= max_var_uu) & (c2[:, 2] <= max_var_uu)
        r, c, beta, inv, c2 = r[good], c[good], beta[good], inv[good], c2[good]
        Pu[r, c] = beta[:, 1]
        Pv[r, c] = beta[:, 2]
        Puu[r, c] = 2.0 * beta[:, 3]
        Puv[r, c] = beta[:, 4]
        Pvv[r, c] = 2.0 * beta[:, 5]
        var_u[r, c] = inv[:, 1, 1]
        var_v[r, c] = inv[:, 2, 2]
        cov2[r, c] = c2
