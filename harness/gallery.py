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
    localise_params: Any = None  # the core's LocaliseParams from the suite (None: the defaults)


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
    core = dict(methods.get("core", {}))
    desc = describe(scan, method_params("core", core))
    return Rerun(spec, scan, truth, prepared, desc, _localise_params(core))


def _localise_params(core: Mapping[str, Any]) -> Any:
    """The core method's localisation parameters as the suite sets them (None where the harness has no
    per-method localisation parameters: the defaults)."""
    from harness import trial

    full = getattr(trial, "method_core_params", None)
    return getattr(full("core", dict(core)), "localise", None) if full is not None else None


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


def localise_again(r: Rerun):
    """The core's localisation of the re-run's description against the a priori model, as
    :func:`harness.trial.estimate_pose` runs it (:class:`recognition.localisation.PoseResult`: the pose before
    and after ICP, ``ok`` and ``reason``)."""
    from recognition.localisation import LocaliseParams, localise

    params = r.localise_params if r.localise_params is not None else LocaliseParams()
    return localise(r.description, r.scan, r.prepared.apriori, params, r.prepared.predictor.simulator)


def estimated_poses(r: Rerun, record_pose: Mapping[str, Any], located=None
                    ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The core's ``T_world_sensor`` before and after ICP: from the pose record when it holds them
    (``initial.T_world_sensor``, ``T_world_sensor``), else from the localisation run again (``located``, or
    :func:`localise_again`). ``(None, None)`` when neither has a pose."""
    after = record_pose.get("T_world_sensor")
    before = (record_pose.get("initial") or {}).get("T_world_sensor")
    if after is None:
        located = located if located is not None else localise_again(r)
        after, before = located.T_world_sensor, located.T_world_sensor_initial
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


def registration_residuals(r: Rerun, record_pose: Mapping[str, Any], located=None
                           ) -> tuple[np.ndarray | None, np.ndarray] | None:
    """Measured minus a priori model range with the model cast from the core's estimated pose, before ICP
    (None when unknown) and after; None when there is no estimate to draw."""
    before, after = estimated_poses(r, record_pose, located)
    if after is None:
        return None
    return (None if before is None else r.scan.range - model_range(r, before)), r.scan.range - model_range(r, after)


def _pose_words(pose: Mapping[str, Any] | None, key: str = "") -> str:
    sec = (pose or {}).get(key) if key else pose
    if not sec or sec.get("rotation_error_deg") is None:
        return ""
    return f"{sec['rotation_error_deg']:.2f} deg, {sec['translation_error_mm']:.1f} mm from the truth"


CAPTIONS = {
    "range": "The range image: distance along each ray in metres (colour bar below; black: no return). Look for "
             "the span of ranges and the holes: grazing faces, shiny parts and the sky give none.",
    "shaded": "Cosine-shaded range image (black: no return). The surfaces as the sensor saw them, noise "
              "included: the paper's Fig. 2.",
    "hk": "H-K curvature classes per pixel, the paper's central step: signs of the mean (H) and Gaussian (K) "
          "curvature beyond their propagated noise; patches grow from connected pieces of one class. Look for "
          "speckle on planes (noise above the threshold) and thin bands along creases.",
    "truth": "Truth surfaces, each in its own colour: what the segmentation should find (Hoover's ground truth).",
    "regions": "The core's regions, each in the colour of the truth surface it mostly covers, so a right "
               "segmentation looks like the truth picture; a lighter or darker shade of one colour is a second "
               "region on that surface (over-segmentation), a colour absent from the truth covers no single "
               "surface. Numbers: the patch ids of the paper's classification table.",
    "classes": "The core's class labels over the shaded image, in the class colours of every table; red stripes: "
               "the label differs from the truth class.",
    "change_truth": "Truth change label of every visible feature (a priori model against the actual scene).",
    "change_core": "The core's change label of every visible feature: compare with the truth change map.",
    "registration": "Registration: the a priori model cast from the core's estimated pose, measured minus model "
                    "range, before ICP (the pose from matched invariants) and after. White means registered; "
                    "a red/blue ramp across a surface is a rotation error, a uniform colour a shift.",
    "scene": "The scene in 3D: the a priori model (grey, dashed) against the actual scene (in its change "
             "colours; missing features red dashed), the measured points, and the sensor's field of view at the "
             "true pose (black) and as estimated before (dotted) and after ICP (dashed).",
}


def draw(record: Mapping[str, Any], r: Rerun, why: str) -> GalleryTrial:
    """The gallery entry of one re-run trial: its pictures, each with a caption saying what to look at."""
    from reports.colours import matched_region_colours
    from reports.scene3d import corner_rays, scene_figure, scene_labels
    from sensors.io import shaded_image

    core = (record.get("methods") or {}).get("core") or {}
    patches = (core.get("classification") or {}).get("patches", [])
    shade = shaded_image(r.scan)
    seg = r.description.segmentation
    truth_ids = np.where(r.truth.surface_id >= 0, r.truth.surface_id, -1)
    notes: list[str] = []
    if not reproduced(record, r.description):
        notes.append("The re-run's patches differ from the recorded ones (the code changed since the run?): "
                     "the pictures show the current code, the numbers are the run's.")
    panels = [
        image(figures.range_picture(r.scan.range), CAPTIONS["range"]),
        image(figures.shaded_picture(shade), CAPTIONS["shaded"]),
        image(figures.hk_picture(seg.hk_class, seg.edges, r.scan.valid), CAPTIONS["hk"]),
        image(figures.region_picture(truth_ids, "truth surfaces", number_min_pixels=10**9,
                                     key="each truth surface in its own colour; black: no surface"),
              CAPTIONS["truth"]),
        image(figures.region_picture(r.description.labels, colours=matched_region_colours(r.description.labels,
                                                                                          truth_ids)),
              CAPTIONS["regions"]),
        image(figures.class_overlay_picture(shade, r.description.class_image(),
                                            wrong_label_mask(r.description, patches)), CAPTIONS["classes"]),
        image(figures.change_picture(shade, truth_change_index(r.truth, r.prepared), "truth change labels"),
              CAPTIONS["change_truth"]),
    ]
    change = core.get("change")
    predicted = predicted_change_index(r.truth, change.get("features", [])) if change else None
    pose = core.get("pose")
    if predicted is not None:
        panels.append(image(figures.change_picture(shade, predicted, "predicted change labels (core)"),
                            CAPTIONS["change_core"]))
    elif not change:
        notes.append("Predicted change map: none, " + ("the pose stage gave no pose to compare the model at."
                                                      if pose else "change detection did not run (no pose record)."))
    else:
        notes.append("Predicted change map: the change records do not name their features.")
    located = None
    poses: dict[str, np.ndarray | None] = {"true": np.asarray(r.truth.T_world_sensor)}
    if pose:
        try:
            if pose.get("T_world_sensor") is None:
                located = localise_again(r)
                if not located.ok:
                    notes.append(f"The re-run's pose is not ok ({located.reason}): the registration and the 3D "
                                 "scene show the pose it would give." if located.T_world_sensor is not None
                                 else f"No pose estimate to draw: {located.reason}.")
            poses["initial"], poses["estimated"] = estimated_poses(r, pose, located)
            residuals = registration_residuals(r, pose, located)
            if residuals is not None:
                subs = (f"before ICP: {_pose_words(pose, 'initial')}", f"after ICP: {_pose_words(pose)}")
                panels.append(image(figures.registration_picture(*residuals, "registration: measured - model "
                                                                 "range", subtitles=subs),
                                    CAPTIONS["registration"], width_px=1320, span=2))
        except Exception as exc:  # noqa: BLE001 - a picture that cannot be drawn becomes a note
            notes.append(f"Registration before and after ICP could not be drawn ({type(exc).__name__}: {exc}).")
    else:
        notes.append("Registration before and after ICP: the record has no pose section.")
    try:
        apriori, actual = r.prepared.apriori.features, r.prepared.actual.features
        T = np.asarray(r.truth.T_world_sensor)
        pts = r.scan.points.reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)] @ T[:3, :3].T + T[:3, 3]
        depth = float((record.get("view") or {}).get("median_range_m") or np.nanmedian(r.scan.range))
        panels.append(image(scene_figure(apriori, actual, scene_labels(apriori, actual,
                                                                       r.prepared.change_truth.feature_label),
                                         poses, corner_rays(r.scan.sensor.ray_directions()), depth, pts),
                            CAPTIONS["scene"], width_px=1320, span=2))
    except Exception as exc:  # noqa: BLE001
        notes.append(f"The 3D scene could not be drawn ({type(exc).__name__}: {exc}).")
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
