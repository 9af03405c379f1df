"""Plane fits: the dedicated weighted fit (classification) and the plain total-least-squares fit of the
segmenter's planar patches (section 3 of Fillatreau & Fisher), both giving a :class:`PlaneFit`.

:func:`fit_plane` is a weighted total-least-squares plane (weights ``1 / sigma²``, closed form) with the
sandwich covariance and residuals in sigma units of the orthogonal distance, like every dedicated fit.
:func:`fit_plane_lsq` is the unweighted total-least-squares plane the segmenter attaches to its patches, with
the first-order covariance of the eigen-decomposition and residuals along the sensor ray in sigma units (the
range change that would put the point on the plane).

Both fix the sign gauge so that the unit normal faces the sensor (the origin of the points' frame) unless
normals say otherwise: for ``normal . x = offset`` the offset is then negative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.geometry import perpendicular_basis

from ._solver import TRIM_SIGMA, _check_origin, _FitStats, _input_problem, _local_cov, _nan_fit, _stats
from .algebra import check_patch, check_points, plane_params, ray_residuals

__all__ = ["PlaneFit", "fit_plane", "fit_plane_lsq"]


@dataclass(frozen=True, kw_only=True)
class PlaneFit(_FitStats):
    """Plane ``normal . x = offset``.

    Attributes
    ----------
    normal : ndarray of shape (3,), unit
        Facing the sensor (``normal . x < 0`` on the patch) unless given normals said otherwise.
    offset : float, metres
        ``-offset`` is the distance of the plane from the origin (the sensor) when the normal faces it.
    cov : ndarray of shape (4, 4)
        Covariance of ``(normal, offset)`` (rank 3: the normal's norm is fixed).
    normal_sigma_rad : float
        RMS angle of the normal error, ``sqrt(trace)`` of the tilt covariance.
    offset_sigma : float, metres
    rms_m, rms_sigma, chi2, chi2_trim
        Residual statistics (:class:`~recognition.fitting._solver._FitStats`): of the orthogonal distance over
        sigma for :func:`fit_plane`, of the range residual along the ray over sigma for :func:`fit_plane_lsq`
        (whose ``chi2_trim`` is NaN, and ``rms_sigma`` and ``chi2`` NaN without sigma).
    """

    normal: np.ndarray
    offset: float
    cov: np.ndarray
    normal_sigma_rad: float
    offset_sigma: float
    n_params: int = 3

    @property
    def params(self) -> np.ndarray:
        """The plane as quadric parameters (10,), ``f = normal . x - offset``."""
        return plane_params(self.normal, self.offset)


def _fail_plane(n, reason):
    return _nan_fit(PlaneFit, n, reason, normal=np.full(3, np.nan), offset=np.nan,
                    cov=np.full((4, 4), np.nan), normal_sigma_rad=np.nan, offset_sigma=np.nan)


def fit_plane(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    origin: np.ndarray | None = None,
    cos_min: float = 0.2,
    trim_sigma: float = TRIM_SIGMA,
) -> PlaneFit:
    """Weighted total-least-squares plane (closed form: weighted PCA, weights ``1/sigma²``).

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
    normals : ndarray of shape (N, 3), optional
        Only used to orient the normal (towards the mean of the given normals).
    origin, cos_min
        See :func:`fit_sphere` (with an origin the weighted fit is repeated once with the incidence-scaled
        sigmas).
    trim_sigma : float
        Residuals beyond this many sigmas count as ``trim_sigma²`` in the fit's ``chi2_trim``.

    Returns
    -------
    PlaneFit
        ``ok=False`` for fewer than 3 points, non-finite input or collinear points.
    """
    pts, sig, nrm = check_patch(points, sigma, normals)
    n = len(pts)
    why = _input_problem(pts, sig, 3)
    if why:
        return _fail_plane(n, why)
    org = _check_origin(origin)
    sig_in = sig
    for _ in range(1 if org is None else 2):
        w = 1.0 / sig**2
        c = (w @ pts) / w.sum()
        d = pts - c
        S = (d * w[:, None]).T @ d
        vals, vecs = np.linalg.eigh(S)
        if vals[1] <= 1e-12 * max(vals[2], 1e-300):
            return _fail_plane(n, "points are collinear: plane not unique")
        nv = vecs[:, 0]
        if org is not None:
            u = pts - org
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            sig = sig_in * np.maximum(np.abs(u @ nv), cos_min)
    if nrm is not None and np.all(np.isfinite(nrm)) and nv @ nrm.sum(axis=0) < 0:
        nv = -nv
    elif nrm is None and nv @ c > 0:
        nv = -nv  # face the origin (the sensor, for points in the sensor frame)
    off = float(nv @ c)
    dist = pts @ nv - off
    r = dist / sig
    e1, e2 = perpendicular_basis(nv)
    # local parameters: tilt about (e1, e2) through the weighted centroid, offset
    J = np.stack([(d @ e1) / sig, (d @ e2) / sig, -1.0 / sig], axis=1)
    cov3 = _local_cov(r, J, np.ones(n), 3)
    # map (tilt1, tilt2, offset at centroid) -> (normal, offset): offset = n . c, dn = t1 e1 + t2 e2
    M = np.zeros((4, 3))
    M[:3, 0], M[:3, 1] = e1, e2
    M[3, 0], M[3, 1], M[3, 2] = e1 @ c, e2 @ c, 1.0
    cov = M @ cov3 @ M.T
    return PlaneFit(normal=nv, offset=off, cov=cov, normal_sigma_rad=float(np.sqrt(cov3[0, 0] + cov3[1, 1])),
                    offset_sigma=float(np.sqrt(cov[3, 3])), **_stats(r, dist, 3, 0, trim_sigma), ok=True)


def fit_plane_lsq(points: np.ndarray, sigma: np.ndarray | None = None) -> PlaneFit:
    """Total-least-squares plane through points (unweighted), normal facing the sensor: the segmenter's fit.

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
    >>> fit = fit_plane_lsq(np.column_stack([g, np.full(25, 3.0)]))
    >>> np.round(fit.normal, 6).tolist(), round(fit.offset, 6)
    ([0.0, 0.0, -1.0], -3.0)
    """
    x, s = check_points(points, sigma)
    n = len(x)
    if n < 3:
        return _fail_plane(n, "fewer than 3 points")
    c = x.mean(axis=0)
    S = (x - c).T @ (x - c)
    lam, V = np.linalg.eigh(S)
    if lam[1] <= 1e-12 * max(lam[2], 1e-300):
        return _fail_plane(n, "collinear points")
    normal = V[:, 0]
    if normal @ c > 0:
        normal = -normal
    offset = float(normal @ c)
    dof = max(n - 3, 1)
    s2 = max(float(lam[0]), 0.0) / dof
    Cn = s2 * (np.outer(V[:, 1], V[:, 1]) / lam[1] + np.outer(V[:, 2], V[:, 2]) / lam[2])
    cov = np.empty((4, 4))
    cov[:3, :3] = Cn
    cov[:3, 3] = cov[3, :3] = Cn @ c
    cov[3, 3] = s2 / n + c @ Cn @ c
    p = plane_params(normal, offset)
    dist, _, z = ray_residuals(p, x, s)
    rms_s = float(np.sqrt(np.mean(z**2))) if s is not None else float("nan")
    chi2 = float(np.sum(z**2)) if s is not None else float("nan")
    return PlaneFit(normal=normal, offset=offset, cov=cov, normal_sigma_rad=float(np.sqrt(np.trace(Cn))),
                    offset_sigma=float(np.sqrt(cov[3, 3])), rms_m=float(np.sqrt(np.mean(dist**2))), rms_sigma=rms_s,
                    chi2=chi2, n_points=n, n_iter=0, ok=True)
