"""The a priori model's predicted range image at a sensor pose (DESIGN 10.11: cast once per pose
hypothesis, shared by verification, ICP and change detection)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.model import SceneModel
from sensors.models import SensorModel
from sensors.simulate import Simulator


@dataclass(frozen=True)
class PredictedImage:
    """What the a priori model looks like from ``T_world_sensor``.

    Attributes
    ----------
    T_world_sensor : (4, 4) the pose it was cast from.
    range : (H, W) metres along each ray to the model (NaN = no model surface within range).
    surface_id : (H, W) int32 index into ``surface_features`` (-1 = none).
    surface_features : feature id of each model surface (a cylinder's side and caps share one feature).
    surface_classes : truth class of each model surface part (PLAN for a cylinder cap...).
    """

    T_world_sensor: np.ndarray
    range: np.ndarray
    surface_id: np.ndarray
    surface_features: tuple[str, ...]
    surface_classes: tuple[str, ...]

    def feature_pixels(self) -> dict[str, np.ndarray]:
        """Flat pixel indices predicted on each visible model feature."""
        sid = self.surface_id.reshape(-1)
        hit = np.flatnonzero(sid >= 0)
        feats = np.array(self.surface_features, dtype=object)[sid[hit]]
        order = np.argsort(feats, kind="stable")
        names, starts = np.unique(feats[order], return_index=True)
        groups = np.split(hit[order], starts[1:])
        return {str(n): g for n, g in zip(names, groups, strict=True)}


class ModelPredictor:
    """The a priori model compiled once, cast from any pose with any sensor."""

    def __init__(self, model: SceneModel):
        self.model = model
        self.simulator = Simulator.from_scene(model)
        surfaces = self.simulator.surfaces
        self.surface_features = tuple(s.feature_id for s in surfaces)
        self.surface_classes = tuple(s.truth_class for s in surfaces)

    def predict(self, sensor: SensorModel, T_world_sensor: np.ndarray) -> PredictedImage:
        rng, sid = self.simulator.truth_image(sensor, T_world_sensor, check=False)
        return PredictedImage(np.asarray(T_world_sensor, dtype=np.float64), rng, sid, self.surface_features,
                              self.surface_classes)
