"""Prediction of the a priori model's range image from a pose (the paper's section 4 verifies hypotheses, and
section 5 detects changes, against it): the model is ray cast with the scan's own sensor (:func:`predict`,
through a :class:`sensors.simulate.Simulator` built once per model: :class:`ModelPredictor`), optionally on a
coarser grid of the same rays (every ``stride``-th pixel: a camera or laser whose rays are exactly the full
sensor's rays at those pixels, :func:`coarse_sensor`). A model object that would contain the sensor cannot be
where the model says: the prediction's rays pass through it.

The prediction, :class:`Prediction` (range and surface ids), is cast once per pose hypothesis and shared by
verification, ICP and change detection (DESIGN 10.11).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from scenes.model import SceneModel
from sensors.models import PinholeCamera, ScanningLaser, SensorModel
from sensors.simulate import Simulator

__all__ = ["Prediction", "ModelPredictor", "predict", "coarse_sensor", "pixels_by_feature"]


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


class ModelPredictor:
    """The a priori ``model`` compiled once (``simulator``), cast from any pose."""

    def __init__(self, model: SceneModel):
        self.model = model
        self.simulator = Simulator.from_scene(model)

    def predict(self, sensor: SensorModel, T_world_sensor: np.ndarray, stride: int = 1) -> Prediction:
        return predict(self.simulator, sensor, T_world_sensor, stride)
