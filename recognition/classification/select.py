"""The model-selection classifier, ``method="select"`` of :func:`recognition.classification.classify_patch`
(the core's default; the paper's section 3 classifies by a quadric's canonical form, this chooses between
dedicated fits, DESIGN 6.2).

``method="select"`` (the core's default, :class:`SelectParams`) fits a plane, a cylinder, a sphere and a cone
(:mod:`recognition.fitting`) and, as the model of OTH, a general quadric, and chooses by an information
criterion on the sigma-normalised residuals (BIC ``chi² + k ln N`` or AIC ``chi² + 2k``). Posterior model
probabilities are ``exp(-delta/2)`` normalised. Each primitive must also pass a goodness-of-fit test (its
reduced chi² below ``gof_factor + gof_z sqrt(2 / dof)``, a tolerance for model error), as a smooth
plausibility ``g``; a model's probability is ``posterior * g`` and OTH gets the posterior of the quadric
plus all the mass that failed the test, so elbows (tori) and unknown shapes stay OTH. The cone is nested with
the cylinder (half-angle 0) and started from the cylinder fit, so the criterion chooses the cone exactly when
the data pay for its extra parameter. A ring torus (:func:`recognition.fitting.fit_torus`, k = 7) competes as
a second model of OTH where bending the cylinder's axis passes a score test: a pipe elbow it explains is OTH
with its bend and pipe radii as invariants (``major_radius_m``, ``minor_radius_m``). A patch that would be OTH
but whose majority (``min_inliers``) one primitive fits within noise after least-trimmed-squares steps takes
that primitive's label (a neighbour merged in by the segmenter), unless the torus explains it (an elbow).

Robustness and speed of ``select`` (issue 14, measured on real simulated scans of the default suite's
groups, with the real segmenter and with the truth segmentation): segmented patches carry mixed pixels,
outliers and bits of a neighbouring surface, so (1) the criterion and the goodness of fit use a trimmed
chi² (residuals beyond ``trim_sigma`` = 3.5 count as 3.5², :func:`recognition.fitting.trimmed_chi2`; the
quadric's Sampson distances likewise), (2) gross outliers off the patch's bulk are dropped first
(``outlier_k``). For speed, (3) cylinders, cones and spheres are not fitted when a linear quadratic height
field over the plane cannot pay for their extra parameters (``plane_gate``: large planes were most of a
frame's time), and (4) the cone is fitted only when a score test at the cylinder's solution says it might
win (``cone_score_skip``). With the sensor's sub-ray directions (``rays``), (5) a chosen cylinder or sphere
is refitted in range space with the beam footprint modelled (:func:`recognition.fitting.refit_along_rays`):
the geometric fit's radius was 2.1 % low (median) at factory-scanner resolution, the refit's is within
0.02 %. Cost on the ``default`` suite's VGA frames: median 0.14 s of CPU, p90 0.4 s, with the torus and the
trimmed rescue (``time.process_time``, single-threaded BLAS; a multi-threaded BLAS on a loaded 2-core machine
inflates process time 1.5-2x by spinning threads); ``paper`` about 0.1-0.2 s.
"""

from __future__ import annotations

import math

import numpy as np

from recognition import fitting
from recognition.fitting import evaluate, fit_quadric
from scenes.geometry import perpendicular_basis

from .criteria import _chi2_of, _criteria, _criterion, _price
from .params import SelectParams
from .rescue import _trimmed_rescue
from .result import CLASSES, PatchClassification, Primitive, _check_rays, _invariants, _probs, _result, _subsample


def _classify_select(pts, sig, nrm, params: SelectParams, planar_hint: bool, rays=None,
                     correlation_area: float = 1.0) -> PatchClassification:
    n_in = len(pts)
    n_dropped = 0
    keep = None
    if params.outlier_k is not None:
        out = _gross_outliers(pts, sig, params.outlier_k)
        n_dropped = int(out.sum())
        if 0 < n_dropped <= 0.2 * n_in and n_in - n_dropped >= 10:
            keep = ~out
            pts, sig = pts[keep], sig[keep]
            nrm = None if nrm is None else nrm[keep]
            if rays is not None and not callable(rays):
                rays = rays[:, keep]
        else:
            n_dropped = 0
            keep = None
    n_all = len(pts)
    idx = _subsample(n_all, params.max_points)
    # too many gross outliers to drop them all (a curved strip's rims among them): the points they leave
    # still give the trimmed rescue a start off the mixture's basin
    core = None if keep is not None or params.outlier_k is None or not out.any() else ~out[idx]
    ps, ss = pts[idx], sig[idx]
    ns = None if nrm is None else nrm[idx]
    n = len(ps)
    # points of the subsample per independent error: the image's correlation area thinned by the stride
    rho = max(1.0, float(correlation_area) * n / n_all)
    kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter, "trim_sigma": params.trim_sigma}
    fits: dict[str, Primitive] = {}
    fits["PLAN"] = fitting.fit_plane(ps, ss, ns, trim_sigma=params.trim_sigma)

    def cap() -> float | None:
        """Early stop for fits that are clearly losing: 1.5x the best chi² so far."""
        c = [f.chi2 for f in fits.values() if f.ok and np.isfinite(f.chi2)]
        return 1.5 * min(c) if c else None

    flat = False
    if params.plane_gate is not None and fits["PLAN"].ok:
        dec = _curvature_gain(fits["PLAN"], ps, ss, params.trim_sigma)
        price = 2.0 * _price(n, "bic", rho) + (2.0 * np.log(params.planar_hint_odds) if planar_hint else 0.0)
        flat = dec / rho < params.plane_gate * price and \
            _criteria({"PLAN": fits["PLAN"]}, n, params, rho)[1]["PLAN"] >= 0.5
    if flat:
        # no quadratic height field does better than the plane by the price of the curved models' two extra
        # parameters: cylinders, cones and spheres (locally such height fields) cannot win; not fitted
        crit, gof = _criteria(fits, n, params, rho)
        return _decide(fits, crit, gof, None, ps, ss, pts, sig, nrm, rays, params, planar_hint, n, n_all,
                       {"curved_fits_skipped": True, "curvature_gain": dec, "n_gross_outliers": n_dropped,
                        "correlation": rho, "correlation_area": float(correlation_area)},
                       n_in=n_in, keep=keep)
    q = fit_quadric(ps, ss, max_iter=3, with_cov=False)
    # the sphere first: a cheap fit (a linear start) whose chi² caps the costlier cylinder and cone fits
    fits["SPH"] = fitting.fit_sphere(ps, ss, stop_above=cap(), **kw)
    axes = fitting.axis_candidates(ps, ss, ns, quadric=q)
    fits["CYL"] = fitting.fit_cylinder(ps, ss, ns, axes=axes, stop_above=cap(), **kw)
    skip_cone = False
    if fits["CYL"].ok and params.cone_score_skip is not None:
        sc = _cone_score(fits["CYL"], ps, ss, params.huber)
        if sc is not None and sc[0] / rho < params.cone_score_skip * _price(n, params.criterion, rho):
            skip_cone = True
    if skip_cone:
        # the cone cannot pay for its parameter: its criterion is that of the cylinder plus the price of one
        # parameter minus the predicted decrease (so it keeps a small, honest posterior share)
        fits["CONE"] = fitting.ConeFit(
            apex=np.full(3, np.inf), axis=fits["CYL"].axis, half_angle=0.0, length=fits["CYL"].length,
            point=fits["CYL"].point, radius_at_point=fits["CYL"].radius, cov=np.full((8, 8), np.nan),
            half_angle_sigma=np.nan, axis_sigma_rad=np.nan, rms_m=fits["CYL"].rms_m,
            rms_sigma=fits["CYL"].rms_sigma, chi2=max(fits["CYL"].chi2 - sc[0], 0.0), n_points=n, n_iter=0,
            ok=True, reason="not fitted: score test against the cylinder",
            chi2_trim=max(_chi2_of(fits["CYL"]) - sc[0], 0.0))
    else:
        fits["CONE"] = fitting.fit_cone(ps, ss, ns, init=fits["CYL"] if fits["CYL"].ok else None, axes=axes,
                                     quadric=q, stop_above=cap(), **kw)
    cone, cyl0 = fits["CONE"], fits["CYL"]
    if cone.ok and not skip_cone and (not cyl0.ok or _criterion(_chi2_of(cone), cone.n_params, n, params.criterion, rho)
                                      < _criterion(_chi2_of(cyl0), cyl0.n_params, n, params.criterion, rho)):
        # the cone would win: the cylinder is the cone at half-angle 0, and started on the cone's axis it may
        # leave a wrong basin of its own starts (a near-cylinder that only the cone fitted)
        cyl = fitting.fit_cylinder(ps, ss, init=(cone.point, cone.axis, cone.radius_at_point), **kw)
        if cyl.ok and (not fits["CYL"].ok or _chi2_of(cyl) < _chi2_of(fits["CYL"])):
            fits["CYL"] = cyl
    crit, gof = _criteria(fits, n, params, rho)
    if params.torus and n_all >= params.min_torus_points and fits["CYL"].ok and min(crit, key=crit.get) != "PLAN":
        gain, bend = fitting.bend_test(fits["CYL"], ps, ss, params.huber)
        # fitted only when bending the cylinder's axis might pay for the torus's two extra parameters (a
        # score test, as for the cone) and bends it like an elbow (within 3x the largest elbow's bend)
        fit_torus = (gain / rho >= params.torus_score_skip * 2.0 * _price(n, params.criterion, rho) and
                     bend <= 3.0 * params.max_bend_ratio * fits["CYL"].radius)
    else:
        fit_torus = False
    if fit_torus:
        fits["TOR"] = fitting.fit_torus(ps, ss, ns, cylinder=fits["CYL"], stop_above=cap(), **kw)
        if fits["TOR"].ok and fits["TOR"].major_radius <= params.max_bend_ratio * fits["TOR"].minor_radius:
            crit, gof = _criteria(fits, n, params, rho)
        else:
            del fits["TOR"]
    extra = {"cone_skipped": skip_cone, "n_gross_outliers": n_dropped, "correlation": rho,
             "correlation_area": float(correlation_area)}
    return _decide(fits, crit, gof, q, ps, ss, pts, sig, nrm, rays, params, planar_hint, n, n_all, extra,
                   axes=axes, ns=ns, n_in=n_in, keep=keep, core=core)


def _decide(fits, crit, gof, q, ps, ss, pts, sig, nrm, rays, params: SelectParams, planar_hint: bool, n: int,
            n_all: int, extra: dict, axes=None, ns=None, n_in: int = 0, keep=None,
            core: np.ndarray | None = None) -> PatchClassification:
    kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter, "trim_sigma": params.trim_sigma}
    skip_cone = extra.get("cone_skipped", False)
    rho = extra.get("correlation", 1.0)
    if params.quadric_as_other:
        if q is not None and q.ok and _single_sheet(q, ps, fits["PLAN"], params.single_sheet_fraction):
            crit["OTH"] = _criterion(_quadric_chi2_trim(q, ps, ss, params.trim_sigma), 9, n, params.criterion, rho) + \
                params.other_penalty
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
    pr["OTH"] = post.get("OTH", 0.0) + post.get("TOR", 0.0) + sum(post.get(c, 0.0) * (1.0 - gof.get(c, 0.0))
                                                                  for c in ("PLAN", "CYL", "SPH", "CONE"))
    probs = _probs(**pr)
    label = max(CLASSES, key=lambda c: probs[c])
    details = {"criterion": crit, "gof": gof, "posterior": post, "fits": fits, "n_used": n, **extra}
    # the fits' covariances treat every point as an independent error; errors shared by groups of
    # ``correlation_area`` pixels make their parameters vary up to that many times more (variance)
    sigma_scale = params.invariant_sigma_scale * math.sqrt(
        max(1.0, min(extra.get("correlation_area", 1.0), len(pts))))
    elbow = _elbow(crit, gof)
    if label == "OTH" and params.min_inliers is not None and n_all >= params.min_torus_points and not elbow:
        rescue = _trimmed_rescue(fits, crit, gof, ps, ss, ns, axes, q, params, n, rho, core)
        if rescue is not None:
            label, fit, frac = rescue
            fits[label] = fit
            pr = {c: 0.0 for c in CLASSES}
            pr[label] = frac
            pr["OTH"] = 1.0 - frac
            probs = _probs(**pr)
            label = max(CLASSES, key=lambda c: probs[c])
            details["trimmed_inlier_fraction"] = frac
    path = decision_path(label, extra.get("curved_fits_skipped", False), "trimmed_inlier_fraction" in details, elbow)
    details["path"], details["floor"] = path, params.floor(path)
    probs = _floored(probs, details["floor"])
    plaus = {c: float(probs[c]) for c in ("CYL", "SPH", "CONE")}
    if label == "OTH":
        if elbow:
            t = fits["TOR"]
            why = (f"a torus (pipe elbow) explains the points: bend radius {t.major_radius * 1e3:.4g} mm, pipe "
                   f"radius {t.minor_radius * 1e3:.4g} mm")
            return _result("OTH", probs, plaus, t, _invariants(t, pts, sigma_scale), why, details)
        best = min((c for c in crit if c not in ("OTH", "TOR")), key=crit.get, default=None)
        if best is not None and gof.get(best, 0.0) < 0.5:
            f = fits[best]
            why = (f"best primitive {best} does not fit within noise (robust reduced chi² "
                   f"{_chi2_of(f) / max(n - f.n_params, 1):.2f}, RMS {f.rms_m * 1e3:.3g} mm)")
        else:
            why = "a general quadric explains the points better than any primitive"
        return _result("OTH", probs, plaus, None, {}, why, details)
    fit = fits[label]
    if label == "CONE" and skip_cone:  # only reachable with unusual params: fit it for real
        fit = fitting.fit_cone(ps, ss, ns, init=fits["CYL"], axes=axes, quadric=q, **kw)
        if not fit.ok:
            return _result("OTH", probs, plaus, None, {}, f"cone fit failed: {fit.reason}", details)
    if n_all > n:
        polished = _polish(fit, pts, sig, nrm, params.huber, params.trim_sigma)
        if polished.ok:
            fit = polished
    if rays is not None and params.range_refit and isinstance(fit, fitting.CylinderFit | fitting.SphereFit):
        if callable(rays):
            rays = _check_rays(rays(), n_in)
            if keep is not None:
                rays = rays[:, keep]
        refit = fitting.refit_along_rays(fit, pts, sig, rays, huber=params.huber, trim=params.refit_trim,
                                         max_points=params.refit_points, max_iter=params.refit_iter,
                                         final_points=params.refit_final_points, trim_sigma=params.trim_sigma)
        details["geometric_fit"] = fit
        fit = refit
    return _result(label, probs, plaus, fit, _invariants(fit, pts, sigma_scale), "", details)


# ------------------------------------------------------------------------------------------ helpers


def decision_path(label: str, plane_gate: bool, rescued: bool, elbow: bool) -> str:
    """How :func:`_decide` reached its label: one of :data:`recognition.classification.params.DECISION_PATHS`.

    ``"plane_gate"``: the curved models were not fitted (the plane gate) and the plane won; ``"rescue"``: a
    primitive fits the patch's majority (the trimmed rescue); ``"elbow"``: OTH, a torus explains the points;
    ``"unexplained"``: OTH, no primitive fits within noise or a general quadric fits better; ``"criterion"``:
    a primitive won the criterion outright.
    """
    if rescued:
        return "rescue"
    if label == "OTH":
        return "elbow" if elbow else "unexplained"
    return "plane_gate" if plane_gate else "criterion"


def _floored(probs: dict[str, float], floor: float) -> dict[str, float]:
    """``(1 - floor) p + floor / 5``: mixed with the uniform distribution (the label is kept)."""
    if floor <= 0:
        return probs
    return _probs(**{c: (1.0 - floor) * v + floor / len(CLASSES) for c, v in probs.items()})


def _polish(fit: Primitive, pts, sig, nrm, huber, trim_sigma: float) -> Primitive:
    """Refit the chosen primitive on all points from its subsample solution (a few iterations)."""
    kw = {"max_points": None, "huber": huber, "max_iter": 1, "trim_sigma": trim_sigma}
    if isinstance(fit, fitting.PlaneFit):
        return fitting.fit_plane(pts, sig, nrm, trim_sigma=trim_sigma)
    if isinstance(fit, fitting.SphereFit):
        return fitting.fit_sphere(pts, sig, init=(fit.centre, fit.radius), **kw)
    if isinstance(fit, fitting.CylinderFit):
        return fitting.fit_cylinder(pts, sig, init=(fit.point, fit.axis, fit.radius), **kw)
    if isinstance(fit, fitting.ConeFit):
        init = (fit.point, fit.axis, fit.radius_at_point, np.tan(fit.half_angle))
        return fitting.fit_cone(pts, sig, init=init, axis_search=False, **kw)
    return fit


def _single_sheet(q, pts: np.ndarray, plane: fitting.PlaneFit, min_fraction: float) -> bool:
    """True when the quadric's gradient keeps one orientation over the patch.

    A noisy plane is fitted better by two parallel planes ``(n.x - d - e)(n.x - d + e) = 0`` (a degenerate
    quadric with the points on both sheets), which is not a surface: such a quadric may not compete as OTH.
    The test: the sign of ``grad f . n_plane`` must be the same for ``min_fraction`` of the points
    (``SelectParams.single_sheet_fraction``).
    """
    if not plane.ok:
        return True
    _, grad = evaluate(q.params, pts)
    s = np.sign(grad @ plane.normal)
    return bool(max(np.mean(s > 0), np.mean(s < 0)) >= min_fraction)


def _quadric_chi2_trim(q, pts: np.ndarray, sig: np.ndarray, trim_sigma: float) -> float:
    """Trimmed chi² of the quadric's Sampson distances (the same trimming as the primitives')."""
    f, grad = evaluate(q.params, pts)
    g = np.sqrt(np.einsum("ij,ij->i", grad, grad))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = f / np.maximum(g, 1e-300) / sig
    r = np.where(np.isfinite(r), r, 1e6)
    return fitting.trimmed_chi2(r, trim_sigma)


def _cone_score(cyl: fitting.CylinderFit, ps, ss, huber) -> tuple[float, tuple] | None:
    """Rao score test of the cone against the cylinder it nests, at the cylinder's solution.

    One Gauss-Newton step of the 6-parameter cone model from ``t = 0``: its predicted decrease of the
    (Huber) cost ``g' H^-1 g`` and the stepped state. Near t = 0 the cone's cost is close to quadratic in its
    parameters, so a predicted decrease well below the criterion's price of one parameter means the full
    cone fit (the costliest of all candidates: ~40 residual evaluations) cannot win.
    """
    state = (cyl.axis, cyl.point, cyl.radius, 0.0)
    r, J = fitting.cone_residuals(state, ps, ss)
    w = fitting.huber_weights(r, huber)
    Jw = J * w[:, None]
    H = J.T @ Jw
    g = Jw.T @ r
    try:
        step = -np.linalg.solve(H + 1e-12 * np.trace(H) * np.eye(6), g)
    except np.linalg.LinAlgError:
        return None
    dec = float(-(g @ step))
    if not np.isfinite(dec):
        return None
    return dec, step


def _gross_outliers(pts: np.ndarray, sig: np.ndarray, k: float) -> np.ndarray:
    """Mask of points far off the patch's bulk: distance to its (weighted PCA) plane more than ``k`` robust
    spreads (1.4826 MAD) from the median, and more than ``k`` sigmas.

    A patch's curvature keeps its points within a bounded, compact band about that plane; pixels of
    another surface met across a depth jump (a pipe behind, the wall behind a silhouette) lie far
    outside it and, a few percent of them, pulled the algebraic starts of the fits to a wrong cylinder
    whose local minimum the robust iterations could not leave.
    """
    sub = _subsample(len(pts), 2000)
    ps, ss = pts[sub], sig[sub]
    keep = np.ones(len(ps), bool)
    for _ in range(3):  # the plane of the kept points; a few far points can tilt the first one
        w = 1.0 / ss[keep] ** 2
        c = (w @ ps[keep]) / w.sum()
        d = ps[keep] - c
        _, vecs = np.linalg.eigh((d * w[:, None]).T @ d)
        # the scatter direction whose heights have the smallest robust spread: far points inflate the
        # variance along their direction and may make it any of the three eigenvectors, not the thinnest
        hh = (ps - c) @ vecs
        meds = np.median(hh[keep], axis=0)
        mads = np.median(np.abs(hh[keep] - meds), axis=0)
        j = int(np.argmin(mads))
        nv, hs, med = vecs[:, j], hh[:, j], float(meds[j])
        spread = 1.4826 * float(mads[j])
        new_keep = np.abs(hs - med) <= k * np.maximum(spread, ss)
        if np.array_equal(new_keep, keep) or new_keep.sum() < 0.5 * len(ps):
            break
        keep = new_keep
    dev = np.abs(pts @ nv - (c @ nv + med))
    return dev > k * np.maximum(spread, sig)


def _curvature_gain(plane: fitting.PlaneFit, ps: np.ndarray, ss: np.ndarray, trim_sigma: float) -> float:
    """Decrease of the trimmed chi² from the plane to the best quadratic height field over it (linear
    least squares in the plane's frame, residuals along its normal)."""
    e1, e2 = perpendicular_basis(plane.normal)
    c = ps.mean(axis=0)
    y = ps - c
    u, v = y @ e1, y @ e2
    h = y @ plane.normal
    s = max(float(np.sqrt(np.mean(u * u + v * v))), 1e-12)
    u, v = u / s, v / s
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1) / ss[:, None]
    sol, *_ = np.linalg.lstsq(A, h / ss, rcond=None)
    r = h / ss - A @ sol
    return _chi2_of(plane) - fitting.trimmed_chi2(r, trim_sigma)


def _elbow(crit: dict[str, float], gof: dict[str, float]) -> bool:
    """The torus fits within noise and beats every primitive (and the quadric): a pipe elbow."""
    return "TOR" in crit and gof.get("TOR", 0.0) >= 0.5 and crit["TOR"] <= min(crit.values())
