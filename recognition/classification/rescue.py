"""The trimmed rescue of the model-selection classifier (:mod:`.select`): a patch that no model fits whole,
but whose majority one primitive fits within noise (a neighbour merged in by the segmenter), takes that
primitive's label; least-trimmed-squares refits of one primitive."""

from __future__ import annotations

import numpy as np

from recognition import fitting

from .criteria import _criterion, _gof_threshold
from .params import SelectParams


def _trimmed_rescue(fits, crit, gof, ps, ss, ns, axes, q, params: SelectParams, n: int, rho: float = 1.0,
                    core: np.ndarray | None = None):
    """A patch none of whose models fits all points: does one primitive fit most of them?

    Segmented patches may include a neighbouring surface's pixels at their borders, or a piece of another
    surface merged in. For each of plane, cylinder and sphere, keep the points within ``trim_sigma`` of it
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
        kw = {"max_points": None, "huber": params.huber, "max_iter": params.max_iter, "trim_sigma": params.trim_sigma}
        nc = None if ns is None else ns[core]
        fresh = {"PLAN": lambda: fitting.fit_plane(ps[core], ss[core], nc, trim_sigma=params.trim_sigma),
                 "CYL": lambda: fitting.fit_cylinder(ps[core], ss[core], nc, **kw),
                 "SPH": lambda: fitting.fit_sphere(ps[core], ss[core], **kw)}
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
        score = _criterion(fitting.trimmed_chi2(_residuals(got[0], ps, ss), params.trim_sigma), got[0].n_params, n,
                           params.criterion, rho)
        if found is None or score < found[3]:
            found = (c, got[0], got[1], score)
    return None if found is None else found[:3]


def _trim_refit(fit, ps, ss, ns, params: SelectParams, n: int):
    """Concentration steps of one primitive (least trimmed squares: three refits on the ``min_inliers``
    fraction of points closest to the current fit); ``(fit, inlier fraction)`` if it passes, else None.

    On the first phase's ``calibration`` suite these steps rescued more than two refits on the points within
    ``trim_sigma`` (accuracy 0.912 -> 0.917, factory scanner 0.950 -> 0.958): a fit pulled by a merged neighbour
    may leave fewer than ``min_inliers`` of the points within ``trim_sigma`` at the start."""
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
    mask = np.abs(r) <= params.trim_sigma
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
    if isinstance(fit, fitting.PlaneFit):
        return (pts @ fit.normal - fit.offset) / sig
    if isinstance(fit, fitting.SphereFit):
        return (np.linalg.norm(pts - fit.centre, axis=1) - fit.radius) / sig
    if isinstance(fit, fitting.CylinderFit):
        return fitting.cylinder_residuals((fit.axis, fit.point, fit.radius), pts, sig)[0]
    if isinstance(fit, fitting.ConeFit):
        return fitting.cone_residuals((fit.axis, fit.point, fit.radius_at_point, np.tan(fit.half_angle)), pts, sig)[0]
    return None


def _refit(fit, pts, sig, nrm, params: SelectParams):
    kw = {"max_points": None, "huber": params.huber, "max_iter": 8, "trim_sigma": params.trim_sigma}
    if isinstance(fit, fitting.PlaneFit):
        return fitting.fit_plane(pts, sig, nrm, trim_sigma=params.trim_sigma)
    if isinstance(fit, fitting.SphereFit):
        return fitting.fit_sphere(pts, sig, init=(fit.centre, fit.radius), **kw)
    if isinstance(fit, fitting.CylinderFit):
        return fitting.fit_cylinder(pts, sig, init=(fit.point, fit.axis, fit.radius), **kw)
    init = (fit.point, fit.axis, fit.radius_at_point, np.tan(fit.half_angle))
    return fitting.fit_cone(pts, sig, init=init, axis_search=False, **kw)
