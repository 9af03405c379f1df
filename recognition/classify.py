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
the data pay for its extra parameter. A ring torus (:func:`recognition.primitives.fit_torus`, k = 7) competes as
a second model of OTH where bending the cylinder's axis passes a score test: a pipe elbow it explains is OTH
with its bend and pipe radii as invariants (``major_radius_m``, ``minor_radius_m``). A patch that would be OTH
but whose majority (``min_inliers``) one primitive fits within noise after least-trimmed-squares steps takes
that primitive's label (a neighbour merged in by the segmenter), unless the torus explains it (an elbow).

Both methods fit on a regular-stride subsample of at most ``max_points`` points (the information criterion
then works with that N: the decision is that of a patch of ``max_points`` points), and the chosen primitive
is polished by a Gauss-Newton step on all points so its parameters, covariance and invariants use the
whole patch.

Robustness and speed of ``select`` (issue 14, measured on real simulated scans of the default suite's
groups, with the real segmenter and with the truth segmentation): segmented patches carry mixed pixels,
outliers and bits of a neighbouring surface, so (1) the criterion and the goodness of fit use a trimmed
chi² (residuals beyond ``TRIM_SIGMA`` = 3.5 count as 3.5², :func:`recognition.primitives.trimmed_chi2`; the
quadric's Sampson distances likewise), (2) gross outliers off the patch's bulk are dropped first
(``outlier_k``). For speed, (3) cylinders, cones and spheres are not fitted when a linear quadratic height
field over the plane cannot pay for their extra parameters (``plane_gate``: large planes were most of a
frame's time), and (4) the cone is fitted only when a score test at the cylinder's solution says it might
win (``cone_score_skip``). With the sensor's sub-ray directions (``rays``), (5) a chosen cylinder or sphere
is refitted in range space with the beam footprint modelled (:func:`recognition.primitives.refit_along_rays`):
the geometric fit's radius was 2.1 % low (median) at factory-scanner resolution, the refit's is within
0.02 %. Cost on the ``default`` suite's VGA frames: median 0.14 s of CPU, p90 0.4 s, with the torus and the
trimmed rescue (``time.process_time``, single-threaded BLAS; a multi-threaded BLAS on a loaded 2-core machine
inflates process time 1.5-2x by spinning threads); ``paper`` about 0.1-0.2 s.

The invariants' visible length has a heuristic sigma: the point spacing ``sqrt(L W / N)`` (W the patch
width across the axis), since the length is set by the patch ends, not by the fit.

Degenerate patches (fewer than 10 points, NaNs, collinear or exactly coplanar points) give OTH with a
``reason`` (PLAN for coplanar points with ``planar_hint``), never an exception; wrong shapes raise
``ValueError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.special import ndtr

from scenes.geometry import perpendicular_basis

from . import primitives as prim
from .quadric import canonicalise, check_patch, evaluate, fit_quadric

__all__ = [
    "CLASSES", "PaperParams", "SelectParams", "PatchClassification", "classify_patch", "paper_plausibilities",
    "merge_test",
]

CLASSES = ("PLAN", "CYL", "SPH", "CONE", "OTH")

Primitive = prim.PlaneFit | prim.CylinderFit | prim.SphereFit | prim.ConeFit | prim.TorusFit


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
        Fit it on a calibration suite, never on the evaluation suite (DESIGN 10.8): T = 1 was best on the
        ``calibration`` suite (see ``prob_floor``).
    max_points : int
        Subsample size for the fits and the criterion.
    max_iter : int
        Iteration limit of each candidate fit. Correct models converge in 3-6 iterations from their starts
        at low noise but may crawl for 15-20 at Kinect-like noise (a cylinder cut off at 10 lost to the
        cone nested in it); models that are clearly losing stop early (``stop_above``).
    huber : float or None
        Huber threshold (sigma units) of the fits.
    cone_score_skip : float
        The cone is fitted only when a score test at the cylinder's solution (the decrease of the cost that
        one Gauss-Newton step of the cone predicts) reaches this fraction of the criterion's price of one
        parameter (``ln N`` for BIC); otherwise its criterion is the cylinder's plus that price minus the
        predicted decrease. 0: always fit it.
    prob_floor : float
        Mixed with the uniform distribution: ``p = (1 - f) p + f / 5`` (bounds the Brier cost of a confident
        error). Fitted with ``temperature`` and ``gof_width`` on the ``calibration`` suite
        (``harness/suites/calibration.yaml``, seed 4242, never on ``default``; DESIGN 10.8): grid search of the
        multi-class Brier score over the 199 patches of >= 200 pixels of its 24 scans, end to end (real
        segmenter), with T in {1, 2, 4, ..., 32}, f in {0, 0.05, 0.1, 0.2, 0.3}, gof_width in {0.1, ..., 1.6}:
        best T = 1, f = 0.1, gof_width = 0.1 (Brier 0.240 -> 0.227 at accuracy 0.879). The remaining Brier
        is that of confident errors on patches the segmenter merged across two surfaces, which no
        re-weighting of the posterior fixes.
    range_refit : bool
        With sub-ray directions (``rays`` of :func:`classify_patch`), refit a chosen cylinder or sphere in
        range space (:func:`recognition.primitives.refit_along_rays`), which removes the radius bias of the
        geometric fit (beam footprint, noise along the ray).
    refit_points : int
        Subsample size of that refit's iterations.
    outlier_k : float
        Gross outliers (see :func:`_gross_outliers`) are removed before fitting when they are at most 20 %
        of the patch; 0: keep all points.
    min_inliers : float
        A patch that would be OTH (no primitive fits all its points within noise, or a general quadric fits
        them better) gets the label of a primitive (plane, cylinder or sphere; not the cone, the most
        flexible) when, after three least-trimmed-squares refits on this fraction of its points, at least
        this fraction lies within ``TRIM_SIGMA`` of it and those pass the goodness-of-fit test; probability:
        that fraction. For patches the segmenter merged across two surfaces. 1: off. A pipe elbow also has
        most of its points near a cylinder (91 % within 3.5 sigma on a low-noise synthetic one), so an elbow
        that a torus explains (``torus``) is never rescued. Chosen on the ``calibration`` suite (seed 4242,
        never ``default``; DESIGN 10.8), end to end with the torus: 0.6, 0.7, 0.8 and 0.9 gave the same labels
        there, accuracy 0.895 -> 0.917 (factory scanner 0.924 -> 0.958, mock-up 0.983 -> 1.0, Kinect-like
        unchanged) and Brier 0.190 -> 0.151; 0.8, the middle, is the default.
    torus : bool
        Fit a ring torus (a pipe elbow, :func:`recognition.primitives.fit_torus`) when a curved primitive
        leads the criterion and the bend test passes (``torus_score_skip``). It competes as a model of OTH
        (k = 7): an elbow that it explains wins as OTH with its bend and pipe radii as invariants, where a
        cylinder or sphere would otherwise take its points at Kinect-like noise; and a torus that fits within
        noise and beats every primitive vetoes the trimmed rescue (``min_inliers``). The points must be in the
        sensor frame (the tube's normals are turned to face the origin).
    max_bend_ratio : float
        A torus competes only when its bend radius is at most this many pipe radii (pipe elbows are bent at
        1-5 pipe diameters): a torus of a much larger bend radius is a cylinder bent by the residuals of an
        impure patch or by range bias, not an elbow.
    torus_score_skip : float
        When the best primitive fits within noise, the torus is fitted only if bending the cylinder's axis
        (:func:`recognition.primitives.bend_test`, one linear least-squares step) predicts a decrease of
        the chi² of at least this fraction of the criterion's price of the torus's two extra parameters, with
        a bend radius of at most ``3 max_bend_ratio`` cylinder radii. On the ``calibration`` suite the torus
        took accuracy from 0.890 to 0.895 without the trimmed rescue (mock-up 0.967 -> 0.983).
    min_torus_points : int
        Patches of fewer points (after the gross outliers) get neither the torus nor the trimmed rescue:
        too few points to pin a torus's 7 parameters or to tell a majority from a merged neighbour; the size
        below which the evaluation does not score patches either. On the ``calibration`` suite 200 and 0 gave
        the same accuracy, Brier and correct detection; on ``default`` the 15-20 small patches of a
        factory-scanner frame took half its classification time with them.
    plane_gate : float
        Cylinders, cones and spheres are not fitted when the plane passes the goodness-of-fit test and a
        quadratic height field over it lowers the trimmed chi² by less than this fraction of their price
        (``2 ln N`` for two more parameters, plus the planar hint's log odds): at this scale they are such
        height fields, so they cannot win (large planar patches were 70 % of a frame's time). 0: always fit
        them.
    invariant_sigma_scale : float
        Multiplies the sigmas of the reported invariants (radius, half-angle, length; the fits' own
        covariances are left alone). The fits' sandwich covariances miss errors shared by neighbouring points
        (beam footprint, incidence-dependent range bias): on the ``calibration`` suite (seed 4242, never
        ``default``; DESIGN 10.8) the radius errors of the 77 patches labelled CYL or SPH on a true cylinder or
        sphere had a median of 0.95 predicted sigmas where a Gaussian has 0.674: scale 1.415, rounded to 1.4.
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
    cone_score_skip: float = 0.7
    prob_floor: float = 0.1
    range_refit: bool = True
    refit_points: int = 600
    outlier_k: float = 8.0
    min_inliers: float = 0.8
    torus: bool = True
    max_bend_ratio: float = 10.0
    torus_score_skip: float = 0.7
    min_torus_points: int = 200
    plane_gate: float = 0.5
    invariant_sigma_scale: float = 1.4


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
    primitive : PlaneFit | CylinderFit | SphereFit | ConeFit | TorusFit | None
        The dedicated fit of the label; for OTH the torus of a pipe elbow, or None.
    invariants : dict[str, tuple[float, float]]
        ``name -> (value, sigma)``: ``radius_m``, ``length_m`` (cylinder); ``radius_m`` (sphere);
        ``half_angle_rad``, ``length_m`` (cone); ``major_radius_m``, ``minor_radius_m`` (OTH that a torus
        explains: a pipe elbow's bend and pipe radii).
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


def _check_rays(rays, n: int) -> np.ndarray:
    r = np.asarray(rays, dtype=np.float64)
    if r.ndim == 2:
        r = r[None]
    if r.ndim != 3 or r.shape[1:] != (n, 3):
        raise ValueError(f"expected rays of shape (k, {n}, 3), got {r.shape}")
    return r


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
    sub = pts[_subsample(n, 4000)]
    d = sub - sub.mean(axis=0)
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


def _invariants(fit: Primitive | None, pts: np.ndarray, sigma_scale: float = 1.0) -> dict[str, tuple[float, float]]:
    """The fit's invariants as ``{name: (value, sigma)}``, the sigmas times ``sigma_scale``."""
    k = sigma_scale
    if isinstance(fit, prim.CylinderFit) and fit.ok:
        return {"radius_m": (fit.radius, k * fit.radius_sigma),
                "length_m": (fit.length, k * _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, prim.SphereFit) and fit.ok:
        return {"radius_m": (fit.radius, k * fit.radius_sigma)}
    if isinstance(fit, prim.ConeFit) and fit.ok:
        return {"half_angle_rad": (fit.half_angle, k * fit.half_angle_sigma),
                "length_m": (fit.length, k * _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, prim.TorusFit) and fit.ok:  # a pipe elbow: its bend and pipe radii
        return {"major_radius_m": (fit.major_radius, k * fit.major_radius_sigma),
                "minor_radius_m": (fit.minor_radius, k * fit.minor_radius_sigma)}
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


def _price(n: int, kind: str, rho: float = 1.0) -> float:
    """The criterion's price of one parameter: ``ln n_eff`` (BIC, ``n_eff = n / rho`` independent samples,
    at least 8: never below AIC's 2) or 2 (AIC)."""
    return float(np.log(max(n / rho, 8.0))) if kind == "bic" else 2.0


def _criterion(chi2: float, k: int, n: int, kind: str, rho: float = 1.0) -> float:
    """Information criterion of a fit of ``k`` parameters to ``n`` points whose errors are correlated in
    groups of ``rho`` (:func:`_classify_select`): ``chi2 / rho + k price``."""
    return chi2 / rho + k * _price(n, kind, rho)


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


def _chi2_of(f) -> float:
    """The robust (trimmed) chi² of a fit, or its plain chi² when the trimmed one is not available."""
    c = getattr(f, "chi2_trim", np.nan)
    return float(c) if np.isfinite(c) else float(f.chi2)


def _quadric_chi2_trim(q, pts: np.ndarray, sig: np.ndarray) -> float:
    """Trimmed chi² of the quadric's Sampson distances (the same trimming as the primitives')."""
    f, grad = evaluate(q.params, pts)
    g = np.sqrt(np.einsum("ij,ij->i", grad, grad))
    with np.errstate(divide="ignore", invalid="ignore"):
        r = f / np.maximum(g, 1e-300) / sig
    r = np.where(np.isfinite(r), r, 1e6)
    return prim.trimmed_chi2(r)


def _cone_score(cyl: prim.CylinderFit, ps, ss, huber) -> tuple[float, tuple] | None:
    """Rao score test of the cone against the cylinder it nests, at the cylinder's solution.

    One Gauss-Newton step of the 6-parameter cone model from ``t = 0``: its predicted decrease of the
    (Huber) cost ``g' H^-1 g`` and the stepped state. Near t = 0 the cone's cost is close to quadratic in its
    parameters, so a predicted decrease well below the criterion's price of one parameter means the full
    cone fit (the costliest of all candidates: ~40 residual evaluations) cannot win.
    """
    state = (cyl.axis, cyl.point, cyl.radius, 0.0)
    r, J = prim._cone_fun(state, ps, ss)
    w = prim._huber_w(r, huber)
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


def _trimmed_rescue(fits, crit, gof, ps, ss, ns, axes, q, params: SelectParams, n: int, rho: float = 1.0,
                    core: np.ndarray | None = None):
    """A patch none of whose models fits all points: does one primitive fit most of them?

    Segmented patches may include a neighbouring surface's pixels at their borders, or a piece of another
    surface merged in. For each of plane, cylinder and sphere, keep the points within ``TRIM_SIGMA`` of it
    and refit on them (concentration steps of a least-trimmed-squares fit, twice). When at least
    ``min_inliers`` of the points remain and the refit passes the goodness-of-fit test on them, return
    ``(label, fit, inlier fraction)`` of the one of lowest criterion on its trimmed chi²; else None.
    Curved shapes that no primitive explains (elbows) leave large, structured residuals on most points and
    stay OTH. ``core`` (subsample mask): the points the gross outlier test keeps when it flagged too many to
    drop; each primitive is also fitted afresh on them and refined from there, since a fit of all the points
    of a pipe with the wall behind it merged in may sit in the mixture's basin, which the concentration
    steps do not leave.
    """
    # not the cone: the most flexible primitive, it fits most of an elbow's points within noise
    cands = [c for c in ("PLAN", "CYL", "SPH") if c in crit and fits[c].ok and not fits[c].reason]
    if not cands:
        return None
    found = None
    starts = [(c, fits[c]) for c in sorted(cands, key=crit.get)]
    if core is not None and core.sum() >= max(10, params.min_inliers * n * 0.5):
        kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter}
        nc = None if ns is None else ns[core]
        fresh = {"PLAN": lambda: prim.fit_plane(ps[core], ss[core], nc),
                 "CYL": lambda: prim.fit_cylinder(ps[core], ss[core], nc, **kw),
                 "SPH": lambda: prim.fit_sphere(ps[core], ss[core], **kw)}
        for c in list(cands):
            f = fresh[c]()
            if f.ok:
                starts.append((c, f))
    for c, start in starts:
        got = _trim_refit(start, ps, ss, ns, params, n)
        if got is None:
            continue
        # among those that pass, the lowest criterion on the trimmed chi² of all points (a more flexible
        # primitive always keeps at least as many inliers)
        score = _criterion(prim.trimmed_chi2(_residuals(got[0], ps, ss)), got[0].n_params, n, params.criterion,
                           rho)
        if found is None or score < found[3]:
            found = (c, got[0], got[1], score)
    return None if found is None else found[:3]


def _trim_refit(fit, ps, ss, ns, params: SelectParams, n: int):
    """Concentration steps of one primitive (least trimmed squares: three refits on the ``min_inliers``
    fraction of points closest to the current fit); ``(fit, inlier fraction)`` if it passes, else None.

    On the ``calibration`` suite these steps rescued more than two refits on the points within ``TRIM_SIGMA``
    (accuracy 0.912 -> 0.917, factory scanner 0.950 -> 0.958): a fit pulled by a merged neighbour may leave
    fewer than ``min_inliers`` of the points within ``TRIM_SIGMA`` at the start."""
    h = max(int(np.ceil(params.min_inliers * n)), 10)
    for _ in range(3):
        r = _residuals(fit, ps, ss)
        if r is None or h > len(r):
            return None
        # least trimmed squares: refit on the h points closest to the current fit
        mask = np.zeros(len(r), bool)
        mask[np.argpartition(np.abs(r), h - 1)[:h]] = True
        fit = _refit(fit, ps[mask], ss[mask], None if ns is None else ns[mask], params)
        if not fit.ok:
            return None
    r = _residuals(fit, ps, ss)
    mask = np.abs(r) <= prim.TRIM_SIGMA
    frac = float(mask.mean())
    m = int(mask.sum())
    if frac < params.min_inliers:
        return None
    chi2 = float(np.sum(r[mask] ** 2))
    dof = max(m - fit.n_params, 1)
    if not chi2 / dof <= _gof_threshold(params, dof):
        return None
    return fit, frac


def _residuals(fit, pts, sig) -> np.ndarray | None:
    """Sigma-normalised orthogonal residuals of a primitive."""
    if isinstance(fit, prim.PlaneFit):
        return (pts @ fit.normal - fit.offset) / sig
    if isinstance(fit, prim.SphereFit):
        return (np.linalg.norm(pts - fit.centre, axis=1) - fit.radius) / sig
    if isinstance(fit, prim.CylinderFit):
        return prim._cyl_fun((fit.axis, fit.point, fit.radius), pts, sig)[0]
    if isinstance(fit, prim.ConeFit):
        return prim._cone_fun((fit.axis, fit.point, fit.radius_at_point, np.tan(fit.half_angle)), pts, sig)[0]
    return None


def _refit(fit, pts, sig, nrm, params: SelectParams):
    kw = {"max_points": None, "huber": params.huber, "max_iter": 8}
    if isinstance(fit, prim.PlaneFit):
        return prim.fit_plane(pts, sig, nrm)
    if isinstance(fit, prim.SphereFit):
        return prim.fit_sphere(pts, sig, init=(fit.centre, fit.radius), **kw)
    if isinstance(fit, prim.CylinderFit):
        return prim.fit_cylinder(pts, sig, init=(fit.point, fit.axis, fit.radius), **kw)
    init = (fit.point, fit.axis, fit.radius_at_point, np.tan(fit.half_angle))
    return prim.fit_cone(pts, sig, init=init, axis_search=False, **kw)


def merge_test(fit_a: Primitive, points_a: np.ndarray, sigma_a: np.ndarray, fit_b: Primitive,
               points_b: np.ndarray, sigma_b: np.ndarray, params: SelectParams | None = None,
               correlation_area: float = 1.0, max_points: int = 1500) -> tuple[Primitive, float] | None:
    """Does one primitive of the same type explain two patches (a surface the segmenter left in pieces)?

    The union is fitted from ``fit_a`` (the larger patch's fit, say) on a regular-stride subsample of at most
    ``max_points`` points; it must pass the goodness-of-fit test, and its trimmed chi² may exceed that of the
    two patches' own fits on the same points by less than the criterion's price of the parameters the merge
    saves (as in :func:`classify_patch`, correlated errors counted as ``correlation_area`` pixels per
    independent one). Returns ``(union fit, criterion gain)`` (gain < 0) or None.
    """
    params = SelectParams() if params is None else params
    if type(fit_a) is not type(fit_b) or not (fit_a.ok and fit_b.ok):
        return None
    pts = np.concatenate([points_a, points_b])
    sig = np.concatenate([sigma_a, sigma_b])
    in_a = np.arange(len(pts)) < len(points_a)
    idx = _subsample(len(pts), max_points)
    ps, ss, ia = pts[idx], sig[idx], in_a[idx]
    union = _refit(fit_a, ps, ss, None, params)
    if not union.ok:
        return None
    r = _residuals(union, ps, ss)
    ra, rb = _residuals(fit_a, ps[ia], ss[ia]), _residuals(fit_b, ps[~ia], ss[~ia])
    if r is None or ra is None or rb is None:
        return None
    n, k = len(ps), union.n_params
    rho = max(1.0, float(correlation_area) * n / len(pts))
    chi2 = prim.trimmed_chi2(r)
    dof = max(n - k, 1)
    if not chi2 / dof <= _gof_threshold(params, dof):
        return None
    gain = (chi2 - prim.trimmed_chi2(ra) - prim.trimmed_chi2(rb)) / rho - k * _price(n, params.criterion, rho)
    return (union, float(gain)) if gain < 0 else None


def _classify_select(pts, sig, nrm, params: SelectParams, planar_hint: bool, rays=None,
                     correlation_area: float = 1.0) -> PatchClassification:
    n_in = len(pts)
    n_dropped = 0
    keep = None
    if params.outlier_k > 0:
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
    core = None if keep is not None or params.outlier_k <= 0 or not out.any() else ~out[idx]
    ps, ss = pts[idx], sig[idx]
    ns = None if nrm is None else nrm[idx]
    n = len(ps)
    # points of the subsample per independent error: the image's correlation area thinned by the stride
    rho = max(1.0, float(correlation_area) * n / n_all)
    kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter}
    fits: dict[str, Primitive] = {}
    fits["PLAN"] = prim.fit_plane(ps, ss, ns)

    def cap() -> float | None:
        """Early stop for fits that are clearly losing: 1.5x the best chi² so far."""
        c = [f.chi2 for f in fits.values() if f.ok and np.isfinite(f.chi2)]
        return 1.5 * min(c) if c else None

    flat = False
    if params.plane_gate > 0 and fits["PLAN"].ok:
        dec = _curvature_gain(fits["PLAN"], ps, ss)
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
    fits["SPH"] = prim.fit_sphere(ps, ss, stop_above=cap(), **kw)
    axes = prim.axis_candidates(ps, ss, ns, quadric=q)
    fits["CYL"] = prim.fit_cylinder(ps, ss, ns, axes=axes, stop_above=cap(), **kw)
    skip_cone = False
    if fits["CYL"].ok and params.cone_score_skip > 0:
        sc = _cone_score(fits["CYL"], ps, ss, params.huber)
        if sc is not None and sc[0] / rho < params.cone_score_skip * _price(n, params.criterion, rho):
            skip_cone = True
    if skip_cone:
        # the cone cannot pay for its parameter: its criterion is that of the cylinder plus the price of one
        # parameter minus the predicted decrease (so it keeps a small, honest posterior share)
        fits["CONE"] = prim.ConeFit(
            apex=np.full(3, np.inf), axis=fits["CYL"].axis, half_angle=0.0, length=fits["CYL"].length,
            point=fits["CYL"].point, radius_at_point=fits["CYL"].radius, cov=np.full((8, 8), np.nan),
            half_angle_sigma=np.nan, axis_sigma_rad=np.nan, rms_m=fits["CYL"].rms_m,
            rms_sigma=fits["CYL"].rms_sigma, chi2=max(fits["CYL"].chi2 - sc[0], 0.0), n_points=n, n_iter=0,
            ok=True, reason="not fitted: score test against the cylinder",
            chi2_trim=max(_chi2_of(fits["CYL"]) - sc[0], 0.0))
    else:
        fits["CONE"] = prim.fit_cone(ps, ss, ns, init=fits["CYL"] if fits["CYL"].ok else None, axes=axes,
                                     quadric=q, stop_above=cap(), **kw)
    cone, cyl0 = fits["CONE"], fits["CYL"]
    if cone.ok and not skip_cone and (not cyl0.ok or _criterion(_chi2_of(cone), cone.n_params, n, params.criterion, rho)
                                      < _criterion(_chi2_of(cyl0), cyl0.n_params, n, params.criterion, rho)):
        # the cone would win: the cylinder is the cone at half-angle 0, and started on the cone's axis it may
        # leave a wrong basin of its own starts (a near-cylinder that only the cone fitted)
        cyl = prim.fit_cylinder(ps, ss, init=(cone.point, cone.axis, cone.radius_at_point), **kw)
        if cyl.ok and (not fits["CYL"].ok or _chi2_of(cyl) < _chi2_of(fits["CYL"])):
            fits["CYL"] = cyl
    crit, gof = _criteria(fits, n, params, rho)
    if params.torus and n_all >= params.min_torus_points and fits["CYL"].ok and min(crit, key=crit.get) != "PLAN":
        gain, bend = prim.bend_test(fits["CYL"], ps, ss, params.huber)
        # fitted only when bending the cylinder's axis might pay for the torus's two extra parameters (a
        # score test, as for the cone) and bends it like an elbow (within 3x the largest elbow's bend)
        fit_torus = (gain / rho >= params.torus_score_skip * 2.0 * _price(n, params.criterion, rho) and
                     bend <= 3.0 * params.max_bend_ratio * fits["CYL"].radius)
    else:
        fit_torus = False
    if fit_torus:
        fits["TOR"] = prim.fit_torus(ps, ss, ns, cylinder=fits["CYL"], stop_above=cap(), **kw)
        if fits["TOR"].ok and fits["TOR"].major_radius <= params.max_bend_ratio * fits["TOR"].minor_radius:
            crit, gof = _criteria(fits, n, params, rho)
        else:
            del fits["TOR"]
    extra = {"cone_skipped": skip_cone, "n_gross_outliers": n_dropped, "correlation": rho,
             "correlation_area": float(correlation_area)}
    return _decide(fits, crit, gof, q, ps, ss, pts, sig, nrm, rays, params, planar_hint, n, n_all, extra,
                   axes=axes, ns=ns, n_in=n_in, keep=keep, core=core)


def _curvature_gain(plane: prim.PlaneFit, ps: np.ndarray, ss: np.ndarray) -> float:
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
    return _chi2_of(plane) - prim.trimmed_chi2(r)


def _criteria(fits, n: int, params: SelectParams, rho: float = 1.0) -> tuple[dict[str, float], dict[str, float]]:
    crit: dict[str, float] = {}
    gof: dict[str, float] = {}
    for c, f in fits.items():
        if f.ok and np.isfinite(f.chi2):
            chi2 = _chi2_of(f)
            crit[c] = _criterion(chi2, f.n_params, n, params.criterion, rho)
            dof = max(n - f.n_params, 1)
            gof[c] = _gof(chi2 / dof, _gof_threshold(params, dof), params.gof_width)
    return crit, gof


def _gof_threshold(params: SelectParams, dof: int) -> float:
    """Largest reduced chi² of a model that fits within noise: ``gof_factor + gof_z sqrt(2 / dof)``."""
    return params.gof_factor + params.gof_z * np.sqrt(2.0 / dof)


def _gof(red: float, thr: float, width: float) -> float:
    """Smooth goodness-of-fit plausibility: 1/2 at the threshold, logistic in ``(red - thr) / (width thr)``."""
    return float(1.0 / (1.0 + np.exp(np.clip((red - thr) / (width * thr), -50, 50))))


def _elbow(crit: dict[str, float], gof: dict[str, float]) -> bool:
    """The torus fits within noise and beats every primitive (and the quadric): a pipe elbow."""
    return "TOR" in crit and gof.get("TOR", 0.0) >= 0.5 and crit["TOR"] <= min(crit.values())


def _decide(fits, crit, gof, q, ps, ss, pts, sig, nrm, rays, params: SelectParams, planar_hint: bool, n: int,
            n_all: int, extra: dict, axes=None, ns=None, n_in: int = 0, keep=None,
            core: np.ndarray | None = None) -> PatchClassification:
    kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter}
    skip_cone = extra.get("cone_skipped", False)
    rho = extra.get("correlation", 1.0)
    if params.quadric_as_other:
        if q is not None and q.ok and _single_sheet(q, ps, fits["PLAN"]):
            crit["OTH"] = _criterion(_quadric_chi2_trim(q, ps, ss), 9, n, params.criterion, rho) + \
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
    if params.prob_floor > 0:
        probs = _probs(**{c: (1.0 - params.prob_floor) * v + params.prob_floor / len(CLASSES)
                          for c, v in probs.items()})
    plaus = {c: float(probs[c]) for c in ("CYL", "SPH", "CONE")}
    label = max(CLASSES, key=lambda c: probs[c])
    details = {"criterion": crit, "gof": gof, "posterior": post, "fits": fits, "n_used": n, **extra}
    # the fits' covariances treat every point as an independent error; errors shared by groups of
    # ``correlation_area`` pixels make their parameters vary up to that many times more (variance)
    sigma_scale = params.invariant_sigma_scale * math.sqrt(
        max(1.0, min(extra.get("correlation_area", 1.0), len(pts))))
    if label == "OTH" and params.min_inliers < 1.0 and n_all >= params.min_torus_points and not _elbow(crit, gof):
        rescue = _trimmed_rescue(fits, crit, gof, ps, ss, ns, axes, q, params, n, rho, core)
        if rescue is not None:
            label, fit, frac = rescue
            fits[label] = fit
            pr = {c: 0.0 for c in CLASSES}
            pr[label] = frac
            pr["OTH"] = 1.0 - frac
            probs = _probs(**pr)
            if params.prob_floor > 0:
                probs = _probs(**{c: (1.0 - params.prob_floor) * v + params.prob_floor / len(CLASSES)
                                  for c, v in probs.items()})
            plaus = {c: float(probs[c]) for c in ("CYL", "SPH", "CONE")}
            label = max(CLASSES, key=lambda c: probs[c])
            details["trimmed_inlier_fraction"] = frac
    if label == "OTH":
        if _elbow(crit, gof):
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
        fit = prim.fit_cone(ps, ss, ns, init=fits["CYL"], axes=axes, quadric=q, **kw)
        if not fit.ok:
            return _result("OTH", probs, plaus, None, {}, f"cone fit failed: {fit.reason}", details)
    if n_all > n:
        polished = _polish(fit, pts, sig, nrm, params.huber)
        if polished.ok:
            fit = polished
    if rays is not None and params.range_refit and isinstance(fit, prim.CylinderFit | prim.SphereFit):
        if callable(rays):
            rays = _check_rays(rays(), n_in)
            if keep is not None:
                rays = rays[:, keep]
        refit = prim.refit_along_rays(fit, pts, sig, rays, huber=params.huber, max_points=params.refit_points)
        details["geometric_fit"] = fit
        fit = refit
    return _result(label, probs, plaus, fit, _invariants(fit, pts, sigma_scale), "", details)


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
    rays: np.ndarray | None = None,
    correlation_area: float = 1.0,
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
    rays : ndarray of shape (k, N, 3) or callable returning one, optional
        Unit directions of each point's sub-rays (beam footprint, the centre ray first; ``k = 1``: the
        centre rays only), with ``points`` in the sensor frame (sensor at the origin); a callable is only
        called when needed. ``select`` then refits
        a chosen cylinder or sphere in range space (see :attr:`SelectParams.range_refit`); ``paper``
        ignores it.
    correlation_area : float
        Pixels per independent range error in the patch's image (>= 1; the sensor's
        :attr:`sensors.noise.NoiseModel.correlation_area`). ``select`` divides its chi² differences by
        the points of its subsample per independent error and prices parameters by the independent samples
        (BIC's ``ln n_eff``): correlated errors are not evidence for a more flexible model. The reported
        invariants' sigmas are multiplied by ``sqrt(correlation_area)`` (at most the patch's point count):
        the fits' covariances count every point as an independent error (the primitive's own covariance is
        left as fitted). 1 (default): independent errors; ``paper`` ignores it.

    Returns
    -------
    PatchClassification

    Raises
    ------
    ValueError
        On wrong shapes, an unknown method or params of the wrong type.
    """
    pts, sig, nrm = check_patch(points, sigma, normals)
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
    if rays is not None and not callable(rays):
        rays = _check_rays(rays, len(pts))
    return _classify_select(pts, sig, nrm, params, planar_hint, rays, correlation_area)
