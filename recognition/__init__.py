"""The recognition core of Fillatreau & Fisher: what a robot makes of a range image, given its sensor model and
the partially correct a priori model (never any ground truth).

The pipeline, by the paper's sections, one subpackage each:

- :mod:`recognition.segmentation` (section 3): H-K segmentation into surface patches;
- :mod:`recognition.classification` (section 3): PLAN / CYL / SPH / CONE / OTH, the paper's rule and the core's
  model selection, over the fits of :mod:`recognition.fitting`; :func:`describe` runs both on a scan;
- :mod:`recognition.localisation` (section 4): matching, pose, verification, ICP: :func:`localise`;
- :mod:`recognition.change` (section 5): :func:`detect_changes`;
- :mod:`recognition.peers`: the baselines behind the same stage interfaces.

This module is the public API: read a scan (:func:`read_scan`, re-exported from :mod:`sensors.readers`: PCD,
PLY, 16-bit depth PNG, the project's ``.npz``), the a priori model (:class:`SceneModel`), then::

    description = describe(scan)
    pose = localise(description, scan, model)
    changes = detect_changes(description, scan, model, pose.T_world_sensor, pose.cov_T_world_sensor,
                             predicted=pose.predicted)

:func:`segmentation_from_labels` feeds a label image of one's own segmenter to the core's classifier
(``describe(scan, params, segmentation)``); :mod:`recognition.interfaces` types the stages a method can replace
(:class:`Describer`, :class:`Localiser`, :class:`ChangeDetector`, registered as a :class:`Peer`) and gathers the
parameters of every stage in :class:`CoreParams`.
"""

from recognition.change import ChangeParams, ChangeResult, FeatureChange, detect_changes
from recognition.classification import PaperParams, SelectParams
from recognition.describe import DescribeParams, SceneDescription, ScenePatch, describe
from recognition.interfaces import ChangeDetector, CoreParams, Describer, Localiser, check_stage_result
from recognition.labels import segmentation_from_labels
from recognition.localisation import LocaliseParams, MatchParams, ModelPredictor, PoseResult, localise
from recognition.peers import Peer
from recognition.segmentation import Segmentation, SegmentationParams, segment
from scenes.model import SceneModel
from sensors.range_image import Scan
from sensors.readers import load_scan, read_scan

__all__ = [
    "ChangeDetector",
    "ChangeParams",
    "ChangeResult",
    "CoreParams",
    "DescribeParams",
    "Describer",
    "FeatureChange",
    "Localiser",
    "LocaliseParams",
    "MatchParams",
    "ModelPredictor",
    "PaperParams",
    "Peer",
    "PoseResult",
    "Scan",
    "SceneDescription",
    "SceneModel",
    "ScenePatch",
    "Segmentation",
    "SegmentationParams",
    "SelectParams",
    "check_stage_result",
    "describe",
    "detect_changes",
    "load_scan",
    "localise",
    "read_scan",
    "segment",
    "segmentation_from_labels",
]
