"""Geometric cylinder and cone fits with covariance (dedicated fits of classification, section 3 of
Fillatreau & Fisher), sharing their axis machinery.

Initial axes come from the axis of the Taubin quadric (or of the normals when given, :func:`axis_candidates`)
followed by an algebraic circle fit, so a few iterations of the shared solver (:mod:`recognition.fitting._solver`)
suffice. The cone is parameterised by a point on its axis near the data, the radius there and the slope
``t = tan(half-angle)``, so it is continuous through ``t = 0`` (the cylinder) and nests it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.geometry import perpendicular_basis

from ._solver import (
    _INIT_POINTS,
    TRIM_SIGMA,
    _check_origin,
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
    _with_incidence,
)
from .algebra import check_patch
from .quadric import QuadricFit, canonicalise, fit_quadric

__all__ = ["CylinderFit", "ConeFit", "fit_cylinder", "fit_cone", "axis_candidates", "cylinder_residuals",
           "cone_residuals"]


@dataclass(frozen=True, kw_only=True)
class CylinderFit(_FitStats):
    """Cylinder: axis line through ``point`` with direction ``axis``, ``radius``.

    Attributes
    ----------
    point : ndarray of shape (3,), metres
        The point of the axis closest to the data centroid.
    axis : ndarray of shape (3,), unit
    radius : float, metres
    length : float, metres
        Visible extent of the points along the axis.
    cov : ndarray of shape (7, 7)
        Covariance of ``(point, axis, radius)`` (rank 5).
    radius_sigma : float, metres
    axis_sigma_rad : float
        RMS angle of the axis error.
    """

    point: np.ndarray
    axis: np.ndarray
    radius: float
    length: float
    cov: np.ndarray
    radius_sigma: float
    axis_sigma_rad: float
    n_params: int = 5


@dataclass(frozen=True, kw_only=True)
class ConeFit(_FitStats):
    """Cone: radius ``radius_at_point + tan(half_angle) * h`` at signed distance h along ``axis`` from
    ``point``; the axis points from the apex into the surface (``half_angle >= 0``).

    Attributes
    ----------
    apex : ndarray of shape (3,), metres
        ``point - radius_at_point / tan(half_angle) * axis`` (infinite coordinates when the half-angle is 0).
    axis : ndarray of shape (3,), unit
    half_angle : float, radians
    length : float, metres
        Visible extent of the points along the axis.
    point : ndarray of shape (3,), metres
        The point of the axis closest to the data centroid.
    radius_at_point : float, metres
    cov : ndarray of shape (8, 8)
        Covariance of ``(point, axis, radius_at_point, half_angle)`` (rank 6).
    half_angle_sigma : float, radians
    axis_sigma_rad : float
    """

    apex: np.ndarray
    axis: np.ndarray
    half_angle: float
    length: float
    point: np.ndarray
    radius_at_point: float
    cov: np.ndarray
    half_angle_sigma: float
    axis_sigma_rad: float
    n_params: int = 6


def _cylinder_cov(a: np.ndarray, cov5: np.ndarray) -> np.ndarray:
    """Covariance (7, 7) of (point, axis, radius) from that (5, 5) of the local parameters: the axis turn
    and the point shift along the two directions ``perpendicular_basis(a)`` perpendicular to the axis, and the
    radius."""
    e1, e2 = perpendicular_basis(a)
    M = np.zeros((7, 5))
    M[0:3, 2], M[0:3, 3] = e1, e2
    M[3:6, 0], M[3:6, 1] = e1, e2
    M[6, 4] = 1.0
    return M @ cov5 @ M.T


def _fail_cylinder(n, reason):
    return _nan_fit(CylinderFit, n, reason, point=np.full(3, np.nan), axis=np.full(3, np.nan), radius=np.nan,
                    length=np.nan, cov=np.full((7, 7), np.nan), radius_sigma=np.nan, axis_sigma_rad=np.nan)


def _fail_cone(n, reason):
    return _nan_fit(ConeFit, n, reason, apex=np.full(3, np.nan), axis=np.full(3, np.nan), half_angle=np.nan,
                    length=np.nan, point=np.full(3, np.nan), radius_at_point=np.nan,
                    cov=np.full((8, 8), np.nan), half_angle_sigma=np.nan, axis_sigma_rad=np.nan)


# ---------------------------------------------------------------------------------------- residuals


def cone_residuals(state, pts, sig):
    """Residuals and Jacobian w.r.t. (alpha, beta, u, v, r0, t) for the cone; t fixed at 0 for cylinder.

    In the frame (e1, e2, a) at the axis point p: ``rho = |(u1, u2)|``, ``h`` the axial coordinate, distance
    ``(rho - r0 - t h) / sqrt(1 + t²)``.
    """
    a, p, r0, t = state
    e1, e2 = perpendicular_basis(a)
    W = (pts - p) @ np.stack([e1, e2, a], axis=1)
    u1, u2, h = W[:, 0], W[:, 1], W[:, 2]
    rho = np.sqrt(u1 * u1 + u2 * u2)
    inv = 1.0 / np.maximum(rho, 1e-300)
    n1, n2 = u1 * inv, u2 * inv
    k = 1.0 / np.sqrt(1.0 + t * t)
    isig = k / sig
    dist = (rho - r0 - t * h) * k
    Jt = np.empty((6, len(pts)))  # rows are contiguous: faster to fill; returned transposed (a view)
    Jt[0] = (-h * n1 - t * u1) * isig
    Jt[1] = (-h * n2 - t * u2) * isig
    Jt[2] = -n1 * isig
    Jt[3] = -n2 * isig
    Jt[4] = -isig
    Jt[5] = (-h - dist * t * k) * isig
    return dist / sig, Jt.T


def _cone_normals(state, pts):
    a, p, t = state[0], state[1], (state[3] if len(state) > 3 else 0.0)
    w = pts - p
    q = w - (w @ a)[:, None] * a
    nh = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-300)
    return (nh - t * a) / np.sqrt(1.0 + t * t)


def cylinder_residuals(state, pts, sig):
    a, p, r0 = state
    e1, e2 = perpendicular_basis(a)
    W = (pts - p) @ np.stack([e1, e2, a], axis=1)
    u1, u2, h = W[:, 0], W[:, 1], W[:, 2]
    rho = np.sqrt(u1 * u1 + u2 * u2)
    inv = 1.0 / np.maximum(rho, 1e-300)
    isig = 1.0 / sig
    n1, n2 = u1 * inv * isig, u2 * inv * isig
    Jt = np.empty((5, len(pts)))
    Jt[0] = -h * n1
    Jt[1] = -h * n2
    Jt[2] = -n1
    Jt[3] = -n2
    Jt[4] = -isig
    return (rho - r0) * isig, Jt.T


def _regauge(a, p, r0, t, centroid):
    s = (centroid - p) @ a
    return p + s * a, r0 + t * s


def _make_retract(centroid, cone: bool):
    def retract(state, step):
        a, p = state[0], state[1]
        e1, e2 = perpendicular_basis(a)
        a_new = a + step[0] * e1 + step[1] * e2
        a_new /= np.linalg.norm(a_new)
        p_new = p + step[2] * e1 + step[3] * e2
        r0 = state[2] + step[4]
        t = state[3] + step[5] if cone else 0.0
        p_new, r0 = _regauge(a_new, p_new, r0, t, centroid)
        return (a_new, p_new, r0, t) if cone else (a_new, p_new, r0)

    return retract


# ------------------------------------------------------------------------------------------- starts


def _circle_init(pts: np.ndarray, w: np.ndarray, a: np.ndarray):
    """Axis point (closest to the centroid) and radius from an algebraic circle fit orthogonal to ``a``."""
    m = (w @ pts) / w.sum()
    e1, e2 = perpendicular_basis(a)
    y = pts - m
    u, v = y @ e1, y @ e2
    A0 = np.stack([2 * u, 2 * v, np.ones_like(u)], axis=1)
    b0 = u * u + v * v
    keep = np.ones(len(u), bool)
    for _ in range(2):
        # algebraic circle fit, then once more without the points far off it: a few percent of pixels from
        # another surface (across a depth jump) otherwise drag the start into a wrong basin
        sw = np.sqrt(w[keep])
        sol, *_ = np.linalg.lstsq(A0[keep] * sw[:, None], b0[keep] * sw, rcond=None)
        cu, cv = sol[0], sol[1]
        R = float(np.sqrt(max(sol[2] + cu * cu + cv * cv, 1e-300)))
        dev = np.abs(np.hypot(u - cu, v - cv) - R)
        mad = 1.4826 * float(np.median(dev))
        new_keep = dev <= max(6.0 * mad, 1e-12)
        if new_keep.all() or new_keep.sum() < max(10, len(u) // 2):
            break
        keep = new_keep
    return m + cu * e1 + cv * e2, R


def axis_candidates(
    points: np.ndarray,
    sigma: np.ndarray,
    normals: np.ndarray | None = None,
    *,
    quadric: QuadricFit | None = None,
) -> list[np.ndarray]:
    """Candidate axis directions (unit, shape (3,)) for cylinders and cones.

    From the Taubin/Sampson quadric (the eigenvector whose eigenvalue is most distinct from the other two;
    ``quadric`` if given, else a Taubin fit of the points) and, when normals are given, from their scatter
    matrix (the direction most orthogonal to them).
    """
    cands = []
    q = fit_quadric(points, sigma, max_iter=0, with_cov=False) if quadric is None else quadric
    if q.ok:
        can = canonicalise(q, rank=3)
        lam = can.eigenvalues
        dist = [min(abs(lam[i] - lam[j]) for j in range(3) if j != i) for i in range(3)]
        # all three eigenvectors, the most distinct eigenvalue first: on small noisy patches the quadric's
        # eigenvalue pattern can be wrong while one of its eigenvectors is still close to the axis
        cands.extend(can.axes[i] for i in np.argsort(dist)[::-1])
    if normals is not None:
        nn = normals[np.all(np.isfinite(normals), axis=1)]
        if len(nn) >= 3:
            _, vecs = np.linalg.eigh(nn.T @ nn)
            cands.append(vecs[:, 0])
    if not cands:
        _, vecs = np.linalg.eigh(np.cov((points - points.mean(axis=0)).T))
        cands.append(vecs[:, 2])  # a patch elongated along the axis
    return cands


def _axis_stats(pts, a, p):
    h = (pts - p) @ a
    return float(h.max() - h.min())


# ----------------------------------------------------------------------------------------- cylinder


def fit_cylinder(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    init: tuple[np.ndarray, np.ndarray, float] | None = None,
    axes: list[np.ndarray] | None = None,
    max_points: int | None = 1500,
    huber: float | None = 3.0,
    origin: np.ndarray | None = None,
    cos_min: float = 0.2,
    stop_above: float | None = None,
    max_iter: int = 20,
    tol: float = 1e-6,
    trim_sigma: float = TRIM_SIGMA,
) -> CylinderFit:
    """Geometric cylinder fit (residual: distance to the axis minus the radius).

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
    normals : ndarray of shape (N, 3), optional
        Estimated unit normals: an extra axis candidate.
    init : (point (3,), axis (3,), radius) or None
        Initial values; None: from the quadric's axis and/or the normals, then an algebraic circle fit.
    axes : list of ndarray of shape (3,), optional
        Precomputed axis candidates (see :func:`axis_candidates`), to share them between fits.
    max_points, huber, origin, cos_min, max_iter, tol, trim_sigma
        See :func:`fit_sphere`.

    Returns
    -------
    CylinderFit
    """
    pts, sig, nrm = check_patch(points, sigma, normals)
    n = len(pts)
    why = _input_problem(pts, sig, 6)
    if why:
        return _fail_cylinder(n, why)
    if _collinear(pts):
        return _fail_cylinder(n, "points are collinear (or coincide)")
    ext = _extent(pts)
    w = 1.0 / sig**2
    centroid = (w @ pts) / w.sum()
    sub = _subsample(n, max_points)
    ps, ss = (pts, sig) if sub is None else (pts[sub], sig[sub])
    if init is None:
        best = None
        if axes is None:
            axes = axis_candidates(ps, ss, None if nrm is None else (nrm if sub is None else nrm[sub]))
        crs = _subsample(len(ps), _INIT_POINTS)
        pc, sc = (ps, ss) if crs is None else (ps[crs], ss[crs])
        for a in axes:
            p0, R0 = _circle_init(pc, 1.0 / sc**2, a)
            st = (a, _regauge(a, p0, R0, 0.0, centroid)[0], R0)
            c = _huber_cost(cylinder_residuals(st, pc, sc)[0], huber)
            if best is None or c < best[0]:
                best = (c, st)
        state = best[1]
    else:
        a = np.asarray(init[1], float)
        a = a / np.linalg.norm(a)
        p0, _ = _regauge(a, np.asarray(init[0], float), float(init[2]), 0.0, centroid)
        state = (a, p0, float(init[2]))
    if not np.isfinite(state[2]):
        return _fail_cylinder(n, "no finite initial radius")
    fun = _with_incidence(cylinder_residuals, _cone_normals, _check_origin(origin), cos_min)
    state, r, J, wts, it = _solve(fun, _make_retract(centroid, cone=False), [state], pts, sig,
                                  max_iter=max_iter, tol=tol, huber=huber, max_points=max_points,
                                  stop_above=stop_above)
    a, p, R = state
    if not np.isfinite(R) or abs(R) > 1e3 * ext:
        return _fail_cylinder(
            n, f"cylinder radius diverged ({R:.3g} m for a patch of {ext:.3g} m): planar patch")
    R = abs(R)
    cov5 = _local_cov(r, J, wts, 5)
    cov = _cylinder_cov(a, cov5)
    d = cylinder_residuals(state, pts, np.ones(n))[0]
    return CylinderFit(point=p, axis=a, radius=float(R), length=_axis_stats(pts, a, p), cov=cov,
                       radius_sigma=float(np.sqrt(cov5[4, 4])),
                       axis_sigma_rad=float(np.sqrt(cov5[0, 0] + cov5[1, 1])),
                       **_stats(r, d, 5, it, trim_sigma), ok=True)


# --------------------------------------------------------------------------------------------- cone


def _cone_result(state, r, J, wts, pts, sig, it, ext, trim_sigma):
    a, p, r0, t = state
    d = cone_residuals(state, pts, np.ones(len(pts)))[0]
    n = len(pts)
    if not (np.isfinite(t) and np.isfinite(r0)) or abs(r0) > 1e3 * ext:
        return _fail_cone(n, "cone parameters diverged: planar patch")
    e1, e2 = perpendicular_basis(a)
    cov6 = _local_cov(r, J, wts, 6)
    sgn = 1.0
    if t < 0:  # orient the axis from the apex into the surface
        sgn = -1.0
        a, t = -a, -t
    half = float(np.arctan(t))
    M = np.zeros((8, 6))
    M[0:3, 2], M[0:3, 3] = e1, e2
    M[3:6, 0], M[3:6, 1] = sgn * e1, sgn * e2
    M[6, 4] = 1.0
    M[7, 5] = sgn / (1.0 + t * t)
    cov = M @ cov6 @ M.T
    with np.errstate(divide="ignore", invalid="ignore"):
        apex = p - (r0 / t) * a if t > 0 else np.full(3, np.inf)
    return ConeFit(apex=apex, axis=a, half_angle=half, length=_axis_stats(pts, a, p), point=p,
                   radius_at_point=float(r0), cov=cov, half_angle_sigma=float(np.sqrt(cov[7, 7])),
                   axis_sigma_rad=float(np.sqrt(cov6[0, 0] + cov6[1, 1])),
                   **_stats(r, d, 6, it, trim_sigma), ok=True)


def fit_cone(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    init: CylinderFit | tuple | None = None,
    axes: list[np.ndarray] | None = None,
    quadric: QuadricFit | None = None,
    axis_search: bool = True,
    max_points: int | None = 1500,
    huber: float | None = 3.0,
    origin: np.ndarray | None = None,
    cos_min: float = 0.2,
    stop_above: float | None = None,
    max_iter: int = 20,
    tol: float = 1e-6,
    trim_sigma: float = TRIM_SIGMA,
) -> ConeFit:
    """Geometric cone fit (orthogonal distance to the cone's generatrix in the meridian half-plane).

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
    normals : ndarray of shape (N, 3), optional
        Estimated unit normals: an extra axis candidate.
    init : CylinderFit, (point (3,), axis (3,), radius_at_point, tan_half_angle) or None
        Initial values. Besides this, the cone is always also started from each candidate axis with a
        linear fit of radius against axial position; the best result is kept. Starting from a cylinder fit
        guarantees the cone's chi² is not worse than the cylinder's (the models are nested).
    axes : list of ndarray of shape (3,), optional
        Precomputed axis candidates (see :func:`axis_candidates`).
    quadric : QuadricFit, optional
        A quadric fitted to the points: when its canonical form has one negative eigenvalue, its apex,
        axis and half-angle are one more start.
    axis_search : bool
        False: start only from ``init`` (e.g. to polish a previous solution); ignored without ``init``.
    max_points, huber, origin, cos_min, max_iter, tol, trim_sigma
        See :func:`fit_sphere`.

    Returns
    -------
    ConeFit
        ``half_angle`` may be ~0 (a cylinder); the apex is then at infinity.
    """
    pts, sig, nrm = check_patch(points, sigma, normals)
    n = len(pts)
    why = _input_problem(pts, sig, 7)
    if why:
        return _fail_cone(n, why)
    if _collinear(pts):
        return _fail_cone(n, "points are collinear (or coincide)")
    ext = _extent(pts)
    w = 1.0 / sig**2
    centroid = (w @ pts) / w.sum()
    sub = _subsample(n, max_points)
    ps, ss = (pts, sig) if sub is None else (pts[sub], sig[sub])
    starts = []
    if isinstance(init, CylinderFit):
        if init.ok:
            starts.append((init.axis, init.point, init.radius, 0.0))
    elif init is not None:
        a = np.asarray(init[1], float)
        starts.append((a / np.linalg.norm(a), np.asarray(init[0], float), float(init[2]), float(init[3])))
    search = axis_search or not starts
    if search and axes is None:
        axes = axis_candidates(ps, ss, None if nrm is None else (nrm if sub is None else nrm[sub]))
    crs = _subsample(len(ps), _INIT_POINTS)
    pc, sc = (ps, ss) if crs is None else (ps[crs], ss[crs])
    if search and quadric is not None and quadric.ok:
        can = canonicalise(quadric, rank=3)
        lam = can.eigenvalues
        if lam[2] < 0 < lam[1]:
            a = can.axes[2]
            hc = float((centroid - can.centre) @ a)
            if hc < 0:
                a, hc = -a, -hc
            t = float(np.sqrt(-lam[2] / (0.5 * (lam[0] + lam[1]))))
            if np.isfinite(hc) and np.isfinite(t):
                starts.append((a, can.centre + hc * a, t * hc, t))
    for a in axes if search else []:
        p0, _ = _circle_init(pc, 1.0 / sc**2, a)
        y = pc - p0
        h = y @ a
        q = y - h[:, None] * a
        rho = np.sqrt(np.einsum("ij,ij->i", q, q))
        A = np.stack([np.ones_like(h), h], axis=1) / sc[:, None]
        sol, *_ = np.linalg.lstsq(A, rho / sc, rcond=None)
        starts.append((a, p0, float(sol[0]), float(sol[1])))
    retract = _make_retract(centroid, cone=True)
    fun = _with_incidence(cone_residuals, _cone_normals, _check_origin(origin), cos_min)
    states = []
    for a, p0, r0, t in starts:
        p0, r0 = _regauge(a, p0, r0, t, centroid)
        st = (a, p0, r0, t)
        if all(np.all(np.isfinite(x)) for x in st):
            states.append(st)
    # two starts: the cone's cost landscape is curved (tilt and taper trade off on one-sided patches), and
    # the start of lowest initial cost (often the cylinder) is not always the one that converges best
    out = _solve(fun, retract, states, pts, sig, max_iter=max_iter, tol=tol, huber=huber,
                 max_points=max_points, stop_above=stop_above, n_starts=2)
    if out is None:
        return _fail_cone(n, "no finite initial cone")
    st, r, J, wts, it = out
    return _cone_result(st, r, J, wts, pts, sig, it, ext, trim_sigma)
