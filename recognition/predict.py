"""The a priori model compiled once for prediction: its range image from any pose, with any sensor.

The prediction itself is :class:`recognition.verify.Prediction`, cast once per pose hypothesis and shared
by verification, ICP and change detection (DESIGN 10.11).
"""

from __future__ import annotations

import numpy as np

from recognition.verify import Prediction, predict
from scenes.model import SceneModel
from sensors.models import SensorModel
from sensors.simulate import Simulator


class ModelPredictor:
    """The a priori ``model`` compiled once (``simulator``), cast from any pose."""

    def __init__(self, model: SceneModel):
        self.model = model
        self.simulator = Simulator.from_scene(model)

    def predict(self, sensor: SensorModel, T_world_sensor: np.ndarray, stride: int = 1) -> Prediction:
        return predict(self.simulator, sensor, T_world_sensor, stride)

