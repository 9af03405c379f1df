"""The classification's result, :class:`PatchClassification`, and the helpers both classifiers share
(probabilities, invariants with their sigmas, subsampling)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recognition import fitting
from scenes.vocabulary import CLASSES  # the paper's classes, declared once for every layer

__all__ = ["CLASSES", "Primitive", "PatchClassification"]


Primitive = fitting.PlaneFit | fitting.CylinderFit | fitting.SphereFit | fitting.ConeFit | fitting.TorusFit


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


# ------------------------------------------------------------------------------------------ helpers


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
    if isinstance(fit, fitting.CylinderFit) and fit.ok:
        return {"radius_m": (fit.radius, k * fit.radius_sigma),
                "length_m": (fit.length, k * _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, fitting.SphereFit) and fit.ok:
        return {"radius_m": (fit.radius, k * fit.radius_sigma)}
    if isinstance(fit, fitting.ConeFit) and fit.ok:
        return {"half_angle_rad": (fit.half_angle, k * fit.half_angle_sigma),
                "length_m": (fit.length, k * _length_sigma(pts, fit.axis, fit.length))}
    if isinstance(fit, fitting.TorusFit) and fit.ok:  # a pipe elbow: its bend and pipe radii
        return {"major_radius_m": (fit.major_radius, k * fit.major_radius_sigma),
                "minor_radius_m": (fit.minor_radius, k * fit.minor_radius_sigma)}
    return {}
