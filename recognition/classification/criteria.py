"""Information criteria and goodness of fit of the model-selection classifier (:mod:`.select`), shared with
its trimmed rescue and the merge test."""

from __future__ import annotations

import numpy as np

from .params import SelectParams


def _price(n: int, kind: str, rho: float = 1.0) -> float:
    """The criterion's price of one parameter: ``ln n_eff`` (BIC, ``n_eff = n / rho`` independent samples,
    at least 8: never below AIC's 2) or 2 (AIC)."""
    return float(np.log(max(n / rho, 8.0))) if kind == "bic" else 2.0


def _criterion(chi2: float, k: int, n: int, kind: str, rho: float = 1.0) -> float:
    """Information criterion of a fit of ``k`` parameters to ``n`` points whose errors are correlated in
    groups of ``rho`` (:func:`_classify_select`): ``chi2 / rho + k price``."""
    return chi2 / rho + k * _price(n, kind, rho)


def _chi2_of(f) -> float:
    """The robust (trimmed) chi² of a fit, or its plain chi² when the trimmed one is not available."""
    c = getattr(f, "chi2_trim", np.nan)
    return float(c) if np.isfinite(c) else float(f.chi2)


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
