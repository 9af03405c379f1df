"""Range-space refit of cylinders and spheres along the sensor's (sub-)rays: removes the radius bias of the
geometric fits (beam footprint, noise along the ray; see :mod:`recognition.fitting`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.geometry import perpendicular_basis

from ._solver import TRIM_SIGMA, _local_cov, _robust_w, _stats, _subsample
from .cylinder import CylinderFit, _axis_stats, _cylinder_cov
from .sphere import SphereFit

__all__ = ["refit_along_rays"]


def _ray_hits(fit, dirs: np.ndarray) -> np.ndarray:
    """Distance from the origin along unit rays ``dirs`` (..., 3) to the near side of a cylinder or sphere
    (NaN where a ray misses)."""
    if isinstance(fit, CylinderFit | _CylProxy):
        a, p, R = fit.axis, fit.point, fit.radius
        w = dirs - (dirs @ a)[..., None] * a
        q0 = -p + (p @ a) * a  # the origin relative to the axis, across it
        A = np.einsum("...i,...i->...", w, w)
        B = w @ q0
        C = q0 @ q0 - R * R
    else:
        c, R = fit.centre, fit.radius
        A = np.ones(dirs.shape[:-1])
        B = -(dirs @ c)
        C = c @ c - R * R
    disc = B * B - A * C
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-B - np.sqrt(disc)) / A
    return np.where((disc >= 0) & (t > 0), t, np.nan)


def refit_along_rays(fit, points: np.ndarray, sigma: np.ndarray, subrays: np.ndarray | None = None, *,
                     huber: float | None = 3.0, trim: float | None = 4.0, max_points: int | None = 1500,
                     max_iter: int = 5, final_points: int | None = 6000, trim_sigma: float = TRIM_SIGMA):
    """Refit a cylinder or sphere by its range-space likelihood: measured minus predicted range along each ray.

    The geometric fits minimise orthogonal distances, which is the likelihood of noise along the normal.
    A range sensor's noise is along the ray, and its return is the mean range of ``k`` sub-rays (the beam
    footprint: the centre ray and a ring around it) placed along the centre ray. Both bias one-sided fits
    of convex surfaces low: on a convex surface the range is a convex function of the ray direction, so the
    footprint mean lies beyond the centre ray's hit (points inside the surface by ``R'' footprint² / 2``, a
    few mm near the silhouette of a thin distant pipe), and the orthogonal-distance fit of ray noise is
    itself biased once sigma is a sizeable fraction of the radius. On the default suite's factory-scanner
    scans the geometric fit came out 2.1 % low (median, far outside its sigma), 0.9 % low after correcting
    the footprint alone.

    Here the predicted range of a point is the mean over its sub-rays of their distance to the model
    surface, the residual ``(|x| - predicted) / sigma`` (``sigma``: range sigma), minimised by Gauss-Newton
    with Huber weights from the geometric solution (numerical Jacobian, a handful of iterations). Points
    with a sub-ray that misses the current model (at the silhouette: their return is mixed with whatever
    lies behind) are left out. The covariance is the sandwich form of :func:`_local_cov`.

    Parameters
    ----------
    fit : CylinderFit or SphereFit
        A geometric fit on ``points`` (any other type, or a failed fit, is returned unchanged).
    points : ndarray of shape (N, 3), metres, sensor frame (the sensor at the origin)
    sigma : ndarray of shape (N,), metres, range sigma along the ray
    subrays : ndarray of shape (k, N, 3), optional
        Unit sub-ray directions per point, the centre ray first; None: the centre rays ``points / |points|``.
    huber, trim, max_points, max_iter, final_points
        Huber threshold (sigma units), hard trimming threshold (sigma units: points beyond it get weight 0),
        subsample size for the iterations, iteration limit, subsample size of the last two iterations and of
        the statistics and covariance (None: all points).
    trim_sigma : float
        Residuals beyond this many sigmas count as ``trim_sigma²`` in the refit's ``chi2_trim``.

    Returns
    -------
    CylinderFit or SphereFit
        The refit, whose residual statistics are range residuals; ``fit`` itself when the refit fails.
    """
    if not isinstance(fit, CylinderFit | SphereFit) or not fit.ok:
        return fit
    pts = np.asarray(points, dtype=np.float64)
    sig = np.asarray(sigma, dtype=np.float64)
    rng = np.linalg.norm(pts, axis=1)
    if subrays is None:
        subrays = (pts / rng[:, None])[None]
    cyl = isinstance(fit, CylinderFit)
    n = len(pts)
    sub = _subsample(n, max_points)
    idx = np.arange(n) if sub is None else sub
    state = (fit.axis, fit.point, fit.radius) if cyl else (fit.centre, fit.radius)
    k = 5 if cyl else 4
    # iterations on the max_points subsample, then two on at most final_points points (the estimate and
    # its covariance are those of the points used: no rescaling)
    every = np.arange(n) if final_points is None or n <= final_points else _subsample(n, final_points)
    it = 0
    schedule = [idx] * max_iter + ([every] * 2 if len(every) > len(idx) else [])
    for it, use in enumerate(schedule, start=1):
        r, J, ii = _range_residuals(state, cyl, subrays, rng, sig, use)
        if len(ii) < max(k + 10, len(use) // 3):
            return fit
        w = _robust_w(r, huber, trim)
        H = J.T @ (J * w[:, None])
        try:
            step = -np.linalg.solve(H + 1e-9 * np.diag(np.diag(H)), J.T @ (w * r))
        except np.linalg.LinAlgError:
            return fit
        state = _range_retract(state, cyl, step)
        if not np.isfinite(state[-1]) or state[-1] <= 0:
            return fit
        small = np.all(np.abs(step) <= 1e-3 * np.sqrt(np.maximum(np.diag(np.linalg.pinv(H)), 1e-300)))
        if small and (use is every or len(every) <= len(idx)):
            break
        if small and it < max_iter:
            schedule[it:max_iter] = []  # converged on the subsample: go on to the final iterations
    r, J, ii = _range_residuals(state, cyl, subrays, rng, sig, every)
    if len(ii) < max(k + 10, len(every) // 3):
        return fit
    wts = _robust_w(r, huber, trim)
    cov_l = _local_cov(r, J, wts, k)
    st = _stats(r, r * sig[ii], k, it, trim_sigma)
    st["n_points"] = n
    if cyl:
        a, p, R = state
        w8 = 1.0 / sig[ii] ** 2
        centroid = (w8 @ pts[ii]) / w8.sum()
        p = p + ((centroid - p) @ a) * a
        cov = _cylinder_cov(a, cov_l)
        return CylinderFit(point=p, axis=a, radius=float(R), length=_axis_stats(pts, a, p), cov=cov,
                           radius_sigma=float(np.sqrt(cov_l[4, 4])),
                           axis_sigma_rad=float(np.sqrt(cov_l[0, 0] + cov_l[1, 1])), **st, ok=True)
    c, R = state
    return SphereFit(centre=c, radius=float(R), cov=cov_l, radius_sigma=float(np.sqrt(cov_l[3, 3])), **st, ok=True)


def _range_retract(state, cyl: bool, step):
    if cyl:
        a, p, R = state
        e1, e2 = perpendicular_basis(a)
        a_new = a + step[0] * e1 + step[1] * e2
        return (a_new / np.linalg.norm(a_new), p + step[2] * e1 + step[3] * e2, state[2] + step[4])
    return (state[0] + step[:3], state[1] + step[3])


def _range_residuals(state, cyl: bool, subrays, rng, sig, ii):
    """Range residuals ``(|x| - mean_j t_j) / sigma`` and their analytic Jacobian over the local parameters
    (cylinder: axis tilts about e1, e2, axis-point shifts along e1, e2, radius; sphere: centre, radius),
    by implicit differentiation of ``F(t, params) = 0`` along each sub-ray; rows whose sub-rays miss the
    model are dropped. Returns (r, J, kept indices)."""
    V = subrays[:, ii]  # (k, m, 3)
    if cyl:
        a, p, R = state
        e1, e2 = perpendicular_basis(a)
        t = _ray_hits(_CylProxy(p, a, R), V)
        X = t[..., None] * V - p
        Xa = X @ a
        q = X - Xa[..., None] * a
        dFdt = 2.0 * np.einsum("kmi,kmi->km", q, V)
        X1, X2 = X @ e1, X @ e2
        dF = np.stack([-2.0 * Xa * X1, -2.0 * Xa * X2, -2.0 * X1, -2.0 * X2, np.full_like(X1, -2.0 * R)], axis=-1)
    else:
        c, R = state
        t = _ray_hits(_SphProxy(c, R), V)
        X = t[..., None] * V - c
        dFdt = 2.0 * np.einsum("kmi,kmi->km", X, V)
        dF = np.concatenate([-2.0 * X, np.full(X.shape[:-1] + (1,), -2.0 * R)], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        dt = -dF / dFdt[..., None]  # (k, m, p)
    T = np.mean(t, axis=0)
    dT = np.mean(dt, axis=0)
    ok = np.isfinite(T) & np.all(np.isfinite(dT), axis=1)
    s = sig[ii][ok]
    return (rng[ii][ok] - T[ok]) / s, -dT[ok] / s[:, None], ii[ok]


@dataclass(frozen=True)
class _CylProxy:
    point: np.ndarray
    axis: np.ndarray
    radius: float


@dataclass(frozen=True)
class _SphProxy:
    centre: np.ndarray
    radius: float
