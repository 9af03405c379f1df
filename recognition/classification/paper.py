"""The paper's classifier (section 3 of Fillatreau & Fisher), ``method="paper"`` of
:func:`recognition.classification.classify_patch`.

``method="paper"`` is section 3 of Fillatreau & Fisher, made precise and configurable (:class:`PaperParams`):
a general quadric is fitted with its covariance (:func:`recognition.fitting.fit_quadric`), brought to its
canonical form with propagated Gaussians of ``(l1, l2, l3, C_cano)``
(:func:`recognition.fitting.canonicalise`), and the plausibility of each class is the product of the
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
identifiable: any quadric containing the plane fits). The choices the paper leaves open (the "= 0" heuristic,
the eigenvalue bound, how many points are fitted and how they are chosen) are options of :class:`PaperParams`.
Class probabilities (for the Brier score, DESIGN
10.8): the three plausibilities, ``OTH = max(0, 1 - their sum)``, renormalised; ``PLAN = 1`` with the hint.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from recognition import fitting
from recognition.fitting import canonicalise, fit_quadric

from .params import PaperParams
from .result import PatchClassification, _invariants, _probs, _result, _rms_sigma, _subsample

__all__ = ["paper_plausibilities", "paper_subsample"]


def paper_subsample(n: int, max_points: int, mode: str = "stride") -> np.ndarray:
    """Indices (ascending) of the at most ``max_points`` of a patch's ``n`` points that the paper's quadric fit
    uses (:attr:`PaperParams.subsample`): all of them when ``n <= max_points``; else ``"stride"``, the rounded
    ``linspace(0, n - 1, max_points)``, or ``"random"``, ``max_points`` distinct indices drawn uniformly by
    ``default_rng(n)``."""
    if n <= max_points:
        return np.arange(n)
    if mode == "stride":
        return _subsample(n, max_points)
    if mode == "random":
        return np.sort(np.random.default_rng(n).choice(n, max_points, replace=False)).astype(np.intp)
    raise ValueError(f"subsample must be 'stride' or 'random', got {mode!r}")


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
    idx = paper_subsample(len(pts), params.max_points, params.subsample)
    ps, ss = pts[idx], sig[idx]
    bound = params.verify_factor * _rms_sigma(sig)
    if planar_hint:
        pl = fitting.fit_plane(pts, sig, nrm)
        return _result("PLAN", _probs(PLAN=1), None, pl if pl.ok else None, {},
                       "" if pl.ok else pl.reason)
    pl = fitting.fit_plane(ps, ss)
    if pl.ok and pl.rms_m <= bound:
        pl = fitting.fit_plane(pts, sig, nrm)
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
        fit = fitting.fit_sphere(pts, sig, nrm, **kw)
    else:
        axes = fitting.axis_candidates(ps, ss, None if nrm is None else nrm[idx], quadric=q)
        if best == "CYL":
            fit = fitting.fit_cylinder(pts, sig, nrm, axes=axes, **kw)
        else:
            fit = fitting.fit_cone(pts, sig, nrm, axes=axes, quadric=q, **kw)
    if not fit.ok:
        return _result("OTH", probs, plaus, reason=f"dedicated {best} fit failed: {fit.reason}",
                       details=details)
    if not fit.rms_m <= bound:
        return _result("OTH", probs, plaus, reason=(
            f"a posteriori check failed: {best} fit RMS {fit.rms_m * 1e3:.3g} mm > bound "
            f"{bound * 1e3:.3g} mm"),
            details=details)
    return _result(best, probs, plaus, fit, _invariants(fit, pts), "", details)
