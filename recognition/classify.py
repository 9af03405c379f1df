"""Patch classification into PLAN, CYL, SPH, CONE, OTH behind one interface, two classifiers.

``method="paper"`` is section 3 of Fillatreau & Fisher, made precise and configurable (:class:`PaperParams`):
a general quadric is fitted with its covariance (:func:`recognition.quadric.fit_quadric`), brought to its
canonical form with propagated Gaussians of ``(l1, l2, l3, C_cano)``
(:func:`recognition.quadric.canonicalise`), and the plausibility of each class is the product of the
probabilities of its conditions:

- cylinder: ``C_cano < 0``, ``l1 = l2 > 0``, ``l3 = 0`` - here ``l3`` is the eigenvalue closest to 0 and the
  centre solve truncates it (pseudo-inverse), ``l1, l2`` are the other two;
- sphere: ``C_cano < 0``, ``l1 = l2 = l3 > 0`` (tested as ``l1 - l2 = 0`` and ``l2 - l3 = 0``), full-rank
  centre;
- cone: ``C_cano = 0``, ``l1, l2 > 0``, ``l3 < 0`` (``l3`` the smallest), full-rank centre (the apex).

after the sign normalisation of the canonical form (at least two positive eigenvalues). ``P(x > 0)`` is the
Gaussian CDF ``Phi(x / sigma)``; the plausibility of ``x = 0`` is a heuristic of ``P(x > 0)`` and ``P(x <
0)``: ``2 min(P(x > 0), P(x < 0))`` (``zero_rule="literal"``, default) or ``exp(-z²/8)`` (``"soft"``). A
label among CYL/SPH/CONE is given when its plausibility is the highest and beats the others by more than
``margin`` (0.2), and is then verified a posteriori by the dedicated fit, whose RMS distance must be within
``verify_factor * RMS(sigma)``; otherwise OTH. PLAN comes from segmentation (``planar_hint``) or, as
documented here, when a plane fit explains the points within the same noise bound (the quadric is then not
identifiable: any quadric containing the plane fits). Class probabilities (for the Brier score, DESIGN
10.8): the three plausibilities, ``OTH = max(0, 1 - their sum)``, renormalised; ``PLAN = 1`` with the hint.

``method="select"`` (the core's default, :class:`SelectParams`) fits a plane, a cylinder, a sphere and a cone
(:mod:`recognition.primitives`) and, as the model of OTH, a general quadric, and chooses by an information
criterion on the sigma-normalised residuals (BIC ``chi² + k ln N`` or AIC ``chi² + 2k``). Posterior model
probabilities are ``exp(-delta/2)`` normalised. Each primitive must also pass a goodness-of-fit test (its
reduced chi² below ``gof_factor + gof_z sqrt(2 / dof)``, a tolerance for model error), as a smooth
plausibility ``g``; a model's probability is ``posterior * g`` and OTH gets the posterior of the quadric
plus all the mass that failed the test, so elbows (tori) and unknown shapes stay OTH. The cone is nested with
the cylinder (half-angle 0) and started from the cylinder fit, so the criterion chooses the cone exactly when
the data pay for its extra parameter.

Both methods fit on a regular-stride subsample of at most ``max_points`` points (the information criterion
then works with that N: the decision is that of a patch of ``max_points`` points), and the chosen primitive
is polished by a Gauss-Newton step on all points so its parameters, covariance and invariants use the
whole patch. Cost (``python -m recognition.bench_classify``, shared 2-core machine, CPU time): ``select``
about 10-14 ms per patch, dominated by per-iteration numpy overhead rather than by the number of points
(1000 or 800 points per fit were not faster), so a 40-patch VGA frame takes about 0.4-0.5 s; ``paper``
about 4 ms per patch, 0.15-0.2 s per frame. Sub-sampling below 1500 points cost accuracy under
Kinect-like noise (0.92 -> 0.89).

The invariants' visible length has a heuristic sigma: the point spacing ``sqrt(L W / N)`` (W the patch
width across the axis), since the length is set by the patch ends, not by the fit.

Degenerate patches (fewer than 10 points, NaNs, collinear or exactly coplanar points) give OTH with a
``reason`` (PLAN for coplanar points with ``planar_hint``), never an exception; wrong shapes raise
``ValueError``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr

from . import primitives as prim
from .quadric import canonicalise, evaluate, fit_quadric

__all__ = [
    "CLASSES", "PaperParams", "SelectParams", "PatchClassification", "classify_patch", "paper_plausibilities",
]

CLASSES = ("PLAN", "CYL", "SPH", "CONE", "OTH")

Primitive = prim.PlaneFit | prim.CylinderFit | prim.SphereFit | prim.ConeFit


@dataclass(frozen=True)
class PaperParams:
    """Parameters of the paper's plausibility classifier.

    Attributes
    ----------
    zero_rule : {"literal", "soft"}
        Plausibility of ``x = 0``: ``2 min(P(x>0), P(x<0))`` or ``exp(-z²/8)`` with ``z = x / sigma``.
    sigma_mode : {"bauer_fike", "first_order"}
        Eigenvalue sigmas (see :func:`recognition.quadric.canonicalise`).
    margin : float
        The winning plausibility must beat the others by more than this (paper: 0.2).
    verify_factor : float
        A posteriori check: the dedicated fit's RMS distance must be <= ``verify_factor * RMS(sigma)``.
    max_points : int
        Subsample size for the fits.
    huber : float or None
        Huber threshold (sigma units) of the dedicated fits.
    """

    zero_rule: str = "literal"
    sigma_mode: str = "bauer_fike"
    margin: float = 0.2
    verify_factor: float = 1.5
    max_points: int = 2000
    huber: float | None = 3.0


@dataclass(frozen=True)
class SelectParams:
    """Parameters of the model-selection classifier.

    Attributes
    ----------
    criterion : {"bic", "aic"}
        ``chi² + k ln N`` or ``chi² + 2 k``.
    gof_factor : float
        Tolerance for model error: the best model's reduced chi² (orthogonal distances over the given
        sigma) may reach this before the patch is OTH. With sigma along the ray the expected value for a
        correct model is ~E[cos² incidence] < 1.
    gof_z : float
        Statistical allowance ``gof_z * sqrt(2 / dof)`` added to ``gof_factor``.
    gof_width : float
        Relative width of the smooth goodness-of-fit plausibility around the threshold.
    quadric_as_other : bool
        Let a general quadric (k = 9) compete as the model of OTH.
    other_penalty : float
        Added to the quadric's criterion (a prior against OTH): at Kinect-like noise the range-dependent
        bias of one-sided fits makes true primitives slightly non-primitive, and the 9-parameter quadric
        then wins some of them.
    planar_hint_odds : float
        Prior odds multiplying the plane's posterior weight when the segmenter says the patch is planar.
    temperature : float
        Posterior weights ``exp(-delta / (2 T))``: T = 1 is the plain criterion; T > 1 tempers the
        over-confidence that unmodelled errors (range-dependent bias, non-Gaussian noise) give large N.
        Fit it on a calibration suite, never on the evaluation suite (DESIGN 10.8).
    max_points : int
        Subsample size for the fits and the criterion.
    max_iter : int
        Iteration limit of each candidate fit. Correct models converge in 3-6 iterations from their starts
        at low noise but may crawl for 15-20 at Kinect-like noise (a cylinder cut off at 10 lost to the
        cone nested in it); models that are clearly losing stop early (``stop_above``).
    huber : float or None
        Huber threshold (sigma units) of the fits.
    """

    criterion: str = "bic"
    gof_factor: float = 1.5
    gof_z: float = 3.0
    gof_width: float = 0.1
    quadric_as_other: bool = True
    other_penalty: float = 0.0
    planar_hint_odds: float = 100.0
    temperature: float = 1.0
    max_points: int = 1500
    max_iter: int = 25
    huber: float | None = 3.0


@dataclass(frozen=True)
class PatchClassification:
    """Result of :func:`classify_patch`.

    Attributes
    ----------
    label : str
        One of :data:`CLASSES`.
    probabilities : dict[str, float]
        Over all five classes, summing to 1.
    plausibilities : dict[str, float]
        ``P(cyl)``, ``P(sphere)``, ``P(cone)`` (keys ``"CYL"``, ``"SPH"``, ``"CONE"``): the paper's
        plausibilities, or the posterior probabilities for ``select``.
    primitive : PlaneFit | CylinderFit | SphereFit | ConeFit | None
        The dedicated fit of the label (None for OTH).
    invariants : dict[str, tuple[float, float]]
        ``name -> (value, sigma)``: ``radius_m``, ``length_m`` (cylinder); ``radius_m`` (sphere);
        ``half_angle_rad``, ``length_m`` (cone).
    reason : str
        Why OTH or why degenerate; "" otherwise.
    details : dict
        Diagnostics (criterion values, canonical form, ...), free-form.
    """

    label: str
    probabilities: dict[str, float]
    plausibilities: dict[str, float]
    primitive: Primitive | None
    invariants: dict[str, tuple[float, float]]
    reason: str = ""
    details: dict = field(default_factory=dict, compare=False)


# ---------------------------------------------------------------------------------------------------------
# helpers


def _check_inputs(points, sigma, normals):
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


def _probs(**kw) -> dict[str, float]:
    p = {c: float(kw.get(c, 0.0)) for c in CLASSES}
    s = sum(p.values())
    if not s > 0:
        p = {c: 0.0 for c in CLASSES}
        p["OTH"] = 1.0
        return p
    return {c: v / s for c, v in p.items()}


def _result(label, probs, plaus, primitive=None, invariants=None, reason="", details=None):
    return PatchClassification(
        label=label, probabilities=probs, plausibilities=plaus or {"CYL": 0.0, "SPH": 0.0, "CONE": 0.0},
        primitive=primitive, invariants=invariants or {}, reason=reason, details=details or {},
    )


def _degenerate_check(pts, sig, planar_hint):
    """Return a PatchClassification for degenerate input, or None."""
    n = len(pts)
    if n < 10:
        return _result("OTH", _probs(OTH=1), None, reason=f"too few points ({n} < 10)")
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(sig))):
        return _result("OTH", _probs(OTH=1), None, reason="NaN or infinite values in points or sigma")
    if np.any(sig <= 0):
        return _result("OTH", _probs(OTH=1), None, reason="sigma must be positive")
    d = pts - pts.mean(axis=0)
    ev = np.linalg.eigvalsh(d.T @ d)
    top = max(ev[2], 1e-300)
    if ev[1] <= 1e-12 * top:
        return _result("OTH", _probs(OTH=1), None, reason="points are collinear (or coincide)")
    if ev[0] <= 1e-12 * top:
        if planar_hint:
            pl = prim.fit_plane(pts, sig)
            return _result("PLAN", _probs(PLAN=1), None, pl, reason="")
        return _result("OTH", _probs(OTH=1), None,
                       reason="points are exactly coplanar: quadric not unique (no planar hint)")
    return None


def _subsample(n: int, max_points: int) -> np.ndarray:
    if n <= max_points:
        return np.arange(n)
    return np.linspace(0, n - 1, max_points).round().astype(np.intp)


def _rms_sigma(sig: np.ndarray) -> float:
    return float(np.sqrt(np.mean(sig * sig)))


def _length_sigma(pts: np.ndarray, axis: np.ndarray, length: float) -> float:
    """Heuristic sigma of a visible length: the point spacing ``sqrt(L W / N)`` (W: width across the axis)."""
    y = pts - pts.mean(axis=0)
    q = y - np.outer(y @ axis, axis)
    width = float(np.sqrt(np.max(np.einsum("ij,ij->i", q, q)))) * 2.0
    return float(np.sqrt(max(length * width, 0.0) / len(pts)))


def _invariants(fit: Primitive | None, pts: np.ndarray) -> dict[str, tuple[float, float]]:
    if isinstance(fit, prim.CylinderFit) and fit.ok:
        return {"radius_m": (fit.radius, fit.radius_sigma),
                "length_m": (fit.length, _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, prim.SphereFit) and fit.ok:
        return {"radius_m": (fit.radius, fit.radius_sigma)}
    if isinstance(fit, prim.ConeFit) and fit.ok:
        return {"half_angle_rad": (fit.half_angle, fit.half_angle_sigma),
                "length_m": (fit.length, _length_sigma(pts, fit.axis, fit.length))}
    return {}


def _polish(fit: Primitive, pts, sig, nrm, huber) -> Primitive:
    """Refit the chosen primitive on all points from its subsample solution (a few iterations)."""
    kw = {"max_points": None, "huber": huber, "max_iter": 1}
    if isinstance(fit, prim.PlaneFit):
        return prim.fit_plane(pts, sig, nrm)
    if isinstance(fit, prim.SphereFit):
        return prim.fit_sphere(pts, sig, init=(fit.centre, fit.radius), **kw)
    if isinstance(fit, prim.CylinderFit):
        return prim.fit_cylinder(pts, sig, init=(fit.point, fit.axis, fit.radius), **kw)
    if isinstance(fit, prim.ConeFit):
        init = (fit.point, fit.axis, fit.radius_at_point, np.tan(fit.half_angle))
        return prim.fit_cone(pts, sig, init=init, axis_search=False, **kw)
    return fit


# ---------------------------------------------------------------------------------------------------------
# paper


def _p_pos(x: float, s: float) -> float:
    if not s > 0:
        return 1.0 if x > 0 else (0.5 if x == 0 else 0.0)
    return float(ndtr(x / s))


def _p_zero(x: float, s: float, rule: str) -> float:
    if rule == "soft":
        if not s > 0:
            return 1.0 if x == 0 else 0.0
        return float(np.exp(-((x / s) ** 2) / 8.0))
    pp = _p_pos(x, s)
    return 2.0 * min(pp, 1.0 - pp)


def paper_plausibilities(fit, params: PaperParams) -> tuple[dict[str, float], dict]:
    """The paper's plausibilities P(cyl), P(sphere), P(cone) of a fitted quadric.

    Parameters
    ----------
    fit : QuadricFit
    params : PaperParams

    Returns
    -------
    plausibilities : dict with keys "CYL", "SPH", "CONE"
    details : dict
        The canonical forms used (rank 2 for the cylinder test, rank 3 for sphere and cone).
    """
    rule = params.zero_rule
    c2 = canonicalise(fit, rank=2, sigma_mode=params.sigma_mode)
    c3 = canonicalise(fit, rank=3, sigma_mode=params.sigma_mode)
    lam, s2 = c2.eigenvalues, c2.sigmas
    k0 = c2.truncated
    a, b = [i for i in range(3) if i != k0]
    d_ab, sd_ab = c2.difference(a, b)
    p_cyl = (_p_pos(-c2.c_cano, s2[3]) * _p_zero(d_ab, sd_ab, rule) * _p_pos(lam[a], s2[a])
             * _p_pos(lam[b], s2[b]) * _p_zero(lam[k0], s2[k0], rule))
    lam3, s3 = c3.eigenvalues, c3.sigmas
    d12, sd12 = c3.difference(0, 1)
    d23, sd23 = c3.difference(1, 2)
    p_sph = (_p_pos(-c3.c_cano, s3[3]) * _p_zero(d12, sd12, rule) * _p_zero(d23, sd23, rule)
             * _p_pos(lam3[0], s3[0]) * _p_pos(lam3[1], s3[1]) * _p_pos(lam3[2], s3[2]))
    p_cone = (_p_zero(c3.c_cano, s3[3], rule) * _p_pos(lam3[0], s3[0]) * _p_pos(lam3[1], s3[1])
              * _p_pos(-lam3[2], s3[2]))
    return {"CYL": float(p_cyl), "SPH": float(p_sph), "CONE": float(p_cone)}, {"canonical_rank2": c2,
                                                                                "canonical_rank3": c3}


def _classify_paper(pts, sig, nrm, params: PaperParams, planar_hint: bool) -> PatchClassification:
    idx = _subsample(len(pts), params.max_points)
    ps, ss = pts[idx], sig[idx]
    bound = params.verify_factor * _rms_sigma(sig)
    if planar_hint:
        pl = prim.fit_plane(pts, sig, nrm)
        return _result("PLAN", _probs(PLAN=1), None, pl if pl.ok else None, {},
                       "" if pl.ok else pl.reason)
    pl = prim.fit_plane(ps, ss)
    if pl.ok and pl.rms_m <= bound:
        pl = prim.fit_plane(pts, sig, nrm)
        return _result("PLAN", _probs(PLAN=1), None, pl, {}, "",
                       {"note": "plane fit within noise: quadric not identifiable"})
    q = fit_quadric(ps, ss)
    if not q.ok:
        return _result("OTH", _probs(OTH=1), None, reason=f"quadric fit failed: {q.reason}")
    plaus, details = paper_plausibilities(q, params)
    probs = _probs(CYL=plaus["CYL"], SPH=plaus["SPH"], CONE=plaus["CONE"],
                   OTH=max(0.0, 1.0 - sum(plaus.values())))
    details["quadric"] = q
    order = sorted(plaus, key=plaus.get, reverse=True)
    best, second = order[0], order[1]
    if not plaus[best] - plaus[second] > params.margin:
        return _result("OTH", probs, plaus, reason=(
            f"no clear class: best {best} {plaus[best]:.3f}, second {second} {plaus[second]:.3f}, "
            f"margin {params.margin}"), details=details)
    kw = {"max_points": params.max_points, "huber": params.huber}
    if best == "SPH":
        fit = prim.fit_sphere(pts, sig, nrm, **kw)
    else:
        axes = prim.axis_candidates(ps, ss, None if nrm is None else nrm[idx], quadric=q)
        if best == "CYL":
            fit = prim.fit_cylinder(pts, sig, nrm, axes=axes, **kw)
        else:
            fit = prim.fit_cone(pts, sig, nrm, axes=axes, quadric=q, **kw)
    if not fit.ok:
        return _result("OTH", probs, plaus, reason=f"dedicated {best} fit failed: {fit.reason}",
                       details=details)
    if not fit.rms_m <= bound:
        return _result("OTH", probs, plaus, reason=(
            f"a posteriori check failed: {best} fit RMS {fit.rms_m * 1e3:.3g} mm > bound "
            f"{bound * 1e3:.3g} mm"),
            details=details)
    return _result(best, probs, plaus, fit, _invariants(fit, pts), "", details)


# ---------------------------------------------------------------------------------------------------------
# select


def _criterion(chi2: float, k: int, n: int, kind: str) -> float:
    return chi2 + (k * np.log(n) if kind == "bic" else 2.0 * k)


def _single_sheet(q, pts: np.ndarray, plane: prim.PlaneFit, min_fraction: float = 0.9) -> bool:
    """True when the quadric's gradient keeps one orientation over the patch.

    A noisy plane is fitted better by two parallel planes ``(n.x - d - e)(n.x - d + e) = 0`` (a degenerate
    quadric with the points on both sheets), which is not a surface: such a quadric may not compete as OTH.
    The test: the sign of ``grad f . n_plane`` must be the same for ``min_fraction`` of the points.
    """
    if not plane.ok:
        return True
    _, grad = evaluate(q.params, pts)
    s = np.sign(grad @ plane.normal)
    return bool(max(np.mean(s > 0), np.mean(s < 0)) >= min_fraction)


def _classify_select(pts, sig, nrm, params: SelectParams, planar_hint: bool) -> PatchClassification:
    n_all = len(pts)
    idx = _subsample(n_all, params.max_points)
    ps, ss = pts[idx], sig[idx]
    ns = None if nrm is None else nrm[idx]
    n = len(ps)
    kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter}
    fits: dict[str, Primitive] = {}
    fits["PLAN"] = prim.fit_plane(ps, ss, ns)
    q = fit_quadric(ps, ss, max_iter=3, with_cov=False)
    axes = prim.axis_candidates(ps, ss, ns, quadric=q)

    def cap() -> float | None:
        """Early stop for fits that are clearly losing: 1.5x the best chi² so far."""
        c = [f.chi2 for f in fits.values() if f.ok and np.isfinite(f.chi2)]
        return 1.5 * min(c) if c else None

    fits["CYL"] = prim.fit_cylinder(ps, ss, ns, axes=axes, stop_above=cap(), **kw)
    fits["CONE"] = prim.fit_cone(ps, ss, ns, init=fits["CYL"] if fits["CYL"].ok else None, axes=axes,
                                 quadric=q, stop_above=cap(), **kw)
    fits["SPH"] = prim.fit_sphere(ps, ss, stop_above=cap(), **kw)
    crit: dict[str, float] = {}
    gof: dict[str, float] = {}
    for c, f in fits.items():
        if f.ok and np.isfinite(f.chi2):
            crit[c] = _criterion(f.chi2, f.n_params, n, params.criterion)
            dof = max(n - f.n_params, 1)
            thr = params.gof_factor + params.gof_z * np.sqrt(2.0 / dof)
            red = f.chi2 / dof
            gof[c] = float(1.0 / (1.0 + np.exp(np.clip((red - thr) / (params.gof_width * thr), -50, 50))))
    if params.quadric_as_other:
        if q.ok and _single_sheet(q, ps, fits["PLAN"]):
            crit["OTH"] = _criterion(q.chi2, 9, n, params.criterion) + params.other_penalty
    if planar_hint and "PLAN" in crit:
        crit["PLAN"] -= 2.0 * np.log(params.planar_hint_odds)
    if not crit:
        return _result("OTH", _probs(OTH=1), None, reason="no model could be fitted",
                       details={"fits": fits})
    cmin = min(crit.values())
    w = {c: np.exp(-0.5 * (v - cmin) / params.temperature) for c, v in crit.items()}
    tot = sum(w.values())
    post = {c: v / tot for c, v in w.items()}
    pr = {c: post.get(c, 0.0) * gof.get(c, 0.0) for c in ("PLAN", "CYL", "SPH", "CONE")}
    pr["OTH"] = post.get("OTH", 0.0) + sum(post.get(c, 0.0) * (1.0 - gof.get(c, 0.0))
                                           for c in ("PLAN", "CYL", "SPH", "CONE"))
    probs = _probs(**pr)
    plaus = {c: float(probs[c]) for c in ("CYL", "SPH", "CONE")}
    label = max(CLASSES, key=lambda c: probs[c])
    details = {"criterion": crit, "gof": gof, "posterior": post, "fits": fits, "n_used": n}
    if label == "OTH":
        best = min((c for c in crit if c != "OTH"), key=crit.get, default=None)
        if best is not None and gof.get(best, 0.0) < 0.5:
            f = fits[best]
            why = (f"best primitive {best} does not fit within noise (reduced chi² "
                   f"{f.chi2 / max(n - f.n_params, 1):.2f}, RMS {f.rms_m * 1e3:.3g} mm)")
        else:
            why = "a general quadric explains the points better than any primitive"
        return _result("OTH", probs, plaus, None, {}, why, details)
    fit = fits[label]
    if n_all > n:
        polished = _polish(fit, pts, sig, nrm, params.huber)
        if polished.ok:
            fit = polished
    return _result(label, probs, plaus, fit, _invariants(fit, pts), "", details)


# ---------------------------------------------------------------------------------------------------------
# public


def classify_patch(
    points: np.ndarray,
    sigma: np.ndarray | float,
    normals: np.ndarray | None = None,
    *,
    method: str = "select",
    params: PaperParams | SelectParams | None = None,
    planar_hint: bool = False,
) -> PatchClassification:
    """Classify a surface patch as PLAN, CYL, SPH, CONE or OTH.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres
        Patch points in any frame.
    sigma : ndarray of shape (N,) or float, metres
        Per-point range noise sigma.
    normals : ndarray of shape (N, 3), optional
        Estimated unit normals (extra axis candidates for cylinders and cones).
    method : {"select", "paper"}
        Model-selection classifier (default) or the paper's plausibility rule.
    params : PaperParams or SelectParams, optional
        Defaults of the chosen method when None.
    planar_hint : bool
        The segmenter found the patch planar.

    Returns
    -------
    PatchClassification

    Raises
    ------
    ValueError
        On wrong shapes, an unknown method or params of the wrong type.
    """
    pts, sig, nrm = _check_inputs(points, sigma, normals)
    if method not in ("select", "paper"):
        raise ValueError(f"method must be 'select' or 'paper', got {method!r}")
    if params is None:
        params = SelectParams() if method == "select" else PaperParams()
    expected = SelectParams if method == "select" else PaperParams
    if not isinstance(params, expected):
        raise ValueError(f"method {method!r} expects {expected.__name__}, got {type(params).__name__}")
    if nrm is not None and not np.all(np.isfinite(nrm)):
        nrm = None
    deg = _degenerate_check(pts, sig, planar_hint)
    if deg is not None:
        return deg
    if method == "paper":
        return _classify_paper(pts, sig, nrm, params, planar_hint)
    return _classify_select(pts, sig, nrm, params, planar_hint)
