"""Least-squares plane and general-quadric fits of segmented patches, with covariance.

These are the plain fits the segmenter attaches to its patches (section 3 of Fillatreau & Fisher: "planes or
quadrics are fitted to the patches"); the refined, sigma-weighted quadric estimation used for classification
lives in :mod:`recognition.quadric`. Both use the same parameter convention:

    p = (a11, a22, a33, a12, a13, a23, b1, b2, b3, c),   f(x) = m(x) . p = x' A x + b' x + c,
    m(x) = (x², y², z², 2xy, 2xz, 2yz, x, y, z, 1).

Points are in the sensor frame (sensor at the origin), so the ray of a point ``x`` is ``x / |x|``. Both fits
fix the sign gauge so that ``f > 0`` on the sensor side of the surface (for the plane ``n . x = d`` this
means the unit normal ``n`` faces the sensor, and ``d < 0``).

Residuals are reported in metres (orthogonal, first-order Sampson distance ``|f| / |grad f|``) and in
sigma units along the ray (``|f| / (|grad f . ray| sigma)``: the range change that would put the point on the
surface, divided by the point's range sigma).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "PlaneFit",
    "QuadricSurfaceFit",
    "fit_plane",
    "fit_quadric_lsq",
    "quadric_monomials",
    "quadric_gradient",
    "normalisation_transform",
    "ray_residuals",
    "plane_params",
]

# |cos incidence| floor of the ray residual: near a limb the ray residual amplifies small model errors by
# 1 / cos; beyond ~75 deg the orthogonal distance (scaled by 1 / 0.25) is used instead
_MIN_GRAZING = 0.25


def _failed_cov(n: int) -> np.ndarray:
    return np.full((n, n), np.nan)


@dataclass(frozen=True)
class PlaneFit:
    """A total-least-squares plane ``normal . x = d``.

    Attributes
    ----------
    normal : ndarray of shape (3,)
        Unit normal, facing the sensor (``normal . x < 0`` on the patch).
    d : float, metres
        Offset: ``-d`` is the distance of the plane from the sensor origin.
    cov : ndarray of shape (4, 4)
        First-order covariance of ``(normal, d)`` from the residual variance (rank 3: the normal's norm is
        fixed).
    centroid : ndarray of shape (3,), metres
    rms_m : float, metres
        RMS orthogonal residual.
    rms_sigma : float
        RMS residual along the ray in units of each point's range sigma (NaN without sigma).
    n_points : int
    ok : bool
    reason : str
        Why the fit failed ("" when ``ok``); a failed fit is falsy.
    """

    normal: np.ndarray
    d: float
    cov: np.ndarray
    centroid: np.ndarray
    rms_m: float
    rms_sigma: float
    n_points: int
    ok: bool = True
    reason: str = ""
    kind: str = field(default="plane", init=False)

    def __bool__(self) -> bool:
        return self.ok

    @property
    def params(self) -> np.ndarray:
        """The plane as quadric parameters (10,), ``f = n . x - d``."""
        return plane_params(self.normal, self.d)


@dataclass(frozen=True)
class QuadricSurfaceFit:
    """A general quadric ``x' A x + b' x + c = 0`` fitted by algebraic least squares (unit-norm gauge).

    Attributes
    ----------
    params : ndarray of shape (10,)
        Unit-norm parameters in the sensor frame, order ``(a11, a22, a33, a12, a13, a23, b1, b2, b3, c)``;
        ``f > 0`` on the sensor side.
    cov : ndarray of shape (10, 10)
        First-order covariance of ``params`` from the algebraic residuals (rank 9, ``cov @ params ~ 0``).
    rms_m : float, metres
        RMS first-order (Sampson) distance.
    rms_sigma : float
        RMS residual along the ray in sigma units (NaN without sigma).
    n_points : int
    ok : bool
    reason : str
    """

    params: np.ndarray
    cov: np.ndarray
    rms_m: float
    rms_sigma: float
    n_points: int
    ok: bool = True
    reason: str = ""
    kind: str = field(default="quadric", init=False)

    def __bool__(self) -> bool:
        return self.ok

    @property
    def A(self) -> np.ndarray:
        """Symmetric (3, 3) matrix of the quadratic part."""
        p = self.params
        return np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])

    @property
    def b(self) -> np.ndarray:
        """Linear part (3,)."""
        return self.params[6:9].copy()

    @property
    def c(self) -> float:
        """Constant term."""
        return float(self.params[9])


def plane_params(normal: np.ndarray, d: float) -> np.ndarray:
    """Quadric parameters (10,) of the plane ``normal . x - d = 0``."""
    p = np.zeros(10)
    p[6:9] = normal
    p[9] = -d
    return p


def quadric_monomials(x: np.ndarray) -> np.ndarray:
    """Monomials ``(x², y², z², 2xy, 2xz, 2yz, x, y, z, 1)`` of points (N, 3) -> (N, 10)."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    one = np.ones_like(x0)
    return np.stack([x0 * x0, x1 * x1, x2 * x2, 2 * x0 * x1, 2 * x0 * x2, 2 * x1 * x2, x0, x1, x2, one], axis=-1)


def quadric_gradient(params: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Gradient ``2 A x + b`` of the quadric at points (..., 3); ``params`` (10,) or broadcastable (..., 10)."""
    p = params
    g0 = 2 * (p[..., 0] * x[..., 0] + p[..., 3] * x[..., 1] + p[..., 4] * x[..., 2]) + p[..., 6]
    g1 = 2 * (p[..., 3] * x[..., 0] + p[..., 1] * x[..., 1] + p[..., 5] * x[..., 2]) + p[..., 7]
    g2 = 2 * (p[..., 4] * x[..., 0] + p[..., 5] * x[..., 1] + p[..., 2] * x[..., 2]) + p[..., 8]
    return np.stack([g0, g1, g2], axis=-1)


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
    f = np.sum(quadric_monomials(x) * params, axis=-1)
    g = quadric_gradient(params, x)
    gn = np.sqrt(np.einsum('...k,...k->...', g, g))
    rays = x / np.sqrt(np.einsum('...k,...k->...', x, x))[..., None]
    gr = np.sum(g * rays, axis=-1)
    floor = _MIN_GRAZING * gn
    gr = np.where(np.abs(gr) < floor, np.where(gr < 0, -floor, floor), gr)
    with np.errstate(invalid="ignore", divide="ignore"):
        dist = f / gn
        ray = -f / gr
        z = ray / sigma if sigma is not None else np.full_like(ray, np.nan)
    return dist, ray, z


def normalisation_transform(mean: np.ndarray, scale: float) -> np.ndarray:
    """Map (10, 10) from parameters in ``y = (x - mean) / scale`` to parameters in ``x``: ``p_x = T p_y``.

    Equivalently ``m(y) = T' m(x)`` for the monomial vectors.
    """
    m0, m1, m2 = np.asarray(mean, dtype=np.float64)
    s = float(scale)
    is2 = 1.0 / s**2
    T = np.zeros((10, 10))
    T[np.arange(6), np.arange(6)] = is2
    # b_x = -2 A_y mean / s² + b_y / s
    T[6, [0, 3, 4]] = [-2 * m0 * is2, -2 * m1 * is2, -2 * m2 * is2]
    T[7, [3, 1, 5]] = [-2 * m0 * is2, -2 * m1 * is2, -2 * m2 * is2]
    T[8, [4, 5, 2]] = [-2 * m0 * is2, -2 * m1 * is2, -2 * m2 * is2]
    T[6, 6] = T[7, 7] = T[8, 8] = 1.0 / s
    # c_x = mean' A_y mean / s² - b_y . mean / s + c_y
    T[9, :6] = np.array([m0 * m0, m1 * m1, m2 * m2, 2 * m0 * m1, 2 * m0 * m2, 2 * m1 * m2]) * is2
    T[9, 6:9] = [-m0 / s, -m1 / s, -m2 / s]
    T[9, 9] = 1.0
    return T


def _check(points: np.ndarray, sigma: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    x = np.asanyarray(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"expected points of shape (N, 3), got {x.shape}")
    s = None
    if sigma is not None:
        s = np.asanyarray(sigma, dtype=np.float64)
        if s.shape != (len(x),):
            raise ValueError(f"expected sigma of shape ({len(x)},), got {s.shape}")
    return x, s


def _orient_params(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Flip the sign so that ``f`` grows towards the sensor (origin) on average over the points."""
    g = quadric_gradient(p, x)
    return -p if np.sum(g * x) > 0 else p


def fit_plane(points: np.ndarray, sigma: np.ndarray | None = None) -> PlaneFit:
    """Total-least-squares plane through points, normal facing the sensor.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres, sensor frame
    sigma : ndarray of shape (N,), metres, optional
        Range sigma along the ray, for ``rms_sigma``.

    Returns
    -------
    PlaneFit
        Falsy with a reason when fewer than 3 points or the points are collinear.

    Examples
    --------
    >>> import numpy as np
    >>> g = np.stack(np.meshgrid(np.arange(5.0), np.arange(5.0)), -1).reshape(-1, 2)
    >>> fit = fit_plane(np.column_stack([g, np.full(25, 3.0)]))
    >>> np.round(fit.normal, 6).tolist(), round(fit.d, 6)
    ([0.0, 0.0, -1.0], -3.0)
    """
    x, s = _check(points, sigma)
    n = len(x)
    nan3 = np.full(3, np.nan)
    if n < 3:
        return PlaneFit(nan3, np.nan, _failed_cov(4), nan3, np.nan, np.nan, n, False, "fewer than 3 points")
    c = x.mean(axis=0)
    S = (x - c).T @ (x - c)
    lam, V = np.linalg.eigh(S)
    if lam[1] <= 1e-12 * max(lam[2], 1e-300):
        return PlaneFit(nan3, np.nan, _failed_cov(4), c, np.nan, np.nan, n, False, "collinear points")
    normal = V[:, 0]
    if normal @ c > 0:
        normal = -normal
    d = float(normal @ c)
    dof = max(n - 3, 1)
    s2 = max(float(lam[0]), 0.0) / dof
    Cn = s2 * (np.outer(V[:, 1], V[:, 1]) / lam[1] + np.outer(V[:, 2], V[:, 2]) / lam[2])
    cov = np.empty((4, 4))
    cov[:3, :3] = Cn
    cov[:3, 3] = cov[3, :3] = Cn @ c
    cov[3, 3] = s2 / n + c @ Cn @ c
    p = plane_params(normal, d)
    dist, _, z = ray_residuals(p, x, s)
    rms_s = float(np.sqrt(np.mean(z**2))) if s is not None else float("nan")
    return PlaneFit(normal, d, cov, c, float(np.sqrt(np.mean(dist**2))), rms_s, n)


def fit_quadric_lsq(points: np.ndarray, sigma: np.ndarray | None = None) -> QuadricSurfaceFit:
    """General quadric by algebraic least squares with the unit-norm gauge, in normalised coordinates.

    The points are centred on their mean and scaled to unit RMS radius, the parameter vector minimising
    ``sum f(y_i)²`` with ``|p| = 1`` is the smallest eigenvector of the scatter of monomials, then it is
    mapped back to the sensor frame and renormalised. Covariance: first-order eigenvector perturbation,
    ``s² sum_k l_k / (l_k - l_0)² v_k v_k'`` with ``s²`` the algebraic residual variance, mapped with the
    same linear transform and the Jacobian of the renormalisation.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres, sensor frame
    sigma : ndarray of shape (N,), metres, optional

    Returns
    -------
    QuadricSurfaceFit
        Falsy with a reason below 10 points or for a rank-deficient design.
    """
    x, s = _check(points, sigma)
    n = len(x)
    if n < 10:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "fewer than 10 points")
    mean = x.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1))))
    if not scale > 0:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "coincident points")
    D = quadric_monomials((x - mean) / scale)
    Mn = D.T @ D
    lam, V = np.linalg.eigh(Mn)
    if lam[1] <= 1e-13 * lam[-1]:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "rank-deficient design (the points do not determine a quadric)")
    pn = V[:, 0]
    s2 = max(float(lam[0]), 0.0) / max(n - 9, 1)
    w = lam[1:] / (lam[1:] - lam[0]) ** 2
    cov_n = s2 * (V[:, 1:] * w) @ V[:, 1:].T
    T = normalisation_transform(mean, scale)
    q = T @ pn
    qn = float(np.linalg.norm(q))
    p = q / qn
    Jn = (np.eye(10) - np.outer(p, p)) / qn
    JT = Jn @ T
    cov = JT @ cov_n @ JT.T
    p = _orient_params(p, x)
    dist, _, z = ray_residuals(p, x, s)
    rms_s = float(np.sqrt(np.mean(z**2))) if s is not None else float("nan")
    return QuadricSurfaceFit(p, cov, float(np.sqrt(np.mean(dist**2))), rms_s, n)
