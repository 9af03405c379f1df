"""Simulated range sensors: pinhole range camera and scanning laser models, exact ray casting with
``mujoco.mj_multiRay``, a configurable seeded noise model, range images with their truth, and I/O.

The recognition core receives a :class:`Scan` only; :class:`ScanTruth` goes to evaluation (DESIGN 10.1).
"""

from sensors.config import SensorConfig, load_sensor, preset_names
from sensors.models import PinholeCamera, ScanningLaser, SensorModel
from sensors.noise import NoiseModel
from sensors.range_image import FLAG_NAMES, RangeImage, Scan, ScanTruth
from sensors.simulate import SensorPlacementError, Simulator, simulate

__all__ = ["PinholeCamera", "ScanningLaser", "SensorModel", "NoiseModel", "SensorConfig", "load_sensor",
           "preset_names", "Scan", "ScanTruth", "RangeImage", "FLAG_NAMES", "Simulator", "simulate",
           "SensorPlacementError"]
