"""The core's stage interfaces and parameters, for methods that replace a stage and for suites that set them
(DESIGN 11.5).

A method of a benchmark suite is the core's pipeline - description (segmentation + classification),
localisation, change detection - with at most one stage replaced. The stages a method can replace are typed
here as :class:`typing.Protocol` classes; an implementation is an ordinary function, registered as a
:class:`recognition.peers.Peer` (``replaces`` names the stage, ``run`` is the function, ``defaults`` its options)
whether it ships with the project (:data:`recognition.peers.PEERS`) or comes from another package (a plug-in,
see :mod:`harness.methods`). The core runs the stages it does not replace, with the method's
:class:`CoreParams`.

=================  ===============================================  ==============================
stage              interface                                        the core's own
=================  ===============================================  ==============================
``description``    :class:`Describer` -> :class:`SceneDescription`   :func:`recognition.describe`
``pose``           :class:`Localiser` -> :class:`PoseResult`         :func:`recognition.localise`
``change``         :class:`ChangeDetector` -> :class:`ChangeResult`  :func:`recognition.detect_changes`
=================  ===============================================  ==============================

``options`` is the method's own mapping from the suite (keys among its ``defaults``; the stage applies its
defaults to what is missing). A stage must return its result type (:func:`check_stage_result`): a harness
records anything else as a failed trial naming the method.

The core's parameters are one value, :class:`CoreParams`; a suite reaches every field of it by the stage names
of :data:`PARAM_STAGES` (``methods.<name>.params.<stage>.<field>``, nested dataclasses as nested mappings).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from recognition.change import ChangeParams, ChangeResult
from recognition.classification import PaperParams, SelectParams
from recognition.describe import DescribeParams, SceneDescription
from recognition.localisation import LocaliseParams, ModelPredictor, PoseResult, Prediction
from scenes.model import SceneModel
from sensors.range_image import Scan

__all__ = ["Describer", "Localiser", "ChangeDetector", "STAGE_INTERFACES", "STAGE_RESULTS", "CoreParams",
           "PARAM_STAGES", "METHOD_FIELDS", "CLASSIFIER_PARAMS", "REPLACED_PARAMS", "stage_default",
           "check_stage_result"]


@runtime_checkable
class Describer(Protocol):
    """The ``description`` stage: segmentation and classification of a scan (sensor frame).

    ``describe(scan, options) -> SceneDescription``; :func:`recognition.segmentation_from_labels` turns a label
    image of one's own segmenter into the core's segmentation, for the core's classifier
    (:func:`recognition.describe` with ``segmentation=``).
    """

    def __call__(self, scan: Scan, options: Mapping[str, Any] | None, /) -> SceneDescription: ...


@runtime_checkable
class Localiser(Protocol):
    """The ``pose`` stage: ``T_world_sensor`` from a description and the a priori model.

    ``localise(description, scan, model, options, predictor) -> PoseResult``; ``predictor`` casts the a priori
    model's range image from a pose (:class:`recognition.localisation.ModelPredictor`, compiled once per scene).
    """

    def __call__(self, description: SceneDescription, scan: Scan, model: SceneModel,
                 options: Mapping[str, Any] | None, predictor: ModelPredictor, /) -> PoseResult: ...


@runtime_checkable
class ChangeDetector(Protocol):
    """The ``change`` stage: labels of the a priori model's features and objects given a registered scan.

    ``detect(description, scan, model, T_world_sensor (4, 4), cov_T_world_sensor (6, 6) or None, predictor,
    options, predicted=None) -> ChangeResult``; ``predicted`` is the model's range image at that pose when the
    pose stage already cast it (DESIGN 10.11).
    """

    def __call__(self, description: SceneDescription, scan: Scan, model: SceneModel, T_world_sensor: np.ndarray,
                 cov_T_world_sensor: np.ndarray | None, predictor: ModelPredictor,
                 options: Mapping[str, Any] | None, /, predicted: Prediction | None = None) -> ChangeResult: ...


#: the interface of each stage a method can replace (the keys are :data:`recognition.peers.STAGES`)
STAGE_INTERFACES: dict[str, type] = {"description": Describer, "pose": Localiser, "change": ChangeDetector}
#: what each stage must return
STAGE_RESULTS: dict[str, type] = {"description": SceneDescription, "pose": PoseResult, "change": ChangeResult}


def check_stage_result(stage: str, result: Any) -> str | None:
    """Why ``result`` is not what stage ``stage`` must return (None when it is).

    ``description`` and ``change`` results must be instances of their types; a ``pose`` result may be any
    object with the attributes of :class:`PoseResult` (``PoseResult``-like).
    """
    expected = STAGE_RESULTS[stage]
    if isinstance(result, expected):
        return None
    if stage == "pose":
        missing = [f.name for f in dataclasses.fields(PoseResult) if not hasattr(result, f.name)]
        if not missing:
            return None
        return (f"returned {type(result).__name__}, expected a {expected.__name__} (or an object with its "
                f"attributes; missing: {', '.join(missing[:6])})")
    return f"returned {type(result).__name__}, expected a {expected.__name__}"


@dataclass(frozen=True)
class CoreParams:
    """The parameters of every stage of the core, as one value.

    Attributes
    ----------
    describe : :func:`recognition.describe` (segmentation, classifier and its parameters).
    localise : :func:`recognition.localise` (matching, verification, ICP).
    change : :func:`recognition.detect_changes`.
    """

    describe: DescribeParams = field(default_factory=DescribeParams)
    localise: LocaliseParams = field(default_factory=LocaliseParams)
    change: ChangeParams = field(default_factory=ChangeParams)


#: The names by which a suite reaches the core's parameters (``methods.<name>.params.<stage>``), each the path
#: of its dataclass inside :class:`CoreParams`: the paper's stages (segmentation, classification, matching,
#: localisation, change) and the rest of the call they belong to (``describe``, ``localise``). A field that has a
#: stage name of its own (``DescribeParams.segmentation``) is reached only by that name; every other field of
#: a stage's dataclass is reached under the stage, nested dataclasses as nested mappings
#: (``localise: {icp: {max_iterations: 30}}``).
PARAM_STAGES: dict[str, tuple[str, ...]] = {
    "segmentation": ("describe", "segmentation"),     # SegmentationParams
    "classify": ("describe", "classifier_params"),    # SelectParams or PaperParams, by the method's classifier
    "describe": ("describe",),                        # DescribeParams (its other fields)
    "match": ("localise", "match"),                   # MatchParams
    "localise": ("localise",),                        # LocaliseParams (verify, icp, icp_screen, ...)
    "change": ("change",),                            # ChangeParams
}
#: fields a suite sets on the method itself, not under ``params`` (``methods.<name>.classifier``)
METHOD_FIELDS: dict[str, tuple[str, ...]] = {"classifier": ("describe", "classifier")}
#: the parameters of each classifier (what ``classify`` holds)
CLASSIFIER_PARAMS: dict[str, type] = {"select": SelectParams, "paper": PaperParams}
#: the parameter stages that a method replacing a stage does not run (so a suite may not set them for it)
REPLACED_PARAMS: dict[str, tuple[str, ...]] = {"description": ("segmentation", "classify", "describe"),
                                               "pose": ("match", "localise"), "change": ("change",)}

_STAGE_DEFAULTS: dict[str, Callable[[CoreParams], Any]] = {
    "classify": lambda core: CLASSIFIER_PARAMS[core.describe.classifier](),
}


def stage_default(stage: str, core: CoreParams) -> Any:
    """The dataclass instance stage ``stage`` starts from in ``core``: its value there, or, where that is None
    (``classifier_params``: the classifier's defaults), the instance it stands for."""
    value: Any = core
    for name in PARAM_STAGES[stage]:
        value = getattr(value, name)
    if value is None and stage in _STAGE_DEFAULTS:
        value = _STAGE_DEFAULTS[stage](core)
    return value
