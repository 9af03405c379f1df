"""Geometric sphere fit with covariance (a dedicated fit: classification verifies its label with it, section 3
of Fillatreau & Fisher): residual ``|x - c| - R`` from an algebraic start, solved by the
shared Levenberg-Marquardt machinery (:mod:`recognition.fitting._solver`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._solver import (
    TRIM_SIGMA,
    _check_origin,
    _collinear,
    _extent,
    _FitStats,
    _input_problem,
    _local_cov,
    _nan_fit,
    _solve,
    _stats,
    _with_incidence,
)
from .algebra import check_patch

__all__ = ["SphereFit", "fit_sphere"]


@dataclass(frozen=True, kw_only=True)
class SphereFit(_FitStats):
    """Sphere.

    Attributes
    ----------
    centre : ndarray of shape (3,), metres
    radius : float, metres
    cov : ndarray of shape (4, 4)
        Covariance of ``(centre, radius)``.
    radius_sigma : float, metres
    """

    centre: np.ndarray
    radius: float
    cov: np.ndarray
    radius_sigma: float
    n_params: int = 4


def _fail_sphere(n, reason):
    return _nan_fit(SphereFit, n, reason, centre=np.full(3, np.nan), radius=np.nan,
                    cov=np.full((4, 4), np.nan), radius_sigma=np.nan)


def _sphere_fun(state, pts, sig):
    c, R = state
    d = pts - c
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    isig = 1.0 / sig
    Jt = np.empty((4, len(pts)))
    Jt[:3] = -(d.T * (isig / np.maximum(rho, 1e-300)))
    Jt[3] = -isig
    return (rho - R) * isig, Jt.T


def _sphere_normals(state, pts):
    d = pts - state[0]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)


def _sphere_retract(state, step):
    return (state[0] + step[:3], state[1] + step[3])


def fit_sphere(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    init: tuple[np.ndarray, float] | None = None,
    max_points: int | None = 1500,
    huber: float | None = 3.0,
    origin: np.ndarray | None = None,
    cos_min: float = 0.2,
    stop_above: float | None = None,
    max_iter: int = 15,
    tol: float = 1e-6,
    trim_sigma: float = TRIM_SIGMA,
) -> SphereFit:
    """Geometric sphere fit (residual ``|x - c| - R``) from an algebraic initialisation.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
    normals : ndarray of shape (N, 3), optional (unused)
    init : (centre (3,), radius) or None
        Initial values; None: algebraic (linear) sphere fit.
    max_points : int or None
        Subsample size for the iterations (None: all points).
    huber : float or None
        Huber threshold in sigma units (None: plain least squares).
    origin : ndarray of shape (3,), optional
        Sensor origin in the points' frame. When given, ``sigma`` is taken as range noise along the ray and
        each point's distance sigma becomes ``sigma * max(|cos(incidence)|, cos_min)`` (incidence from the
        model normal), which reduces the radius bias of one-sided patches; otherwise ``sigma`` is used as
        the sigma of the orthogonal distance.
    cos_min : float
        Floor of the incidence cosine (grazing points are not trusted more than this).
    stop_above : float or None
        Stop early once the robust chi² decreases by < 1 % per iteration while above this value (e.g. the
        chi² of a competing model: the fit is losing anyway).
    max_iter, tol : int, float
        Iteration limit and relative cost decrease at which to stop.
    trim_sigma : float
        Residuals beyond this many sigmas count as ``trim_sigma²`` in the fit's ``chi2_trim``.

    Returns
    -------
    SphereFit
    """
    pts, sig, _ = check_patch(points, sigma, normals)
    n = len(pts)
    why = _input_problem(pts, sig, 4)
    if why:
        return _fail_sphere(n, why)
    if _collinear(pts):
        return _fail_sphere(n, "points are collinear (or coincide)")
    ext = _extent(pts)
    if init is None:
        m = pts.mean(axis=0)
        y = pts - m
        w = 1.0 / sig**2
        A = np.concatenate([2 * y, np.ones((n, 1))], axis=1) * np.sqrt(w)[:, None]
        b = np.einsum("ij,ij->i", y, y) * np.sqrt(w)
        sol, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
        if rank < 4 or sv[-1] < 1e-9 * sv[0]:
            return _fail_sphere(n, "points are coplanar: sphere not unique")
        c0 = sol[:3] + m
        R0 = float(np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 1e-300)))
    else:
        c0, R0 = np.asarray(init[0], dtype=np.float64), float(init[1])
    fun = _with_incidence(_sphere_fun, _sphere_normals, _check_origin(origin), cos_min)
    # the algebraic start is close whenever a sphere fits: one 10x worse than a competitor is not iterated
    state, r, J, wts, it = _solve(fun, _sphere_retract, [(c0, R0)], pts, sig, max_iter=max_iter,
                                  tol=tol, huber=huber, max_points=max_points, stop_above=stop_above,
                                  hopeless_after=0)
    c, R = state
    if not np.isfinite(R) or R > 1e3 * ext or R <= 0:
        return _fail_sphere(n, f"sphere radius diverged ({R:.3g} m for a patch of {ext:.3g} m): planar patch")
    cov = _local_cov(r, J, wts, 4)
    d = _sphere_fun(state, pts, np.ones(n))[0]
    return SphereFit(centre=c, radius=float(R), cov=cov, radius_sigma=float(np.sqrt(cov[3, 3])),
                     **_stats(r, d, 4, it, trim_sigma), ok=True)
