"""The algebra every fit shares: the quadric's parameters, its monomial basis and gradient, normalisation.

A quadric (section 3 of Fillatreau & Fisher) is ``X' A X + X' B + C = 0`` with ``A`` symmetric (3, 3), ``B``
(3,) and ``C`` a scalar. Its 10 parameters are stored in the order

    p = (a11, a22, a33, a12, a13, a23, b1, b2, b3, c)

so that ``f(x) = m(x) . p`` with the monomials ``m(x) = (x², y², z², 2xy, 2xz, 2yz, x, y, z, 1)``
(:func:`monomials`), and ``grad f = 2 A x + b`` (:func:`gradient`). A plane ``n . x = offset`` is the quadric
``(0, ..., 0, n, -offset)`` (:func:`plane_params`). The parameter vector is defined up to scale: fits return it
with unit norm.

Fits work in normalised coordinates ``y = (x - mean) / scale`` (centred on the points' mean, scaled to unit RMS
radius); :func:`normalisation_map` maps parameters back. Points of the segmentation are in the sensor frame
(sensor at the origin), so the ray of a point ``x`` is ``x / |x|``; :func:`ray_residuals` measures residuals
orthogonally and along that ray.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg

__all__ = [
    "MIN_GRAZING",
    "MONOMIAL_GRADIENT",
    "check_patch",
    "check_points",
    "design_matrices",
    "evaluate",
    "gradient",
    "monomials",
    "normalisation_map",
    "plane_params",
    "quadric_matrices",
    "quadric_params",
    "ray_residuals",
    "taubin_fit",
]


# index pairs of the symmetric matrix entries carried by params 0..5
_A_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


# --------------------------------------------------------------------------------------- parameters


def quadric_matrices(params: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Split parameters into ``(A, B, C)``.

    Parameters
    ----------
    params : ndarray of shape (10,)

    Returns
    -------
    A : ndarray of shape (3, 3), symmetric
    B : ndarray of shape (3,)
    C : float
    """
    p = np.asarray(params, dtype=np.float64)
    A = np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])
    return A, p[6:9].copy(), float(p[9])


def quadric_params(A: np.ndarray, B: np.ndarray, C: float) -> np.ndarray:
    """Inverse of :func:`quadric_matrices`: ndarray of shape (10,) (not normalised)."""
    A = np.asarray(A, dtype=np.float64)
    return np.array([A[0, 0], A[1, 1], A[2, 2], A[0, 1], A[0, 2], A[1, 2], *np.asarray(B, float), float(C)])


def plane_params(normal: np.ndarray, offset: float) -> np.ndarray:
    """Quadric parameters (10,) of the plane ``normal . x - offset = 0``."""
    p = np.zeros(10)
    p[6:9] = normal
    p[9] = -offset
    return p


# ------------------------------------------------------------------- basis, gradient, normalisation


def monomials(points: np.ndarray, axis: int = -1) -> np.ndarray:
    """Monomials ``m(x) = (x², y², z², 2xy, 2xz, 2yz, x, y, z, 1)`` of points, such that ``f(x) = m(x) . p``.

    Parameters
    ----------
    points : ndarray of shape (..., 3), or (3, N) with ``axis=0``
    axis : int
        The axis of the coordinates, which becomes the axis of the 10 monomials: -1 (default) gives shape
        (..., 10); 0 gives rows (10, N), contiguous, as the batched fits of the segmentation use them.

    Returns
    -------
    ndarray of shape (..., 10), or (10, N) with ``axis=0``
    """
    x0, x1, x2 = np.moveaxis(points, axis, 0)
    one = np.ones_like(x0)
    return np.stack([x0 * x0, x1 * x1, x2 * x2, 2 * x0 * x1, 2 * x0 * x2, 2 * x1 * x2, x0, x1, x2, one], axis=axis)


def gradient(params: np.ndarray, points: np.ndarray, axis: int = -1) -> np.ndarray:
    """Gradient ``2 A x + b`` of quadrics at points.

    Parameters
    ----------
    params : ndarray of shape (10,), or broadcastable (..., 10); (10, N) or (10, 1) with ``axis=0``
    points : ndarray of shape (..., 3), or (3, N) with ``axis=0``
    axis : int
        The axis of the parameters and coordinates, and of the gradient's components (see :func:`monomials`).

    Returns
    -------
    ndarray of shape (..., 3), or (3, N) with ``axis=0``
    """
    p = np.moveaxis(params, axis, 0)
    x0, x1, x2 = np.moveaxis(points, axis, 0)
    g0 = 2 * (p[0] * x0 + p[3] * x1 + p[4] * x2) + p[6]
    g1 = 2 * (p[3] * x0 + p[1] * x1 + p[5] * x2) + p[7]
    g2 = 2 * (p[4] * x0 + p[5] * x1 + p[2] * x2) + p[8]
    return np.stack([g0, g1, g2], axis=axis)


def evaluate(params: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic value and gradient of the quadric at points.

    Parameters
    ----------
    params : ndarray of shape (10,)
    points : ndarray of shape (N, 3)

    Returns
    -------
    f : ndarray of shape (N,)
    grad : ndarray of shape (N, 3)

    Notes
    -----
    The gradient is the matrix product ``2 x A + B``, whose rounding differs from :func:`gradient`'s in the last
    bits: the classifiers' decisions were computed with it, so it stays (DESIGN 11.9: stable verdicts).
    """
    A, B, _ = quadric_matrices(params)
    f = monomials(points) @ params
    grad = 2.0 * points @ A + B
    return f, grad


def normalisation_map(mean: np.ndarray, scale: float) -> np.ndarray:
    """Linear map ``L`` (10, 10) from parameters in ``y = (x - mean) / scale`` to parameters in ``x``: ``p_x = L p_y``.

    Equivalently ``m(y) = L' m(x)`` for the monomial vectors.

    ``A = A_n / s²``, ``B = B_n / s - 2 A_n mean / s²``, ``C = C_n + mean' A_n mean / s² - B_n' mean / s``.
    """
    mu, s = np.asarray(mean, dtype=np.float64), float(scale)
    L = np.zeros((10, 10))
    L[np.arange(6), np.arange(6)] = 1.0 / s**2
    for k, (i, j) in enumerate(_A_INDEX):
        E = np.zeros((3, 3))
        E[i, j] = E[j, i] = 1.0
        L[6:9, k] = -2.0 * (E @ mu) / s**2
        L[9, k] = mu @ E @ mu / s**2
    L[6:9, 6:9] = np.eye(3) / s
    L[9, 6:9] = -mu / s
    L[9, 9] = 1.0
    return L


def design_matrices(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monomials D (N, 10) and gradient design G (3, N, 10) with ``f = D p``, ``grad f = G p``."""
    D = monomials(y)
    x, yy, z = y[:, 0], y[:, 1], y[:, 2]
    zero, one = np.zeros_like(x), np.ones_like(x)
    G = np.stack([
        np.stack([2 * x, zero, zero, 2 * yy, 2 * z, zero, one, zero, zero, zero], axis=1),
        np.stack([zero, 2 * yy, zero, 2 * x, zero, 2 * z, zero, one, zero, zero], axis=1),
        np.stack([zero, zero, 2 * z, zero, 2 * x, 2 * yy, zero, zero, one, zero], axis=1),
    ])
    return D, G


# the gradient of the monomials is linear in (x, y, z, 1): grad_k m(y) = (x, y, z, 1) @ MONOMIAL_GRADIENT[k]
MONOMIAL_GRADIENT = np.zeros((3, 4, 10))
for _k, _entries in enumerate((((0, 0), (1, 3), (2, 4)), ((1, 1), (0, 3), (2, 5)), ((2, 2), (0, 4), (1, 5)))):
    for _m, _j in _entries:
        MONOMIAL_GRADIENT[_k, _m, _j] = 2.0
    MONOMIAL_GRADIENT[_k, 3, 6 + _k] = 1.0


def taubin_fit(D: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray | None, str]:
    """Weighted Taubin fit (G. Taubin, PAMI 13(11), 1991): unit parameters (10,), or (None, why) for
    degenerate points.

    ``D`` the monomials (N, 10) of the points ``y`` (N, 3) in normalised coordinates, ``w`` (N,) weights.
    The gradient scatter ``sum w |grad m|²`` is formed from the 4 x 4 moment matrix of ``(y, 1)``, the
    gradient of the monomials being linear in it.
    """
    sw = np.sqrt(w)[:, None]
    Dw = D * sw
    M = Dw.T @ Dw
    # rank check on the design (squared singular values): a quadric through the points must be unique
    ev = np.linalg.eigvalsh(M / np.trace(M))
    if ev[1] < 1e-12:
        return None, ("points are coplanar, collinear or otherwise in a degenerate configuration: "
                      "quadric not unique")
    Y = np.column_stack([y, np.ones(len(y))]) * sw
    S4 = Y.T @ Y
    N9 = sum(g.T @ S4 @ g for g in MONOMIAL_GRADIENT)[:9, :9]
    # eliminate c: c = -M[9, :9] q / M[9, 9]
    S = M[:9, :9] - np.outer(M[:9, 9], M[9, :9]) / M[9, 9]
    S = 0.5 * (S + S.T)
    try:
        vals, vecs = scipy.linalg.eigh(S, N9)
    except np.linalg.LinAlgError:
        return None, "Taubin normalisation matrix is singular (degenerate point configuration)"
    q = vecs[:, int(np.argmin(vals))]
    c = -M[9, :9] @ q / M[9, 9]
    p = np.append(q, c)
    return p / np.linalg.norm(p), ""


# ---------------------------------------------------------------------------------------- residuals


# |cos incidence| floor of the ray residual: near a limb the ray residual amplifies small model errors by
# 1 / cos; beyond ~75 deg the orthogonal distance (scaled by 1 / 0.25) is used instead
MIN_GRAZING = 0.25


def ray_residuals(params: np.ndarray, x: np.ndarray, sigma: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """First-order residuals of points to a quadric, orthogonal and along the sensor ray.

    Parameters
    ----------
    params : ndarray of shape (10,) or (N, 10)
    x : ndarray of shape (N, 3), metres, sensor frame
    sigma : ndarray of shape (N,), metres, optional

    Returns
    -------
    dist_m : ndarray of shape (N,)
        Signed Sampson distance ``f / |grad f|``.
    ray_m : ndarray of shape (N,)
        Signed range change putting the point on the surface to first order, ``-f / (grad f . ray)``
        (the incidence cosine floored at 0.25).
    z : ndarray of shape (N,)
        ``ray_m / sigma`` (NaN if ``sigma`` is None).
    """
    f = np.sum(monomials(x) * params, axis=-1)
    g = gradient(params, x)
    gn = np.sqrt(np.einsum('...k,...k->...', g, g))
    rays = x / np.sqrt(np.einsum('...k,...k->...', x, x))[..., None]
    gr = np.sum(g * rays, axis=-1)
    floor = MIN_GRAZING * gn
    gr = np.where(np.abs(gr) < floor, np.where(gr < 0, -floor, floor), gr)
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = f / gn
        ray = -f / gr
        z = ray / sigma if sigma is not None else np.full_like(ray, np.nan)
    return dist, ray, z


# --------------------------------------------------------------------------------------- validation


def check_patch(points, sigma, normals=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validate a patch once: points (N, 3), sigma (N,) or a scalar, optional normals (N, 3), as float64.

    Raises ValueError naming the expected shape (misuse); degenerate content is the fits' business.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {pts.shape}")
    sig = np.asarray(sigma, dtype=np.float64)
    if sig.ndim == 0:
        sig = np.full(len(pts), float(sig))
    if sig.shape != (len(pts),):
        raise ValueError(f"expected sigma of shape ({len(pts)},), got {sig.shape}")
    nrm = None
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float64)
        if nrm.shape != pts.shape:
            raise ValueError(f"expected normals of shape {pts.shape}, got {nrm.shape}")
    return pts, sig, nrm


def check_points(points: np.ndarray, sigma: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate points (N, 3) and an optional sigma (N,) as float64 (the plain least-squares fits' inputs).

    Raises ValueError naming the expected shape.
    """
    x = np.asanyarray(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {x.shape}")
    s = None
    if sigma is not None:
        s = np.asanyarray(sigma, dtype=np.float64)
        if s.shape != (len(x),):
            raise ValueError(f"expected sigma of shape ({len(x)},), got {s.shape}")
    return x, s
