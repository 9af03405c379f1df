"""The report's gallery: re-run a few trials from their records (deterministic, DESIGN 10.14) and draw them.

A run never needs ``--artifacts`` for its report: the scan is simulated again from the trial's spec, its
recorded viewpoint and its seed, exactly as :func:`harness.trial.run_trial` did, and the core describes it
again. Truth and core stay apart: the core's pictures (regions, classification) come from
:func:`recognition.describe.describe` on the :class:`sensors.range_image.Scan` only; the truth pictures
(truth surfaces, truth change map) from the :class:`sensors.range_image.ScanTruth` and the perturbation's
change truth; the "wrong label" marks from the trial record's own evaluation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.metrics import MIN_SCORED_PIXELS
from harness.suite import TrialSpec
from harness.trial import PreparedScene, method_params, prepare_scene, sensor_for
from recognition.describe import SceneDescription, describe
from reports import figures
from reports.document import GalleryTrial
from reports.render import image, worst_trials
from scenes.vocabulary import CHANGE_LABELS
from sensors.range_image import Scan, ScanTruth


@dataclass(frozen=True)
class Rerun:
    """A trial simulated again: its scan and truth, the prepared scene and the core's description."""

    spec: TrialSpec
    scan: Scan
    truth: ScanTruth
    prepared: PreparedScene
    description: SceneDescription


def spec_from_record(record: Mapping[str, Any]) -> TrialSpec:
    """The :class:`TrialSpec` of a trial record (its ``spec`` dict; ``overrides`` copied, numbers as floats)."""
    d = dict(record["spec"])
    d["overrides"] = {str(k): float(v) for k, v in (d.get("overrides") or {}).items()}
    return TrialSpec(**d)


def rerun(record: Mapping[str, Any], methods: Mapping[str, Mapping[str, Any]], cache_dir: Path | None) -> Rerun:
    """Simulate the trial's scan again from its recorded viewpoint and seed, and describe it with the core.

    The viewpoint is the recorded ``view.T_world_sensor`` (so no viewpoint sampling is repeated); the noise
    generator is ``default_rng([suite_seed, index])`` as in :func:`harness.trial.run_trial`.
    """
    spec = spec_from_record(record)
    prepared = prepare_scene(spec, cache_dir)
    config = sensor_for(spec)
    T_world_sensor = np.asarray(record["view"]["T_world_sensor"], dtype=np.float64)
    rng = np.random.default_rng([spec.suite_seed, spec.index])
    scan, truth = prepared.simulator.simulate(config, T_world_sensor, rng)
    desc = describe(scan, method_params("core", dict(methods.get("core", {}))))
    return Rerun(spec, scan, truth, prepared, desc)


def reproduced(record: Mapping[str, Any], desc: SceneDescription) -> bool:
    """Whether the re-run gives the recorded core patches (ids and sizes)."""
    rows = ((record.get("methods") or {}).get("core") or {}).get("classification") or {}
    recorded = sorted((int(p["patch"]), int(p["n_pixels"])) for p in rows.get("patches", []))
    return recorded == sorted((int(p.id), int(p.n_pixels)) for p in desc.patches)


def wrong_label_mask(desc: SceneDescription, patches: Sequence[Mapping[str, Any]]) -> np.ndarray:
    """(H, W) bool: pixels of the scored patches (:data:`evaluation.metrics.MIN_SCORED_PIXELS` or more) whose
    recorded label differs from the truth."""
    wrong_ids = {int(p["patch"]) for p in patches if p.get("n_pixels", 0) >= MIN_SCORED_PIXELS
                 and p["label"] != p["truth"]}
    mask = np.zeros(desc.labels.shape, dtype=bool)
    for p in desc.patches:
        if p.id in wrong_ids:
            mask.flat[p.pixels] = True
    return mask


def truth_change_index(truth: ScanTruth, prepared: PreparedScene) -> np.ndarray:
    """(H, W) index into ``CHANGE_LABELS`` of the truth change label of each pixel's feature (-1: none)."""
    labels = []
    for s in truth.surfaces:
        try:
            lab = prepared.change_truth.feature_label(s.feature_id)
        except KeyError:
            lab = ""
        labels.append(CHANGE_LABELS.index(lab) if lab in CHANGE_LABELS else -1)
    lut = np.asarray(labels + [-1], dtype=np.int64)  # index -1 maps to the trailing -1
    return lut[np.asarray(truth.surface_id)]


def predicted_change_index(truth: ScanTruth, features: Sequence[Mapping[str, Any]]) -> np.ndarray | None:
    """(H, W) index into ``CHANGE_LABELS`` of the core's predicted label per visible feature, when the change
    records name their features (``feature`` key); None otherwise."""
    named = {str(f["feature"]): f.get("predicted") for f in features if f.get("feature") is not None}
    if not named:
        return None
    lut = np.asarray([CHANGE_LABELS.index(named[s.feature_id]) if named.get(s.feature_id) in CHANGE_LABELS else -1
                      for s in truth.surfaces] + [-1], dtype=np.int64)
    return lut[np.asarray(truth.surface_id)]


def estimated_poses(r: Rerun, record_pose: Mapping[str, Any]) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The core's ``T_world_sensor`` before and after ICP: from the pose record when it holds them
    (``initial.T_world_sensor``, ``T_world_sensor``), else by re-running the pose stage (after ICP only)
    through :func:`harness.trial.estimate_pose` when that stage exists. ``(None, None)`` when neither works."""
    after = record_pose.get("T_world_sensor")
    before = (record_pose.get("initial") or {}).get("T_world_sensor")
    if after is None:
        from harness import trial

        if hasattr(trial, "estimate_pose") and hasattr(trial, "TrialContext"):
            out = trial.estimate_pose(trial.TrialContext(r.scan, r.truth, r.prepared), r.description, None)
            after = out[0] if out is not None else None
    return _matrix(before), _matrix(after)


def _matrix(T: Any) -> np.ndarray | None:
    return None if T is None else np.asarray(T, dtype=np.float64)


def model_range(r: Rerun, T_world_sensor: np.ndarray) -> np.ndarray:
    """(H, W) range (metres) of the a priori model cast from ``T_world_sensor`` with the trial's sensor."""
    sensor = sensor_for(r.spec).model
    predictor = getattr(r.prepared, "predictor", None)
    if predictor is not None:
        return predictor.predict(sensor, T_world_sensor).range
    from sensors.simulate import Simulator

    return Simulator.from_scene(r.prepared.apriori).truth_image(sensor, T_world_sensor, check=False)[0]


def registration_residuals(r: Rerun, record_pose: Mapping[str, Any]
                           ) -> tuple[np.ndarray | None, np.ndarray] | None:
    """Measured minus a priori model range with the model cast from the core's estimated pose, before ICP
    (None when unknown) and after; None when there is no estimate to draw."""
    before, after = estimated_poses(r, record_pose)
    if after is None:
        return None
    return (None if before is None else r.scan.range - model_range(r, before)), r.scan.range - model_range(r, after)


def draw(record: Mapping[str, Any], r: Rerun, why: str) -> GalleryTrial:
    """The gallery entry of one re-run trial."""
    from sensors.io import shaded_image

    core = (record.get("methods") or {}).get("core") or {}
    patches = (core.get("classification") or {}).get("patches", [])
    shade = shaded_image(r.scan)
    notes: list[str] = []
    if not reproduced(record, r.description):
        notes.append("The re-run's patches differ from the recorded ones (the code changed since the run?): "
                     "the pictures show the current code, the numbers are the run's.")
    panels = [
        image(figures.shaded_picture(shade), "Cosine-shaded range image (black: no return)."),
        image(figures.region_picture(np.where(r.truth.surface_id >= 0, r.truth.surface_id, -1),
                                     "truth surfaces", number_min_pixels=10**9),
              "Truth surfaces (each in its own colour)."),
        image(figures.region_picture(r.description.labels), "The core's regions, numbered (patch ids of "
              f"{MIN_SCORED_PIXELS} pixels or more) as in the paper's classification table."),
        image(figures.class_overlay_picture(shade, r.description.class_image(), wrong_label_mask(r.description,
                                                                                                 patches)),
              "The core's labels over the shaded image; red stripes: label differs from the truth class."),
    ]
    pose = core.get("pose")
    try:
        residuals = registration_residuals(r, pose) if pose else None
        failure = ""
    except Exception as exc:  # noqa: BLE001 - a picture that cannot be drawn becomes a note
        residuals, failure = None, f"could not be drawn ({type(exc).__name__}: {exc})."
    if residuals is not None:
        before = "before and after ICP" if residuals[0] is not None else "after ICP"
        panels.append(image(figures.registration_picture(*residuals, "registration: measured - model range"),
                            f"Registration: the a priori model cast from the core's estimated pose, {before}.",
                            width_px=640))
    else:
        notes.append("Registration before and after ICP: " + (failure or (
            "not built yet (pose is null in the record)." if not pose else "no pose estimate to draw (the pose "
            "stage gave none for this trial).")))
    panels.append(image(figures.change_picture(shade, truth_change_index(r.truth, r.prepared),
                                               "truth change labels"),
                        "Truth change label of every visible feature (a priori model vs actual scene)."))
    change = core.get("change")
    predicted = predicted_change_index(r.truth, change.get("features", [])) if change else None
    if predicted is not None:
        panels.append(image(figures.change_picture(shade, predicted, "predicted change labels (core)"),
                            "The core's change label of every visible feature."))
    else:
        notes.append("Predicted change map: " + ("not built yet (change is null in the record)." if not change
                     else "the change records do not name their features."))
    return GalleryTrial(str(record["trial_id"]), str(record["spec"].get("group", "")), why, tuple(panels),
                        tuple(notes))


def build_gallery(records: Sequence[Mapping[str, Any]], methods: Mapping[str, Mapping[str, Any]],
                  cache_dir: Path | None, n: int = 3, log=None) -> list[GalleryTrial]:
    """Choose the ``n`` worst trials and draw each (a trial that cannot be re-run gets a note, not an error)."""
    out = []
    for record, _score, why in worst_trials(records, n):
        if log is not None:
            log(f"gallery: re-running {record['trial_id']}")
        try:
            out.append(draw(record, rerun(record, methods, cache_dir), why))
        except Exception as exc:  # noqa: BLE001 - one trial's pictures must not cost the whole report
            out.append(GalleryTrial(str(record["trial_id"]), str(record["spec"].get("group", "")), why, (),
                                    (f"Could not re-run this trial to draw it: {type(exc).__name__}: {exc}",)))
    return out
