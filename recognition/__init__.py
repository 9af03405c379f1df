"""The recognition core of Fillatreau & Fisher: what a robot makes of a range image, given its sensor model and
the partially correct a priori model (never any ground truth).

The pipeline, by the paper's sections, one subpackage each:

- :mod:`recognition.segmentation` (section 3): H-K segmentation into surface patches;
- :mod:`recognition.classification` (section 3): PLAN / CYL / SPH / CONE / OTH, the paper's rule and the core's
  model selection, over the fits of :mod:`recognition.fitting`; :func:`describe` runs both on a scan;
- :mod:`recognition.localisation` (section 4): matching, pose, verification, ICP: :func:`localise`;
- :mod:`recognition.change` (section 5): :func:`detect_changes`;
- :mod:`recognition.peers`: the baselines behind the same stage interfaces.

Typical use::

    description = describe(scan)
    pose = localise(description, scan, model)
    changes = detect_changes(description, scan, model, pose.T_world_sensor, pose.cov_T_world_sensor,
                             predicted=pose.predicted)
"""

from recognition.change import ChangeParams, ChangeResult, FeatureChange, detect_changes
from recognition.describe import DescribeParams, SceneDescription, ScenePatch, describe
from recognition.localisation import LocaliseParams, PoseResult, localise
from recognition.segmentation import Segmentation

__all__ = [
    "ChangeParams",
    "ChangeResult",
    "DescribeParams",
    "FeatureChange",
    "LocaliseParams",
    "PoseResult",
    "SceneDescription",
    "ScenePatch",
    "Segmentation",
    "describe",
    "detect_changes",
    "localise",
]
