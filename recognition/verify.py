"""Hypothesis verification by predicting the a priori model's range image (the paper's section 4).

For a hypothesised ``T_world_sensor`` the a priori model is ray cast with the scan's own sensor
(:func:`predict`, through a :class:`sensors.simulate.Simulator` built once per model), optionally on a
coarser grid of the same rays (every ``stride``-th pixel: a camera or laser whose rays are exactly the
full sensor's rays at those pixels). :func:`agreement` scores how well the data agree: for every scene
patch, the fraction of its pixels whose measured range lies within ``k_sigma * sigma + abs_m +
rel * range`` of the predicted range, averaged over patches with weights ``log(pixels)`` (DESIGN 6.3), so
a wall does not outvote every pipe and a few changed parts (moved, missing, new) only lower the score.
Pixels seen *behind* the prediction, up to ``seen_through`` of a patch, are left out of its fraction: a
missing pipe is predicted in front of the wall the data shows (the right pose of a mock-up whose pipe was
removed lost to its 180 deg turn, which predicts nothing there). A model object that would contain the
sensor cannot be where the model says: the prediction's rays pass through it (a Kinect-like trial whose
sensor stood where a removed tank had been predicted the tank's inside on every pixel, and the true pose
agreed 0.0; now 0.33, on the floor it sees).

The prediction (range and surface ids) is returned so it can be shared by ICP and change detection
(DESIGN 10.11).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from recognition.describe import SceneDescription
from sensors.models import PinholeCamera, ScanningLaser, SensorModel
from sensors.range_image import Scan

__all__ = ["VerifyParams", "Prediction", "coarse_sensor", "predict", "agreement"]


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
    """

    stride: int = 4
    k_sigma: float = 3.0
    abs_m: float = 0.003
    rel: float = 0.004
    min_pixels: int = 30
    seen_through: float = 0.5

    def __post_init__(self):
        if self.stride < 1 or self.min_pixels < 1:
            raise ValueError("stride and min_pixels must be >= 1")
        if self.k_sigma < 0 or self.abs_m < 0 or self.rel < 0:
            raise ValueError("k_sigma, abs_m and rel must be >= 0")
        if not 0 <= self.seen_through < 1:
            raise ValueError(f"seen_through must be in [0, 1), got {self.seen_through}")


@dataclass(frozen=True, eq=False)
class Prediction:
    """The a priori model's predicted range image at a pose.

    Attributes
    ----------
    T_world_sensor : ndarray of shape (4, 4), the pose it was cast from.
    range : ndarray of shape (h, w), metres, NaN where the model shows nothing.
    surface_id : ndarray of shape (h, w) int32, index into ``surfaces`` (-1 = none).
    surfaces : tuple of ``scenes.mjcf.Surface`` (feature_id, part, truth_class of each surface id).
    stride : the pixel stride: pixel ``(i, j)`` is the full image's ``(offset + i * stride, offset + j * stride)``.
    offset : see ``stride``.
    sensor : the (coarse) sensor model whose rays were cast.
    """

    T_world_sensor: np.ndarray
    range: np.ndarray
    surface_id: np.ndarray
    surfaces: tuple
    stride: int
    offset: int
    sensor: SensorModel

    def points_sensor(self) -> np.ndarray:
        """Predicted points (h, w, 3) in the sensor frame (NaN where none)."""
        return self.range[..., None] * self.sensor.ray_directions()

    def feature_ids(self) -> np.ndarray:
        """(h, w) array of feature ids (object dtype, None where none)."""
        names = np.array([s.feature_id for s in self.surfaces] + [None], dtype=object)
        return names[self.surface_id]

    def feature_pixels(self) -> dict[str, np.ndarray]:
        """Flat pixel indices (into this prediction's grid) predicted on each visible model feature."""
        return pixels_by_feature(self.surface_id, tuple(s.feature_id for s in self.surfaces))


def pixels_by_feature(surface_id: np.ndarray, surface_features: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Flat pixel indices of each feature in a surface-id image (``surface_features[i]``: feature of surface i)."""
    sid = surface_id.reshape(-1)
    hit = np.flatnonzero(sid >= 0)
    feats = np.array(surface_features, dtype=object)[sid[hit]]
    order = np.argsort(feats, kind="stable")
    names, starts = np.unique(feats[order], return_index=True)
    return {str(n): g for n, g in zip(names, np.split(hit[order], starts[1:]), strict=True)}


def coarse_sensor(sensor: SensorModel, stride: int) -> tuple[SensorModel, int]:
    """A sensor whose pixel ``(i, j)`` has exactly the ray of ``sensor``'s pixel ``(o + i s, o + j s)``.

    Returns ``(sensor, o)`` with ``o = stride // 2``; ``(sensor, 0)`` for ``stride == 1``.
    """
    if stride == 1:
        return sensor, 0
    o = stride // 2
    H, W = sensor.shape
    h, w = len(range(o, H, stride)), len(range(o, W, stride))
    if isinstance(sensor, PinholeCamera):
        return dataclasses.replace(sensor, width=w, height=h, fx=sensor.fx / stride, fy=sensor.fy / stride,
                                   cx=(sensor.cx - o) / stride, cy=(sensor.cy - o) / stride), o
    if isinstance(sensor, ScanningLaser):
        da, de = sensor.azimuth_step, sensor.elevation_step
        az0 = sensor.azimuth_min + (o + 0.5) * da - 0.5 * stride * da
        el1 = sensor.elevation_max - (o + 0.5) * de + 0.5 * stride * de
        return dataclasses.replace(sensor, n_azimuth=w, n_elevation=h, azimuth_min=az0,
                                   azimuth_max=az0 + w * stride * da, elevation_max=el1,
                                   elevation_min=el1 - h * stride * de), o
    raise TypeError(f"unsupported sensor model {type(sensor).__name__}")


def predict(simulator, sensor: SensorModel, T_world_sensor: np.ndarray, stride: int = 1) -> Prediction:
    """Ray cast the a priori model (``simulator``: ``Simulator.from_scene(model)``) from ``T_world_sensor``."""
    try:
        cs, o = coarse_sensor(sensor, stride)
    except ValueError:  # limits outside the valid range: fall back to full resolution
        cs, o, stride = sensor, 0, 1
    # a model object that would contain the sensor is not where the model says (the sensor could not be
    # inside it): the rays pass through it rather than predicting its inside everywhere
    rng, sid = simulator.truth_image(cs, np.asarray(T_world_sensor, dtype=np.float64), check=False,
                                     through_containing=True)
    return Prediction(np.array(T_world_sensor, dtype=np.float64), rng, sid, tuple(simulator.exported.surfaces),
                      stride, o, cs)


def agreement(description: SceneDescription, scan: Scan, prediction: Prediction,
              params: VerifyParams = VerifyParams()) -> tuple[float, dict[int, float]]:
    """Score in [0, 1] of the data's agreement with a prediction, and the per-patch fractions.

    Returns
    -------
    (score, fractions) : the ``log(pixels)``-weighted mean of the per-patch fractions of pixels within the
        threshold (module docstring), and ``{patch id: fraction}`` for the scored patches. 0 when nothing
        can be scored.
    """
    s, o = prediction.stride, prediction.offset
    h, w = prediction.range.shape
    labels = description.labels[o::s, o::s][:h, :w]
    meas = scan.range[o::s, o::s][:h, :w]
    sig = description.sigma[o::s, o::s][:h, :w]
    pred = prediction.range
    thr = params.k_sigma * np.nan_to_num(sig, nan=0.0) + params.abs_m + params.rel * np.nan_to_num(meas, nan=0.0)
    with np.errstate(invalid="ignore"):
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
