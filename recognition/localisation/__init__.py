"""Localisation (the paper's section 4): the sensor's pose in the a priori model's frame from a scene
description, by interpretation-tree matching of patches to model features (:mod:`.matching`,
:mod:`.interpretation_tree`), closed-form poses (:mod:`.pose`), verification against the model's predicted range
image (:mod:`.prediction`, :mod:`.verification`) and ICP refinement (:mod:`.icp`); :func:`localise`
(:mod:`.localise`) runs them in one call.
"""

from .icp import IcpParams, IcpResult, icp_refine, model_normals
from .interpretation_tree import Hypothesis, MatchResult, given_match, match
from .localise import LocaliseParams, PoseAlternative, PoseResult, agreement_separation, localise, overlap_pairings
from .matching import MatchParams, ModelElements, SceneItem, model_elements, scene_items
from .pose import (
    AxisPair,
    Pair,
    PlanePair,
    PointPair,
    PoseEstimate,
    apply_left,
    estimate_pose,
    exp_so3,
    free_dof_of,
    log_so3,
    pose_hypotheses,
    residuals,
)
from .prediction import ModelPredictor, Prediction, coarse_sensor, pixels_by_feature, predict
from .verification import VerifyParams, agreement, soft_agreement

__all__ = [
    "AxisPair", "Hypothesis", "IcpParams", "IcpResult", "LocaliseParams", "MatchParams", "MatchResult",
    "ModelElements", "ModelPredictor", "Pair", "PlanePair", "PointPair", "PoseAlternative", "PoseEstimate",
    "PoseResult", "Prediction", "SceneItem", "VerifyParams", "agreement", "agreement_separation", "apply_left",
    "coarse_sensor", "estimate_pose", "exp_so3", "free_dof_of", "given_match", "icp_refine", "localise",
    "log_so3", "match", "model_elements", "model_normals", "overlap_pairings", "pixels_by_feature",
    "pose_hypotheses", "predict", "residuals", "scene_items", "soft_agreement",
]
