"""Hypothesis verification by predicting the a priori model's range image (the paper's section 4).

For a hypothesised ``T_world_sensor`` the a priori model is ray cast with the scan's own sensor
(:func:`recognition.localisation.prediction.predict`), optionally on a coarser grid of the same rays.
:func:`agreement` scores how well the data agree: for every scene
patch, the fraction of its pixels whose measured range lies within ``k_sigma * sigma + abs_m +
rel * range`` of the predicted range, averaged over patches with weights ``log(pixels)`` (DESIGN 6.3), so
a wall does not outvote every pipe and a few changed parts (moved, missing, new) only lower the score.
Pixels seen *behind* the prediction, up to ``seen_through`` of a patch, are left out of its fraction: a
missing pipe is predicted in front of the wall the data shows (the right pose of a mock-up whose pipe was
removed lost to its 180 deg turn, which predicts nothing there). A model object that would contain the
sensor cannot be where the model says: the prediction's rays pass through it (a Kinect-like trial whose
sensor stood where a removed tank had been predicted the tank's inside on every pixel, and the true pose
agreed 0.0; now 0.33, on the floor it sees).

The prediction (:class:`recognition.localisation.Prediction`) is shared by ICP and change detection
(DESIGN 10.11).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recognition.describe import SceneDescription
from recognition.tuning import tuned
from sensors.range_image import Scan

from .prediction import Prediction

__all__ = ["VerifyParams", "agreement", "soft_agreement"]


@dataclass(frozen=True)
class VerifyParams:
    """Parameters of the verification.

    Attributes
    ----------
    stride : pixel stride of the hypothesis predictions (1 = full resolution).
    k_sigma : agreement threshold in units of the core's per-pixel sigma ...
    abs_m : ... plus this absolute allowance (metres) ...
    rel : ... plus this fraction of the range (pose error of a closed-form hypothesis grows with range).
    min_pixels : patches smaller than this are not scored.
    seen_through : up to this fraction of a patch's pixels may lie behind the prediction without counting
        against it: a model object that is missing from the scene is predicted in front of the surface the
        data shows behind it (the pixels neither agree nor disagree). A pose that predicts a wall in front of
        everything still disagrees on the rest. 0: every pixel counts.

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    stride: int = tuned(4, unit="px", chosen="not tuned: a speed setting, set in c9baa1a")
    k_sigma: float = tuned(3.0, unit="sigma", chosen="not tuned: set in c9baa1a")
    abs_m: float = tuned(0.003, unit="m", chosen="not tuned: set in c9baa1a")
    rel: float = tuned(0.004, unit="fraction of range", chosen="not tuned: set in c9baa1a")
    min_pixels: int = tuned(30, unit="px", chosen="not tuned: set in c9baa1a")
    seen_through: float = tuned(
        0.5, unit="fraction", chosen="the first phase's default (now classic): mock-up pose success 11/12 -> 12/12, "
        "change macro-F1 0.845 -> 0.853 (aec1145)")

    def __post_init__(self):
        if self.stride < 1 or self.min_pixels < 1:
            raise ValueError("stride and min_pixels must be >= 1")
        if self.k_sigma < 0 or self.abs_m < 0 or self.rel < 0:
            raise ValueError("k_sigma, abs_m and rel must be >= 0")
        if not 0 <= self.seen_through < 1:
            raise ValueError(f"seen_through must be in [0, 1), got {self.seen_through}")


def agreement(description: SceneDescription, scan: Scan, prediction: Prediction,
              params: VerifyParams = VerifyParams()) -> tuple[float, dict[int, float]]:
    """Score in [0, 1] of the data's agreement with a prediction, and the per-patch fractions.

    Returns
    -------
    (score, fractions) : the ``log(pixels)``-weighted mean of the per-patch fractions of pixels within the
        threshold (module docstring), and ``{patch id: fraction}`` for the scored patches. 0 when nothing
        can be scored.
    """
    return _agreement(description, scan, prediction, params, soft=False)


def soft_agreement(description: SceneDescription, scan: Scan, prediction: Prediction,
                   params: VerifyParams = VerifyParams()) -> tuple[float, dict[int, float]]:
    """:func:`agreement` with each pixel counted by how well it agrees, ``max(0, 1 - (residual / threshold)²)``
    (an Epanechnikov kernel of the range residual), instead of 0 or 1.

    The count of pixels within the threshold does not change while a pose moves by less than the threshold (a
    centimetre at a few metres); this score does, smoothly, so it can tell a pose from one moved by less
    (:mod:`recognition.localisation.precision`).
    """
    return _agreement(description, scan, prediction, params, soft=True)


def _agreement(description: SceneDescription, scan: Scan, prediction: Prediction, params: VerifyParams,
               soft: bool) -> tuple[float, dict[int, float]]:
    s, o = prediction.stride, prediction.offset
    h, w = prediction.range.shape
    labels = description.labels[o::s, o::s][:h, :w]
    meas = scan.range[o::s, o::s][:h, :w]
    sig = description.sigma[o::s, o::s][:h, :w]
    pred = prediction.range
    thr = params.k_sigma * np.nan_to_num(sig, nan=0.0) + params.abs_m + params.rel * np.nan_to_num(meas, nan=0.0)
    with np.errstate(invalid="ignore"):
        if soft:
            good = np.nan_to_num(np.maximum(0.0, 1.0 - ((meas - pred) / thr) ** 2), nan=0.0)
        else:
            good = np.abs(meas - pred) <= thr
        behind = meas - pred > thr
    lab = labels.ravel()
    sel = lab >= 0
    if not sel.any():
        return 0.0, {}
    n_lab = int(lab.max()) + 1
    total = np.bincount(lab[sel], minlength=n_lab).astype(np.float64)
    agree = np.bincount(lab[sel], weights=good.ravel()[sel].astype(np.float64), minlength=n_lab)
    if params.seen_through > 0:
        n_behind = np.bincount(lab[sel], weights=behind.ravel()[sel].astype(np.float64), minlength=n_lab)
        total = total - np.minimum(n_behind, params.seen_through * total)
    num = den = 0.0
    fractions: dict[int, float] = {}
    for p in description.patches:
        if p.n_pixels < params.min_pixels or p.id >= n_lab or total[p.id] == 0:
            continue
        f = float(agree[p.id] / total[p.id])
        wgt = float(np.log(p.n_pixels))
        fractions[p.id] = f
        num += wgt * f
        den += wgt
    return (num / den if den > 0 else 0.0), fractions
