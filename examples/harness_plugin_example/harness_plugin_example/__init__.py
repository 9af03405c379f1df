"""Example plug-in methods for landmark-harness (entry-point group ``landmark_harness.methods``).

A plug-in method is a factory ``() -> recognition.Peer``: the stage it replaces (``replaces``), the function that
runs it (``run``, with the signature of that stage's interface in :mod:`recognition.interfaces`), a one-line
summary and its options' defaults. The core runs the other stages.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

import recognition
from recognition.change import object_label

__version__ = "0.1.0"

RELABEL_DEFAULTS = {"min_displacement_m": 0.03, "k_sigma": 4.0}
DESCRIBE_DEFAULTS = {"rule": "select", "min_pixels": 50}  # rule: the core classifier to use


def relabel_change() -> recognition.Peer:
    """The ``change`` stage: the core's change detection, with moves under ``min_displacement_m`` relabelled
    ``unchanged`` (a conservative change report) and the objects' labels recounted."""
    return recognition.Peer("relabel_change", "change", detect_relabelled,
                            "the core's change detection; moves under min_displacement_m count as unchanged",
                            dict(RELABEL_DEFAULTS))


def detect_relabelled(description: recognition.SceneDescription, scan: recognition.Scan,
                      model: recognition.SceneModel, T_world_sensor: np.ndarray, cov_T_world_sensor: np.ndarray | None,
                      predictor: recognition.ModelPredictor, options: Mapping[str, Any] | None,
                      predicted=None) -> recognition.ChangeResult:
    """A :class:`recognition.ChangeDetector`."""
    opts = {**RELABEL_DEFAULTS, **(options or {})}
    result = recognition.detect_changes(description, scan, model, T_world_sensor, cov_T_world_sensor,
                                        predicted=predicted, predictor=predictor,
                                        params=recognition.ChangeParams(k_sigma=float(opts["k_sigma"])))
    features = {}
    for fid, change in result.features.items():
        small = change.displacement_m is not None and change.displacement_m < float(opts["min_displacement_m"])
        if change.label == "moved" and small:
            change = dataclasses.replace(change, label="unchanged", displacement_m=None,
                                         reason=f"moved {1e3 * result.features[fid].displacement_m:.0f} mm, under "
                                                f"{1e3 * float(opts['min_displacement_m']):.0f} mm")
        features[fid] = change
    objects = {obj.id: object_label([features[f.id] for f in obj.features if f.id in features])
               for obj in model.objects}
    return dataclasses.replace(result, features=features, objects=objects)


def labels_describe() -> recognition.Peer:
    """The ``description`` stage: a segmenter of one's own fed to the core's classifier."""
    return recognition.Peer("labels_describe", "description", describe_from_labels,
                            "the core's H-K segmentation without patches under min_pixels, "
                            "through segmentation_from_labels to the core's classifier", dict(DESCRIBE_DEFAULTS))


def my_segmenter(scan: recognition.Scan, min_pixels: int) -> np.ndarray:
    """Stands for any segmenter: an (H, W) label image, -1 for none (here the core's, small patches dropped)."""
    from recognition.describe import core_sigma

    labels = recognition.segment(scan.points, core_sigma(scan)).labels
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    return np.where(np.isin(labels, ids[counts >= min_pixels]), labels, -1)


def describe_from_labels(scan: recognition.Scan, options: Mapping[str, Any] | None) -> recognition.SceneDescription:
    """A :class:`recognition.Describer`."""
    opts = {**DESCRIBE_DEFAULTS, **(options or {})}
    segmentation = recognition.segmentation_from_labels(my_segmenter(scan, int(opts["min_pixels"])), scan)
    return recognition.describe(scan, recognition.DescribeParams(classifier=str(opts["rule"])), segmentation)
