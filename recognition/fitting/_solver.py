"""The machinery the dedicated fits share (:mod:`recognition.fitting`): a Levenberg-Marquardt solver on a
manifold with Huber weights, coarse-to-fine subsampling, residual statistics and the sandwich covariance.

Every fit minimises the (Huber-robustified) sum of squared sigma-normalised orthogonal distances with a
small Levenberg-Marquardt solver on a manifold (axes are updated by a rotation in the plane orthogonal to
them, axis points slide in that plane), using vectorised residuals and analytic Jacobians, and stops on a
relative cost decrease below ``tol``.

Large patches are subsampled on a regular stride (deterministic) to ``max_points`` for the iterations:
the start of lowest cost is chosen and iterated on a coarse subset of 400 points, refined by a few
iterations on the ``max_points`` subsample and polished by Gauss-Newton steps on all points; the residual
statistics and the covariance are computed on all points (so they reflect the whole patch).

The covariance is the sandwich ``H^-1 (J' W diag(r²) W J) H^-1 n / (n - k)`` with ``H = J' W J`` over the
minimal local parameters (``W``: Huber weights, ``r``: sigma-normalised residuals), then mapped to the
reported parameters (:func:`_local_cov`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["TRIM_SIGMA", "huber_weights", "trimmed_chi2"]


@dataclass(frozen=True, kw_only=True)
class _FitStats:
    """Common fields: residual statistics on all points and the status."""

    rms_m: float
    rms_sigma: float
    chi2: float
    n_points: int
    n_iter: int
    ok: bool
    reason: str = ""
    chi2_trim: float = float("nan")

    def __bool__(self) -> bool:
        return self.ok


# ------------------------------------------------------------------------------------------ helpers


def _input_problem(pts: np.ndarray, sig: np.ndarray, n_min: int) -> str:
    if len(pts) < n_min:
        return f"too few points ({len(pts)} < {n_min})"
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(sig))):
        return "non-finite points or sigma"
    if np.any(sig <= 0):
        return "sigma must be positive"
    return ""


_INIT_POINTS = 400  # points used to choose between initial values (and for the coarse iterations)


def _subsample(n: int, max_points: int | None) -> np.ndarray | None:
    """Regular-stride indices (deterministic) or None when no subsampling is needed."""
    if max_points is None or n <= max_points:
        return None
    return np.linspace(0, n - 1, max_points).round().astype(np.intp)


def huber_weights(r: np.ndarray, c: float | None) -> np.ndarray:
    if c is None:
        return np.ones_like(r)
    a = np.abs(r)
    if a.max() <= c:
        return np.ones_like(r)
    return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))


def _robust_w(r: np.ndarray, c: float | None, trim: float | None) -> np.ndarray:
    """Huber weights, and weight 0 beyond ``trim`` sigmas (hard trimming of mixed pixels and outliers)."""
    w = huber_weights(r, c)
    return w if trim is None else np.where(np.abs(r) <= trim, w, 0.0)


def _huber_cost(r: np.ndarray, c: float | None) -> float:
    if c is None:
        return float(r @ r)
    a = np.abs(r)
    if a.max() <= c:
        return float(r @ r)
    return float(np.sum(np.where(a <= c, a * a, 2 * c * a - c * c)))


def _lm(fun, retract, state, pts, sig, *, max_iter: int, tol: float, huber: float | None,
        stop_above: float | None = None, hopeless_after: int = 3):
    """Levenberg-Marquardt with IRLS Huber weights on a manifold; returns (state, n_iter).

    Stops when the relative cost decrease falls below ``tol``, or below 1e-2 while the cost is still above
    ``stop_above`` (a model that is clearly losing to another one and drifting slowly), or when the cost
    is still above ``10 * stop_above`` after ``hopeless_after`` iterations (0: do not even start).
    """
    r, J = fun(state, pts, sig)
    cost = _huber_cost(r, huber)
    lam, nu = 1e-3, 2.0
    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        if stop_above is not None and it > hopeless_after and cost > 10.0 * stop_above:
            it -= 1
            break  # hopeless: still 10x worse than a competitor
        w = huber_weights(r, huber)
        Jw = J * w[:, None]
        H = J.T @ Jw
        g = Jw.T @ r
        dH = np.diag(H).copy() + 1e-12 * (np.trace(H) + 1e-300)
        done = True
        for _ in range(12):
            try:
                step = -np.linalg.solve(H + lam * np.diag(dH), g)
            except np.linalg.LinAlgError:
                lam, nu = lam * nu, nu * 2
                continue
            st_new = retract(state, step)
            r_new, J_new = fun(st_new, pts, sig)
            c_new = _huber_cost(r_new, huber)
            if np.isfinite(c_new) and c_new <= cost:
                # Nielsen's damping update from the gain ratio (actual / predicted decrease): avoids the
                # accept-overshoot oscillation of a fixed x0.1 / x10 rule in curved valleys (cone vs tilt)
                pred = -(2.0 * (g @ step) + step @ H @ step)
                ratio = (cost - c_new) / pred if pred > 0 else 1.0
                lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), 1e-12)
                nu = 2.0
                rel = (cost - c_new) / max(cost, 1e-300)
                state, r, J, cost = st_new, r_new, J_new, c_new
                done = rel < tol or (stop_above is not None and rel < 1e-2 and cost > stop_above)
                break
            lam, nu = lam * nu, nu * 2
        if done:
            break
    return state, it


def _with_incidence(fun, normal_fn, origin, cos_min: float):
    """Wrap a residual function so each point's sigma becomes ``sigma * max(|n . u|, cos_min)``.

    ``u`` is the unit ray from ``origin`` to the point and ``n`` the model normal there: range noise along
    the ray has a component ``sigma |cos(incidence)|`` along the normal, the distance that is fitted.
    """
    if origin is None:
        return fun

    def wrapped(state, pts, sig):
        u = pts - origin
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        c = np.abs(np.einsum("ij,ij->i", normal_fn(state, pts), u))
        return fun(state, pts, sig * np.maximum(c, cos_min))

    return wrapped


def _check_origin(origin):
    if origin is None:
        return None
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (3,):
        raise ValueError(f"expected origin of shape (3,), got {o.shape}")
    return o


def _solve(fun, retract, starts, pts, sig, *, max_iter, tol, huber, max_points, polish_iter: int = 2,
           stop_above: float | None = None, coarse_points: int = _INIT_POINTS, fine_iter: int = 3,
           hopeless_after: int = 3, n_starts: int = 1):
    """Fit from the start(s) of lowest initial cost, coarse to fine, and polish on all points.

    The ``n_starts`` starts of lowest initial cost are iterated (up to ``max_iter``) on a regular-stride
    subset of ``coarse_points`` points, the best is refined by up to ``fine_iter`` iterations on the
    ``max_points`` subsample, then by ``polish_iter`` on all points (when subsampled). Returns (state, r,
    J, w, n_iter) with residuals, Jacobian and Huber weights on all points, or None when no start has a
    finite cost.
    """
    sub = _subsample(len(pts), max_points)
    ps, ss = (pts, sig) if sub is None else (pts[sub], sig[sub])
    crs = _subsample(len(ps), coarse_points)
    pc, sc = (ps, ss) if crs is None else (ps[crs], ss[crs])
    scored = []
    for k, st0 in enumerate(starts):
        c = _huber_cost(fun(st0, pc, sc)[0], huber)
        if np.isfinite(c):
            scored.append((c, k, st0))
    if not scored:
        return None
    scored.sort(key=lambda x: (x[0], x[1]))
    cap = None if stop_above is None else stop_above * len(pc) / len(ps)
    best = None
    for _, _, st0 in scored[:n_starts]:
        st1, it1 = _lm(fun, retract, st0, pc, sc, max_iter=max_iter, tol=tol, huber=huber, stop_above=cap,
                       hopeless_after=hopeless_after)
        c1 = _huber_cost(fun(st1, pc, sc)[0], huber)
        if best is None or c1 < best[0]:
            best = (c1, st1, it1)
    _, state, it = best
    if crs is not None and it > 0:
        state, it2 = _lm(fun, retract, state, ps, ss, max_iter=fine_iter, tol=tol, huber=huber)
        it += it2
    if sub is not None and it > 0:
        state, it2 = _lm(fun, retract, state, pts, sig, max_iter=polish_iter, tol=tol, huber=huber)
        it += it2
    r, J = fun(state, pts, sig)
    return state, r, J, huber_weights(r, huber), it


TRIM_SIGMA = 3.5
"""The default level (sigmas) of a fit's ``chi2_trim``: residuals beyond it count as ``TRIM_SIGMA²`` (a robust
goodness of fit). The fits' API default, for callers that do not say: the ``select`` classifier passes its own
level, ``SelectParams.trim_sigma`` (where it was chosen: ``docs/tuning.md``)."""


def trimmed_chi2(r: np.ndarray, c: float = TRIM_SIGMA) -> float:
    """``sum(min(r², c²))`` of sigma-normalised residuals: mixed pixels, outliers and bits of a neighbouring
    surface at a patch's border add at most ``c²`` each instead of dominating the sum."""
    return float(np.sum(np.minimum(r * r, c * c)))


def _stats(r: np.ndarray, d: np.ndarray, k: int, n_iter: int, trim_sigma: float) -> dict:
    """Residual statistics from sigma-normalised residuals r (N,) and distances d (N,) in metres (``chi2_trim``
    at ``trim_sigma``)."""
    n = len(r)
    chi2 = float(np.sum(r * r))  # summed like trimmed_chi2 (rounding is monotone: chi2_trim <= chi2 exactly)
    return {"rms_m": float(np.sqrt(np.mean(d * d))), "rms_sigma": float(np.sqrt(chi2 / n)), "chi2": chi2,
            "n_points": n, "n_iter": n_iter, "chi2_trim": trimmed_chi2(r, trim_sigma)}


def _local_cov(r: np.ndarray, J: np.ndarray, w: np.ndarray, k: int) -> np.ndarray:
    """Sandwich covariance ``H^-1 (J' W diag(r²) W J) H^-1 n / (n - k)``, ``H = J' W J``.

    The normalised residuals' variance is not 1 point by point (range noise is along the ray, the fitted
    distance along the normal: grazing points have smaller residuals); the plain ``s² H^-1`` then
    over-predicted the radius and half-angle sigmas by 1.3-1.5x in Monte Carlo checks, the sandwich matched.
    """
    n = len(r)
    Jw = J * w[:, None]
    Hinv = np.linalg.pinv(J.T @ Jw)
    Jr = Jw * r[:, None]
    return (n / max(n - k, 1)) * Hinv @ (Jr.T @ Jr) @ Hinv


def _nan_fit(cls, n: int, reason: str, **shape):
    base = {"rms_m": np.nan, "rms_sigma": np.nan, "chi2": np.nan, "n_points": n, "n_iter": 0, "ok": False,
            "reason": reason}
    return cls(**base, **shape)


def _collinear(pts: np.ndarray) -> bool:
    d = pts - pts.mean(axis=0)
    ev = np.linalg.eigvalsh(d.T @ d)
    return bool(ev[1] <= 1e-12 * max(ev[2], 1e-300))


def _extent(pts: np.ndarray) -> float:
    return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
