"""Whether one primitive explains two patches (a surface the segmenter left in pieces): the merge test of the
scene description (:func:`recognition.describe.describe`, ``DescribeParams.merge_explained``), on the
model-selection classifier's criterion."""

from __future__ import annotations

import numpy as np

from recognition import fitting

from .criteria import _gof_threshold, _price
from .params import SelectParams
from .rescue import _refit, _residuals
from .result import Primitive, _subsample

__all__ = ["merge_test"]


def merge_test(fit_a: Primitive, points_a: np.ndarray, sigma_a: np.ndarray, fit_b: Primitive,
               points_b: np.ndarray, sigma_b: np.ndarray, params: SelectParams | None = None,
               correlation_area: float = 1.0) -> tuple[Primitive, float] | None:
    """Does one primitive of the same type explain two patches (a surface the segmenter left in pieces)?

    The union is fitted from ``fit_a`` (the larger patch's fit, say) on a regular-stride subsample of at most
    ``params.merge_points`` points; it must pass the goodness-of-fit test, and its trimmed chi² may exceed that of the
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
    idx = _subsample(len(pts), params.merge_points)
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
    chi2 = fitting.trimmed_chi2(r, params.trim_sigma)
    dof = max(n - k, 1)
    if not chi2 / dof <= _gof_threshold(params, dof):
        return None
    gain = (chi2 - fitting.trimmed_chi2(ra, params.trim_sigma) - fitting.trimmed_chi2(rb, params.trim_sigma)) / rho \
        - k * _price(n, params.criterion, rho)
    return (union, float(gain)) if gain < 0 else None
