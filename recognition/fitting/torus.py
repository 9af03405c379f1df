"""Geometric fit of a ring torus (a pipe elbow, the paper's class OTH) and the score test that says when to try
it (:func:`bend_test`): residual ``sqrt((rho - R)² + h²) - r``, started from the tube's spine or from the
bent cylinder, solved by the shared machinery (:mod:`recognition.fitting._solver`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from scenes.geometry import perpendicular_basis

from ._solver import (
    _INIT_POINTS,
    TRIM_SIGMA,
    _collinear,
    _extent,
    _FitStats,
    _huber_cost,
    _input_problem,
    _local_cov,
    _nan_fit,
    _solve,
    _stats,
    _subsample,
    huber_weights,
)
from .algebra import check_patch
from .cylinder import CylinderFit, cylinder_residuals, fit_cylinder

__all__ = ["TorusFit", "fit_torus", "bend_test"]


@dataclass(frozen=True, kw_only=True)
class TorusFit(_FitStats):
    """Ring torus (a pipe elbow): the tube of radius ``minor_radius`` around the circle of radius
    ``major_radius`` centred at ``centre`` in the plane orthogonal to ``axis``.

    Attributes
    ----------
    centre : ndarray of shape (3,), metres
    axis : ndarray of shape (3,), unit (sign arbitrary)
    major_radius : float, metres
        Radius of the tube's centre circle (an elbow's bend radius).
    minor_radius : float, metres
        Radius of the tube (the pipe's).
    sweep : float, radians
        Angle around the axis that the points span (the visible part of the bend).
    cov : ndarray of shape (8, 8)
        Covariance of ``(centre, axis, major_radius, minor_radius)`` (rank 7).
    major_radius_sigma, minor_radius_sigma : float, metres
        First-order (sandwich) sigmas. The pipe radius's is within 20 % of the Monte Carlo spread; the bend
        radius trades off nonlinearly with the centre on a partial arc, and its fit spread 1.3x its
        first-order sigma on a 48 deg arc at factory-scanner noise.
    axis_sigma_rad : float
    """

    centre: np.ndarray
    axis: np.ndarray
    major_radius: float
    minor_radius: float
    sweep: float
    cov: np.ndarray
    major_radius_sigma: float
    minor_radius_sigma: float
    axis_sigma_rad: float
    n_params: int = 7


def _fail_torus(n, reason):
    return _nan_fit(TorusFit, n, reason, centre=np.full(3, np.nan), axis=np.full(3, np.nan), major_radius=np.nan,
                    minor_radius=np.nan, sweep=np.nan, cov=np.full((8, 8), np.nan), major_radius_sigma=np.nan,
                    minor_radius_sigma=np.nan, axis_sigma_rad=np.nan)


def _torus_fun(state, pts, sig):
    """Residuals ``(sqrt((rho - R)² + h²) - r) / sigma`` and their Jacobian w.r.t. the local parameters
    (axis rotation alpha, beta about ``e1``, ``e2``; centre shift (3); R; r).

    ``h`` is the coordinate along the axis from the centre and ``rho`` the distance from the axis. The
    derivative w.r.t. the centre is minus the surface normal; w.r.t. an axis rotation ``a += d e_k`` it is
    ``h (q . e_k) R / (rho s)`` with ``s`` the distance to the tube's centre circle.
    """
    c, a, R, r = state
    e1, e2 = perpendicular_basis(a)
    q = pts - c
    h = q @ a
    u = q - h[:, None] * a
    rho = np.maximum(np.sqrt(np.einsum("ij,ij->i", u, u)), 1e-300)
    s = np.maximum(np.sqrt((rho - R) ** 2 + h * h), 1e-300)
    isig = 1.0 / sig
    k = (rho - R) / rho
    nrm = (u * k[:, None] + h[:, None] * a) / s[:, None]
    g = h * R / (rho * s) * isig
    Jt = np.empty((7, len(pts)))
    Jt[0] = g * (q @ e1)
    Jt[1] = g * (q @ e2)
    Jt[2:5] = -(nrm.T * isig)
    Jt[5] = -(rho - R) / s * isig
    Jt[6] = -isig
    return (s - r) * isig, Jt.T


def _torus_residuals(state, pts, sig):
    """The residuals of :func:`_torus_fun` alone."""
    c, a, R, r = state
    q = pts - c
    h = q @ a
    rho = np.sqrt(np.maximum(np.einsum("ij,ij->i", q, q) - h * h, 0.0))
    return (np.sqrt((rho - R) ** 2 + h * h) - r) / sig


def _torus_retract(state, step):
    c, a, R, r = state
    e1, e2 = perpendicular_basis(a)
    a_new = a + step[0] * e1 + step[1] * e2
    return (c + step[2:5], a_new / np.linalg.norm(a_new), R + step[5], r + step[6])


def _estimate_normals(pts: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals (unoriented) from the PCA of each point's ``k`` nearest neighbours."""
    k = min(k, len(pts))
    _, idx = cKDTree(pts).query(pts, k=k)
    nb = pts[idx] - pts[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb))
    return vecs[:, :, 0]


def _torus_start(pts, w, nrm, r: float):
    """Start ``(centre, axis, R, r)`` for the tube radius ``r``: each point moved by ``r`` against its
    outward normal ``nrm`` lies near the tube's centre circle; a plane fit of the moved points (weights
    ``w``) gives the axis, an algebraic circle fit in that plane the centre and ``R``. None when there is no
    ring torus."""
    spine = pts - r * nrm
    m = (w @ spine) / w.sum()
    y = spine - m
    _, v = np.linalg.eigh((y * w[:, None]).T @ y)
    u1, u2 = y @ v[:, 1], y @ v[:, 2]
    A = np.stack([2.0 * u1, 2.0 * u2, np.ones_like(u1)], axis=1)
    Aw = A * w[:, None]
    try:
        cu, cv, c0 = np.linalg.solve(Aw.T @ A, Aw.T @ (u1 * u1 + u2 * u2))
    except np.linalg.LinAlgError:
        return None
    R = float(np.sqrt(max(c0 + cu * cu + cv * cv, 0.0)))
    if not (np.isfinite(R) and R > r):
        return None
    return m + cu * v[:, 1] + cv * v[:, 2], v[:, 0], R, float(r)


def _bend_step(pts, sig, cyl: CylinderFit, huber: float | None):
    """One weighted least-squares step of the cylinder bent along its axis: ``(direction, R, gain)``, the unit
    direction of the bend across the axis and its radius ``R`` (inf for no bend).

    Near a point of its centre circle a torus is the cylinder tangent there with the axis bent by
    ``h² / (2 R)`` towards the centre (``h`` along the axis): the cylinder's residuals plus ``h² (beta . n)``
    (``n`` the radial direction, ``beta = b / (2 R)`` across the axis). The step is taken in the cylinder's
    five local parameters and ``beta`` (Huber weights of the cylinder's residuals); ``gain`` is the decrease
    of the weighted chi² it predicts beyond the same step without ``beta``.
    """
    r, J = cylinder_residuals((cyl.axis, cyl.point, cyl.radius), pts, sig)
    sw = np.sqrt(huber_weights(r, huber))
    e1, e2 = perpendicular_basis(cyl.axis)
    d = pts - cyl.point
    h = d @ cyl.axis
    u = d - h[:, None] * cyl.axis
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-300)
    h2 = h * h / sig
    A = np.column_stack([J, -h2 * (u @ e1), -h2 * (u @ e2)]) * sw[:, None]
    b = -r * sw
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    sol5, *_ = np.linalg.lstsq(A[:, :5], b, rcond=None)
    res7, res5 = b - A @ sol, b - A[:, :5] @ sol5
    beta = sol[5] * e1 + sol[6] * e2
    nb = float(np.linalg.norm(beta))
    return (beta / nb if nb > 0 else beta), (1.0 / (2.0 * nb) if nb > 0 else np.inf), float(res5 @ res5 - res7 @ res7)


def bend_test(cylinder: CylinderFit, points: np.ndarray, sigma: np.ndarray | float,
              huber: float | None = 3.0) -> tuple[float, float]:
    """Score test of a torus against a fitted cylinder: bending the cylinder's axis by one linear
    least-squares step (see :func:`fit_torus`). Returns the decrease of the (Huber-weighted) chi² it
    predicts and the bend radius of that step, metres (``(0, inf)`` for a failed fit)."""
    pts, sig, _ = check_patch(points, sigma, None)
    if not cylinder.ok or len(pts) < 8:
        return 0.0, np.inf
    _, bend, gain = _bend_step(pts, sig, cylinder, huber)
    return max(gain, 0.0), bend


def _bent_cylinder_start(pts, sig, cyl: CylinderFit, huber: float | None):
    """Start ``(centre, axis, R, r)`` from the bent cylinder (:func:`_bend_step`), for a short visible arc; None
    when the bend is too slight for a ring torus."""
    toward, R, _ = _bend_step(pts, sig, cyl, huber)
    if not (np.isfinite(R) and R > cyl.radius):
        return None
    h = (pts - cyl.point) @ cyl.axis
    mid = cyl.point + 0.5 * (h.max() + h.min()) * cyl.axis
    axis = np.cross(cyl.axis, toward)
    return mid + R * toward, axis / np.linalg.norm(axis), float(R), float(cyl.radius)


def _torus_starts(pts, sig, nrm, r0: float, huber: float | None) -> list:
    """Starts for a tube radius near ``r0`` (an elbow's best cylinder may be far off): the start's cost over
    a log grid of radii from ``r0 / 4`` to ``4 r0``, refined by a bounded scalar search around the best."""
    w = 1.0 / sig**2

    def cost(log_r):
        st = _torus_start(pts, w, nrm, float(np.exp(log_r)))
        return 1e200 if st is None else _huber_cost(_torus_residuals(st, pts, sig), huber)

    grid = np.log(r0) + np.linspace(np.log(0.25), np.log(4.0), 7)
    costs = np.array([cost(g) for g in grid])
    if not (costs < 1e200).any():
        return []
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    best = minimize_scalar(cost, bounds=(lo, hi), method="bounded", options={"xatol": 0.02, "maxiter": 12})
    log_r = best.x if best.fun <= costs[k] else grid[k]
    return [st for st in (_torus_start(pts, w, nrm, float(np.exp(log_r))),) if st is not None]


def fit_torus(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    cylinder: CylinderFit | None = None,
    viewpoint: np.ndarray | None = None,
    max_points: int | None = 1500,
    huber: float | None = 3.0,
    stop_above: float | None = None,
    max_iter: int = 20,
    tol: float = 1e-6,
    trim_sigma: float = TRIM_SIGMA,
) -> TorusFit:
    """Geometric fit of a ring torus (a pipe elbow): residual ``sqrt((rho - R)² + h²) - r``.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
    normals : ndarray of shape (N, 3), optional
        Estimated unit normals (either orientation); None: from each point's 12 nearest neighbours.
    cylinder : CylinderFit, optional
        A cylinder fitted to the same points (the tube's local shape, its radius a start); None: fitted here.
    viewpoint : ndarray of shape (3,), optional
        Where the points were seen from (the sensor; None: the frame's origin, the sensor frame). The tube
        is seen from outside, so the normals are turned to face it.
    max_points, huber, stop_above, max_iter, tol, trim_sigma
        See :func:`fit_sphere`.

    Returns
    -------
    TorusFit
        ``ok=False`` with a reason when the points do not bend around a centre (a straight tube), or the
        fit leaves the ring tori (``R <= r``) or diverges.
    """
    pts, sig, nrm = check_patch(points, sigma, normals)
    n = len(pts)
    why = _input_problem(pts, sig, 8)
    if why:
        return _fail_torus(n, why)
    if _collinear(pts):
        return _fail_torus(n, "points are collinear (or coincide)")
    ext = _extent(pts)
    if cylinder is None:
        cylinder = fit_cylinder(pts, sig, nrm, max_points=max_points, huber=huber)
    if not cylinder.ok:
        return _fail_torus(n, f"no cylinder to start from: {cylinder.reason}")
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
    if vp.shape != (3,):
        raise ValueError(f"expected viewpoint of shape (3,), got {vp.shape}")
    sub = _subsample(n, max_points)
    ps, ss = (pts, sig) if sub is None else (pts[sub], sig[sub])
    crs = _subsample(len(ps), _INIT_POINTS)  # the starts are chosen on a coarse subset
    pc, sc = (ps, ss) if crs is None else (ps[crs], ss[crs])
    nc = None if nrm is None else (nrm if sub is None else nrm[sub])
    nc = nc if nc is None or crs is None else nc[crs]
    if nc is not None and not np.all(np.isfinite(nc)):
        good = np.all(np.isfinite(nc), axis=1)  # the starts need only some points with normals
        pc, sc, nc = (pc[good], sc[good], nc[good]) if good.sum() >= max(8, len(good) // 2) else (pc, sc, None)
    if nc is None:
        nc = _estimate_normals(pc)
    nc = nc * np.where(np.einsum("ij,ij->i", nc, pc - vp) > 0, -1.0, 1.0)[:, None]  # outward: facing the viewer
    starts = _torus_starts(pc, sc, nc, cylinder.radius, huber)
    bent = _bent_cylinder_start(ps, ss, cylinder, huber)
    starts += [] if bent is None else [bent]
    out = _solve(_torus_fun, _torus_retract, starts, pts, sig, max_iter=max_iter, tol=tol, huber=huber,
                 max_points=max_points, stop_above=stop_above, n_starts=2)
    if out is None:
        return _fail_torus(n, "the points do not bend around a centre (a straight tube)")
    state, r, J, wts, it = out
    c, a, R, rr = state
    rr = abs(rr)
    if not (np.isfinite(R) and np.isfinite(rr)) or R > 1e3 * ext:
        return _fail_torus(n, f"torus diverged (major radius {R:.3g} m for a patch of {ext:.3g} m)")
    if R <= rr:
        return _fail_torus(n, f"not a ring torus (major radius {R:.3g} m <= minor radius {rr:.3g} m)")
    cov7 = _local_cov(r, J, wts, 7)
    e1, e2 = perpendicular_basis(a)
    T = np.zeros((8, 7))  # local (alpha, beta, centre, R, r) -> (centre, axis, R, r)
    T[0:3, 2:5] = np.eye(3)
    T[3:6, 0], T[3:6, 1] = e1, e2
    T[6, 5] = T[7, 6] = 1.0
    q = pts - c
    ang = np.arctan2(q @ e2, q @ e1)
    d = _torus_fun(state, pts, np.ones(n))[0]
    return TorusFit(centre=c, axis=a, major_radius=float(R), minor_radius=float(rr), sweep=_arc_span(ang),
                    cov=T @ cov7 @ T.T, major_radius_sigma=float(np.sqrt(cov7[5, 5])),
                    minor_radius_sigma=float(np.sqrt(cov7[6, 6])),
                    axis_sigma_rad=float(np.sqrt(cov7[0, 0] + cov7[1, 1])),
                    **_stats(r, d, 7, it, trim_sigma), ok=True)


def _arc_span(ang: np.ndarray) -> float:
    """Smallest arc (radians) containing all angles: 2 pi minus the widest gap between sorted angles."""
    s = np.sort(ang)
    gaps = np.diff(np.concatenate([s, s[:1] + 2 * np.pi]))
    return float(2 * np.pi - gaps.max())
