"""General quadric fits with covariance, and the canonical form with propagated uncertainty.

Two fits, in the parameter convention of :mod:`recognition.fitting.algebra`: :func:`fit_quadric`, the
sigma-weighted geometric estimate that classification uses (section 3 of Fillatreau & Fisher), and
:func:`fit_quadric_lsq`, the plain algebraic least-squares fit the segmenter attaches to its curved patches
("planes or quadrics are fitted to the patches"; :func:`recognition.fitting.fit_plane_lsq` for planar ones).
The parameter vector is only defined up to scale: fits return it with unit norm (the scale gauge), and the
(10, 10) covariance is built from the rank-9 pseudo-inverse of the information matrix restricted to the
tangent space of the unit sphere (so ``cov @ p == 0``), by default in sandwich form (see
:func:`fit_quadric`).

Fitting (section 3 of Fillatreau & Fisher): points are centred on their mean and scaled to unit RMS radius
(numerical conditioning), the quadric is initialised by Taubin's method (G. Taubin, "Estimation of planar
curves, surfaces and nonplanar space curves ...", IEEE PAMI 13(11), 1991, doi:10.1109/34.103273) and refined
by Levenberg-Marquardt (Gauss-Newton with damping) on the Sampson distance ``f / |grad f|`` divided by each
point's sigma. The paper uses an extended Kalman filter on the same model; a batch Gauss-Newton reaches the
same estimate and covariance. The normalised parameters and their covariance are mapped back to the input
frame linearly, then renormalised to unit norm.

Canonicalisation: ``A = R' diag(l1, l2, l3) R``, centre ``T`` from ``A T = -B/2`` (a rank-truncated
pseudo-inverse when an eigenvalue is ~0, i.e. cylinders), ``C_cano = C + T'(A T + B) = f(T)``. The sign is
normalised so that at least two eigenvalues are positive and the scale so that the mean of the two largest
eigenvalues is 1: a cylinder of radius r becomes (1, 1, 0) with ``C_cano = -r²``, a sphere (1, 1, 1) with
``C_cano = -r²`` and a right circular cone of half-angle a (1, 1, -tan² a) with ``C_cano = 0``. ``C_cano`` is
reported in m² (the input frame's units squared). Its uncertainty and that of the eigenvalues come from
first-order Jacobians (``dl_i = v_i' dA v_i``; the derivative of the rank-truncated ``C_cano`` includes the
rotation of the eigenvectors), with correlations; the paper's Bauer-Fike bound is available for the
eigenvalue sigmas (see :func:`canonicalise`).

Monte Carlo check (200 noise draws, tests/test_quadric.py): first-order sigmas of ``C_cano`` and of the
eigenvalues are within 0.93-1.06 of the observed spread (cylinder with the rank-2 solve, cone, ellipsoid);
the Bauer-Fike sigmas are a bound, 4-34x the observed eigenvalue spread.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .algebra import (
    check_patch,
    check_points,
    design_matrices,
    gradient,
    monomials,
    normalisation_map,
    quadric_matrices,
    ray_residuals,
    taubin_fit,
)

__all__ = [
    "QuadricFit",
    "CanonicalQuadric",
    "QuadricSurfaceFit",
    "fit_quadric",
    "fit_quadric_lsq",
    "canonicalise",
    "canonical_quantities",
]


@dataclass(frozen=True)
class QuadricFit:
    """A fitted general quadric.

    Attributes
    ----------
    params : ndarray of shape (10,)
        Unit-norm parameters in the input frame, order ``(a11, a22, a33, a12, a13, a23, b1, b2, b3, c)``.
    cov : ndarray of shape (10, 10)
        Covariance of ``params`` (rank 9, the scale gauge removed: ``cov @ params == 0``).
    params_n, cov_n : ndarray of shape (10,), (10, 10)
        The same in the normalised frame ``y = (x - mean) / scale`` in which the fit was computed
        (better conditioned: canonicalisation works there).
    mean : ndarray of shape (3,), metres
    scale : float, metres
    n_points : int
    chi2 : float
        Sum of squared sigma-normalised Sampson distances.
    rms_m : float
        RMS Sampson distance in metres.
    rms_sigma : float
        RMS of the sigma-normalised Sampson distances.
    n_iter : int
    ok : bool
    reason : str
        Why the fit is degenerate ("" when ``ok``).
    """

    params: np.ndarray
    cov: np.ndarray
    params_n: np.ndarray
    cov_n: np.ndarray
    mean: np.ndarray
    scale: float
    n_points: int
    chi2: float
    rms_m: float
    rms_sigma: float
    n_iter: int
    ok: bool
    reason: str = ""

    def __bool__(self) -> bool:
        return self.ok


@dataclass(frozen=True)
class CanonicalQuadric:
    """Canonical form of a quadric with the covariance of its canonical parameters.

    Attributes
    ----------
    eigenvalues : ndarray of shape (3,)
        Normalised eigenvalues ``(l1, l2, l3)``, descending, at least two positive, ``(l1 + l2) / 2 = 1``.
    axes : ndarray of shape (3, 3)
        Rows are the unit eigenvectors (``R`` of the paper, input frame): ``X' = R (X - centre)``.
    centre : ndarray of shape (3,), metres
        ``T`` solving ``A T = -B / 2`` (rank-truncated when ``rank < 3``), in the input frame.
    c_cano : float, m²
        ``C_cano`` after the same normalisation (``-r²`` for a cylinder or sphere of radius r).
    cov : ndarray of shape (4, 4)
        Covariance of ``(l1, l2, l3, c_cano)``. The eigenvalue block depends on ``sigma_mode``.
    sigma_mode : str
        ``"first_order"`` or ``"bauer_fike"``.
    rank : int
        Number of eigenvalues used in the centre solve (2: the eigenvalue closest to 0 was truncated).
    truncated : int
        Index (0..2) of the truncated eigenvalue, -1 if none.
    jacobian_n : ndarray of shape (4, 10)
        First-order Jacobian of ``(l1, l2, l3, c_cano)`` w.r.t. ``QuadricFit.params_n``.
    """

    eigenvalues: np.ndarray
    axes: np.ndarray
    centre: np.ndarray
    c_cano: float
    cov: np.ndarray
    sigma_mode: str
    rank: int
    truncated: int
    jacobian_n: np.ndarray

    @property
    def sigmas(self) -> np.ndarray:
        """ndarray of shape (4,): standard deviations of ``(l1, l2, l3, c_cano)``."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None))

    def difference(self, i: int, j: int) -> tuple[float, float]:
        """Value and propagated sigma of ``l_i - l_j`` (0-based indices), correlations included."""
        g = np.zeros(4)
        g[i], g[j] = 1.0, -1.0
        return float(self.eigenvalues[i] - self.eigenvalues[j]), float(np.sqrt(max(g @ self.cov @ g, 0.0)))


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


# ------------------------------------------------------------------------------------------ fitting


def _degenerate(n: int, reason: str, mean=None, scale: float = 1.0) -> QuadricFit:
    nan10 = np.full(10, np.nan)
    return QuadricFit(
        params=nan10, cov=np.full((10, 10), np.nan), params_n=nan10.copy(), cov_n=np.full((10, 10), np.nan),
        mean=np.zeros(3) if mean is None else mean, scale=scale, n_points=n, chi2=np.nan, rms_m=np.nan,
        rms_sigma=np.nan, n_iter=0, ok=False, reason=reason,
    )


def _sampson(p: np.ndarray, D: np.ndarray, G: np.ndarray, s: np.ndarray):
    """Sigma-normalised Sampson distances (N,) and their Jacobian (N, 10) w.r.t. p."""
    f = D @ p
    grad = G @ p  # (3, N)
    g = np.maximum(np.sqrt(np.einsum("ij,ij->j", grad, grad)), 1e-12)
    sg = s * g
    r = f / sg
    gdg = np.einsum("ij,ijk->jk", grad, G)
    J = D / sg[:, None] - (r / (g * g))[:, None] * gdg
    return r, J


def fit_quadric(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    max_iter: int = 20,
    tol: float = 1e-9,
    with_cov: bool = True,
    cov_mode: str = "sandwich",
) -> QuadricFit:
    """Fit a general quadric with per-point noise and return its parameter covariance.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
    sigma : ndarray of shape (N,) or float, metres
        Per-point noise sigma (used as the sigma of the geometric distance to the surface).
    normals : ndarray of shape (N, 3), optional
        Unused by the algebraic fit (accepted for interface symmetry with the dedicated fits).
    max_iter : int
        Maximum Levenberg-Marquardt iterations after the Taubin initialisation.
    tol : float
        Relative decrease of the cost below which the iteration stops.
    with_cov : bool
        False skips the covariance (NaN), e.g. when the fit only initialises another fit.
    cov_mode : {"sandwich", "scaled"}
        ``"scaled"``: ``s² H^+`` with ``H = J'J`` and ``s² = chi² / (n - 9)``. ``"sandwich"`` (default):
        ``H^+ (J' diag(r²) J) H^+ n / (n - 9)``, robust to a sigma that is not the sigma of the fitted
        distance point by point (range noise is along the ray, the distance is along the normal, so the
        normalised residuals of grazing points are smaller: ``"scaled"`` then over-predicted the sigma of
        ``C_cano`` of cylinders 1.5x in a Monte Carlo check, the sandwich matched).

    Returns
    -------
    QuadricFit
        ``ok=False`` with a ``reason`` for fewer than 10 points, non-finite input or a degenerate
        (coplanar, collinear) configuration; never raises for such data.

    Raises
    ------
    ValueError
        On wrong shapes.
    """
    pts, sig, _ = check_patch(points, sigma)
    if cov_mode not in ("sandwich", "scaled"):
        raise ValueError(f"cov_mode must be 'sandwich' or 'scaled', got {cov_mode!r}")
    n = len(pts)
    if n < 10:
        return _degenerate(n, f"too few points for a quadric fit ({n} < 10)")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(sig))):
        return _degenerate(n, "non-finite points or sigma")
    if np.any(sig <= 0):
        return _degenerate(n, "sigma must be positive")
    mean = pts.mean(axis=0)
    d = pts - mean
    scale = float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))
    if not scale > 0:
        return _degenerate(n, "all points coincide", mean)
    y = d / scale
    s = sig / scale
    D, G = design_matrices(y)
    p, why = taubin_fit(D, y, 1.0 / s**2)
    if p is None:
        return _degenerate(n, why, mean, scale)
    r, J = _sampson(p, D, G, s)
    cost = float(r @ r)
    lam = 1e-6
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        P = np.eye(10) - np.outer(p, p)
        Jt = J @ P
        H = Jt.T @ Jt
        g = Jt.T @ r
        improved = False
        for _ in range(8):
            Hd = H + lam * np.diag(np.diag(H) + 1e-12) + np.outer(p, p)
            try:
                step = -np.linalg.solve(Hd, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            p_new = p + step
            p_new /= np.linalg.norm(p_new)
            r_new, J_new = _sampson(p_new, D, G, s)
            cost_new = float(r_new @ r_new)
            if np.isfinite(cost_new) and cost_new <= cost:
                improved = True
                rel = (cost - cost_new) / max(cost, 1e-300)
                p, r, J, cost = p_new, r_new, J_new, cost_new
                lam = max(lam / 10, 1e-12)
                break
            lam *= 10
        if not improved or rel < tol:
            break

    L = normalisation_map(mean, scale)
    pw = L @ p
    nw = np.linalg.norm(pw)
    rm = r * s * scale  # Sampson distances in metres
    stats = {"mean": mean, "scale": scale, "n_points": n, "chi2": cost,
             "rms_m": float(np.sqrt(np.mean(rm**2))), "rms_sigma": float(np.sqrt(cost / n)), "n_iter": it,
             "ok": True, "reason": ""}
    if not with_cov:
        nan = np.full((10, 10), np.nan)
        return QuadricFit(params=pw / nw, cov=nan, params_n=p, cov_n=nan.copy(), **stats)
    P = np.eye(10) - np.outer(p, p)
    Jt = J @ P
    H = Jt.T @ Jt
    dof = max(n - 9, 1)
    try:
        Hinv = np.linalg.inv(H + np.outer(p, p)) - np.outer(p, p)
    except np.linalg.LinAlgError:
        return _degenerate(n, "singular information matrix", mean, scale)
    if cov_mode == "sandwich":
        Jr = Jt * r[:, None]
        cov_n = (n / dof) * Hinv @ (Jr.T @ Jr) @ Hinv
    else:
        cov_n = (cost / dof) * Hinv
    cov_n = 0.5 * (cov_n + cov_n.T)
    # back to the input frame, renormalised to unit norm
    Jn = (np.eye(10) - np.outer(pw, pw) / nw**2) / nw @ L
    cov = Jn @ cov_n @ Jn.T
    return QuadricFit(params=pw / nw, cov=0.5 * (cov + cov.T), params_n=p, cov_n=cov_n, **stats)


def _failed_cov(n: int) -> np.ndarray:
    return np.full((n, n), np.nan)


def _orient_params(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Flip the sign so that ``f`` grows towards the sensor (origin) on average over the points."""
    g = gradient(p, x)
    return -p if np.sum(g * x) > 0 else p


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
    x, s = check_points(points, sigma)
    n = len(x)
    if n < 10:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "fewer than 10 points")
    mean = x.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1))))
    if not scale > 0:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "coincident points")
    D = monomials((x - mean) / scale)
    Mn = D.T @ D
    lam, V = np.linalg.eigh(Mn)
    if lam[1] <= 1e-13 * lam[-1]:
        return QuadricSurfaceFit(np.full(10, np.nan), _failed_cov(10), np.nan, np.nan, n, False,
                                 "rank-deficient design (the points do not determine a quadric)")
    pn = V[:, 0]
    s2 = max(float(lam[0]), 0.0) / max(n - 9, 1)
    w = lam[1:] / (lam[1:] - lam[0]) ** 2
    cov_n = s2 * (V[:, 1:] * w) @ V[:, 1:].T
    T = normalisation_map(mean, scale)
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


# ----------------------------------------------------------------------------------- canonical form


def _sym_grad_to_params(G: np.ndarray) -> np.ndarray:
    """Gradient w.r.t. the 6 A-parameters of ``<G, A>`` for symmetric G (off-diagonals count twice)."""
    return np.array([G[0, 0], G[1, 1], G[2, 2], 2 * G[0, 1], 2 * G[0, 2], 2 * G[1, 2]])


def canonical_quantities(params: np.ndarray, rank: int | None = None) -> dict:
    """Raw (un-normalised) canonical quantities of a quadric and their Jacobians.

    Eigenvalues are sorted descending. No sign or scale normalisation is applied.

    Parameters
    ----------
    params : ndarray of shape (10,)
    rank : {2, 3} or None
        2 truncates the eigenvalue closest to 0 in the centre solve, 3 uses all; None means 3.

    Returns
    -------
    dict with keys
        ``eigenvalues`` (3,), ``vectors`` (3, 3) columns = eigenvectors, ``centre`` (3,), ``c_cano`` float,
        ``truncated`` int (-1 if none), ``jacobian`` (4, 10) of ``(l1, l2, l3, c_cano)`` w.r.t. params.
    """
    p = np.asarray(params, dtype=np.float64)
    A, B, C = quadric_matrices(p)
    lam, V = np.linalg.eigh(A)
    order = np.argsort(lam)[::-1]
    lam, V = lam[order], V[:, order]
    keep = np.ones(3, dtype=bool)
    truncated = -1
    if rank == 2:
        truncated = int(np.argmin(np.abs(lam)))
        keep[truncated] = False
    b = V.T @ B  # components of B on the eigenvectors
    with np.errstate(divide="ignore", invalid="ignore"):
        coef = np.where(keep, -b / (2.0 * lam), 0.0)
    centre = V @ coef
    c_cano = C + 0.5 * float(B @ centre)
    J = np.zeros((4, 10))
    for i in range(3):
        v = V[:, i]
        J[i, :6] = _sym_grad_to_params(np.outer(v, v))
    # C_cano = C - sum_{i kept} b_i² / (4 l_i)
    Gm = np.outer(centre, centre)
    for i in np.flatnonzero(keep):
        for j in np.flatnonzero(~keep):
            w = -b[i] * b[j] / (2.0 * lam[i] * (lam[i] - lam[j]))
            Gm += 0.5 * w * (np.outer(V[:, i], V[:, j]) + np.outer(V[:, j], V[:, i]))
    J[3, :6] = _sym_grad_to_params(Gm)
    J[3, 6:9] = centre
    J[3, 9] = 1.0
    return {"eigenvalues": lam, "vectors": V, "centre": centre, "c_cano": c_cano, "truncated": truncated,
            "jacobian": J}


def canonicalise(
    fit: QuadricFit,
    *,
    rank: int | None = None,
    sigma_mode: str = "first_order",
    null_z: float = 3.0,
) -> CanonicalQuadric:
    """Canonical form ``X'^t A_cano X' + C_cano = 0`` of a fitted quadric with propagated covariance.

    Parameters
    ----------
    fit : QuadricFit
        Must be ``ok``.
    rank : {2, 3} or None
        Rank of the centre solve ``A T = -B/2``. 2 truncates the eigenvalue closest to zero (cylinders:
        pseudo-inverse), 3 is the full inverse (spheres, cones: the centre is the apex). None chooses 2 when
        the eigenvalue closest to zero is not significantly non-zero (``|l| < null_z * sigma_l``, first-order
        sigma) and 3 otherwise.
    sigma_mode : {"first_order", "bauer_fike"}
        Eigenvalue uncertainty. ``"first_order"``: ``dl_i = v_i' dA v_i`` with the full (10, 10) parameter
        covariance, correlations with ``C_cano`` included. ``"bauer_fike"`` (the paper): every eigenvalue of a
        symmetric matrix moves by at most ``||dA||_2`` (the eigenvector matrix is orthogonal, condition number
        1); we take ``sigma_l = sqrt(E ||dA||_F²)`` (the Frobenius norm bounds the 2-norm) from the
        covariance of the six A-parameters, independent between eigenvalues and of ``C_cano``.
    null_z : float
        z-threshold of the automatic rank choice.

    Returns
    -------
    CanonicalQuadric
        Quantities normalised in sign (>= 2 positive eigenvalues) and scale (``(l1 + l2)/2 = 1``), with
        ``c_cano`` in m², centre and axes in the input frame.
    """
    if not fit.ok:
        raise ValueError(f"cannot canonicalise a failed quadric fit: {fit.reason}")
    if sigma_mode not in ("first_order", "bauer_fike"):
        raise ValueError(f"sigma_mode must be 'first_order' or 'bauer_fike', got {sigma_mode!r}")
    p = fit.params_n.copy()
    lam0 = np.linalg.eigvalsh(quadric_matrices(p)[0])
    if np.count_nonzero(lam0 > 0) < 2:
        p = -p
    cov_n = fit.cov_n
    if rank is None:
        q = canonical_quantities(p, rank=3)
        Jl = q["jacobian"][:3]
        sl = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", Jl, cov_n, Jl), 0.0))
        k = int(np.argmin(np.abs(q["eigenvalues"])))
        rank = 2 if abs(q["eigenvalues"][k]) < null_z * sl[k] else 3
    q = canonical_quantities(p, rank=rank)
    lam, V, J = q["eigenvalues"], q["vectors"], q["jacobian"]
    raw = np.append(lam, q["c_cano"])
    cov_raw = J @ cov_n @ J.T
    if sigma_mode == "bauer_fike":
        ca = cov_n[:6, :6]
        var_f = float(np.sum(np.diag(ca)[:3]) + 2.0 * np.sum(np.diag(ca)[3:]))
        cov_raw[:3, :] = 0.0
        cov_raw[:, :3] = 0.0
        cov_raw[np.arange(3), np.arange(3)] = var_f
    # scale normalisation y = raw / m, m = (l1 + l2) / 2
    m = 0.5 * (lam[0] + lam[1])
    y = raw / m
    N = np.eye(4) / m
    N[:, 0] -= 0.5 * y / m
    N[:, 1] -= 0.5 * y / m
    cov = N @ cov_raw @ N.T
    # C in m²: normalised frame -> input frame
    s2 = fit.scale**2
    y[3] *= s2
    D = np.diag([1.0, 1.0, 1.0, s2])
    cov = D @ cov @ D
    return CanonicalQuadric(
        eigenvalues=y[:3].copy(), axes=V.T.copy(), centre=fit.mean + fit.scale * q["centre"],
        c_cano=float(y[3]), cov=0.5 * (cov + cov.T), sigma_mode=sigma_mode, rank=int(rank),
        truncated=q["truncated"], jacobian_n=D @ N @ J,
    )
