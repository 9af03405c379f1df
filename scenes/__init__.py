"""Scenes: the a priori model (features, objects), YAML files, the factory generator and the mock-up family,
perturbations with ground truth, and MJCF export for MuJoCo."""

from scenes.config import ConfigError
from scenes.features import TRUTH_CLASSES, Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.model import Object, SceneModel

__all__ = ["ConfigError", "TRUTH_CLASSES", "Feature", "Plane", "Cylinder", "Sphere", "Cone", "Torus", "Object",
           "SceneModel"]
