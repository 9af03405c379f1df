"""The one interface of patch classification (section 3 of Fillatreau & Fisher): :func:`classify_patch`
validates the patch, answers degenerate ones, and hands the rest to the chosen classifier."""

from __future__ import annotations

import numpy as np

from recognition import fitting
from recognition.fitting import check_patch

from .paper import _classify_paper
from .params import PaperParams, SelectParams
from .result import PatchClassification, _check_rays, _probs, _result, _subsample
from .select import _classify_select

__all__ = ["classify_patch"]


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
            pl = fitting.fit_plane(pts, sig)
            return _result("PLAN", _probs(PLAN=1), None, pl, reason="")
        return _result("OTH", _probs(OTH=1), None,
                       reason="points are exactly coplanar: quadric not unique (no planar hint)")
    return None
