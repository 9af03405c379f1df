"""One trial: simulate the scan, run every method's recognition stages, evaluate them against the truth.

This is the only place where truth and the core meet, and they meet at arm's length: the core receives
a :class:`sensors.range_image.Scan` (and the a priori model), the evaluation receives the core's output
and the :class:`sensors.range_image.ScanTruth` (DESIGN 10.1).
"""

from __future__ import annotations

import copy
import functools
import threading
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.change import change_section, kinds_of_features, observable_features
from evaluation.oracles import truth_classification, truth_pairings, truth_segmentation
from evaluation.patches import classification_section, segmentation_section
from evaluation.pose import changed_features, constrained_view, pose_section
from harness.methods import MethodSpec, call_stage, stage_method
from harness.suite import VIEW_DISTANCE_BAND, TrialPlan, TrialSpec
from recognition.change import detect_changes
from recognition.describe import DescribeParams, core_sigma, describe
from recognition.interfaces import CoreParams
from recognition.localisation import LocaliseParams, ModelPredictor, localise
from scenes.families import family_member
from scenes.model import SceneModel
from scenes.perturb import ChangeTruth, PerturbationSpec, perturb
from sensors.config import SensorConfig, load_sensor
from sensors.range_image import Scan, ScanTruth
from sensors.simulate import Simulator
from sensors.viewpoints import ViewpointSpec, sample_viewpoints

TRIAL_SCHEMA = "harness.trial/1"
STAGES = ("sensor", "segmentation", "classification", "matching", "icp", "change")


class TrialFailure(RuntimeError):
    """A trial that cannot be run for a reason worth recording (e.g. no acceptable viewpoint)."""


@dataclass
class PreparedScene:
    """The a priori model, the actual scene, its change truth and the compiled simulator."""

    apriori: SceneModel
    actual: SceneModel
    change_truth: ChangeTruth
    simulator: Simulator
    predictor: ModelPredictor  # the a priori model compiled for prediction (what the core may cast)

    @property
    def model_points(self) -> np.ndarray:
        """Points sampled on the a priori model (for the ADD pose metric), fixed seed."""
        if not hasattr(self, "_model_points"):
            rng = np.random.default_rng(0)
            self._model_points = np.concatenate([f.sample(200, rng)[0] for f in self.apriori.features])
        return self._model_points


_SCENES: OrderedDict[tuple, PreparedScene] = OrderedDict()
_SCENES_LOCK = threading.Lock()
_SCENES_KEPT = 8


def prepare_scene(spec: TrialSpec, cache_dir: Path | None) -> PreparedScene:
    """Perturb the a priori scene and compile it; cached in-process (the runner prepares it before forking the
    trial's process, so trials of one scene share the work) and, as files, in ``cache_dir``."""
    key = spec.prepared_key
    with _SCENES_LOCK:
        if key in _SCENES:
            _SCENES.move_to_end(key)
            return _SCENES[key]
        prepared = _prepare(spec, cache_dir)
        _SCENES[key] = prepared
        while len(_SCENES) > _SCENES_KEPT:
            _SCENES.popitem(last=False)
        return prepared


def apriori_model(spec: TrialSpec, cache_dir: Path | None = None) -> SceneModel:
    """The trial's a priori model: its scene file, or its family member generated from its seed (once per
    run: saved under ``cache_dir/scenes/`` and read back by later processes)."""
    if spec.family is None:
        return SceneModel.load(spec.scene_file)
    path = None
    if cache_dir is not None:
        tag = zlib.crc32(repr(spec.scene_key).encode())
        path = cache_dir / "scenes" / f"{spec.scene}-{tag:08x}.yaml"
        if path.exists():
            return SceneModel.load(path)
    text = family_member(spec.family, spec.scene_seed, spec.family_config).to_yaml()
    if path is not None:
        from harness.store import write_text_atomic

        write_text_atomic(path, text)
    return SceneModel.from_yaml(text)  # read back as later processes will: the same model in every process


def _prepare(spec: TrialSpec, cache_dir: Path | None) -> PreparedScene:
    key = spec.prepared_key
    apriori = apriori_model(spec, cache_dir)
    tag = f"{spec.scene}-{zlib.crc32(repr(key).encode()):08x}"
    actual_path = cache_dir / tag / "actual.yaml" if cache_dir else None
    truth_path = cache_dir / tag / "truth.json" if cache_dir else None
    if actual_path is not None and actual_path.exists() and truth_path.exists():
        actual = SceneModel.load(actual_path)
        truth = ChangeTruth.from_json(truth_path.read_text(encoding="utf-8"))
    else:
        if spec.perturbation_file is None:
            actual, truth = perturb(apriori, PerturbationSpec(moved_probability=0, missing_probability=0,
                                                              altered_probability=0, section_moved_probability=0,
                                                              new_count=(0, 0)), spec.perturbation_seed)
        else:
            actual, truth = perturb(apriori, PerturbationSpec.load(spec.perturbation_file), spec.perturbation_seed)
        actual = actual.rounded()  # the same scene on every machine (SceneModel.rounded)
        if actual_path is not None:
            from harness.store import write_text_atomic

            write_text_atomic(actual_path, actual.to_yaml())
            write_text_atomic(truth_path, truth.to_json())
    return PreparedScene(apriori, actual, truth, Simulator.from_scene(actual), ModelPredictor(apriori))


def sensor_for(spec: TrialSpec) -> SensorConfig:
    """The trial's sensor with the suite's overrides (max range, sweeps) applied."""
    import dataclasses

    config = load_sensor(spec.sensor)
    ov = spec.overrides
    if "max_range" in ov:
        config = config.with_model(dataclasses.replace(config.model, max_range=min(config.model.max_range,
                                                                                     ov["max_range"])))
    if "noise_scale" in ov:
        config = config.with_noise(config.noise.scaled(ov["noise_scale"]))
    if "footprint_rays" in ov:
        config = config.with_noise(config.noise.with_footprint(int(ov["footprint_rays"])))
    return config


def viewpoint_rng(spec: TrialSpec) -> np.random.Generator:
    """Viewpoints depend on the scene, perturbation seed, viewpoint index and sensor, not on the noise seed."""
    key = zlib.crc32(f"{spec.scene}|{Path(spec.sensor).stem}".encode())
    return np.random.default_rng([spec.suite_seed, key, spec.perturbation_seed, spec.viewpoint])


def viewpoint_spec(spec: TrialSpec) -> ViewpointSpec:
    """What the trial's viewpoint must satisfy; a swept ``view_distance`` d fixes its distance band to
    :data:`harness.suite.VIEW_DISTANCE_BAND` times d (otherwise the sensor's own)."""
    d = spec.overrides.get("view_distance")
    band = None if d is None else (VIEW_DISTANCE_BAND[0] * float(d), VIEW_DISTANCE_BAND[1] * float(d))
    return ViewpointSpec(min_surfaces=spec.min_view_surfaces, min_pixels=spec.min_view_pixels, distance_m=band)


def trial_viewpoints(spec: TrialSpec, prepared: PreparedScene, config: SensorConfig):
    """The trial's viewpoint sample (one viewpoint, or none with the rejection counts)."""
    return sample_viewpoints(prepared.simulator, prepared.actual, config.model, 1, viewpoint_rng(spec),
                             viewpoint_spec(spec))


def trial_scan(spec: TrialSpec, prepared: PreparedScene, config: SensorConfig,
               T_world_sensor: np.ndarray) -> tuple[Scan, ScanTruth]:
    """The trial's scan and truth from ``T_world_sensor``, with the trial's noise generator
    ``default_rng([suite_seed, trial index])`` (no method in it: DESIGN 10.4)."""
    return prepared.simulator.simulate(config, T_world_sensor, np.random.default_rng([spec.suite_seed, spec.index]))


def run_trial(spec: TrialSpec, plan: TrialPlan, prepared: PreparedScene,
              artifacts_dir: Path | None = None) -> dict[str, Any]:
    """Run one trial on its prepared scene and return its record (plain JSON data).

    Exceptions propagate to the caller (:mod:`harness.execute` records them as failures).
    """
    t_start = time.perf_counter()
    timing: dict[str, float | None] = dict.fromkeys(STAGES)
    config = sensor_for(spec)
    t0 = time.perf_counter()
    views = trial_viewpoints(spec, prepared, config)
    if not views.viewpoints:
        raise TrialFailure(f"no acceptable viewpoint in {views.attempts} attempts "
                           f"(rejected: {views.rejected})")
    view = views.viewpoints[0]
    scan, truth = trial_scan(spec, prepared, config, view.T_world_sensor)
    timing["sensor"] = time.perf_counter() - t0
    context = TrialContext(scan, truth, prepared)
    specs = plan.method_specs()  # core first: the others reuse what they share with it
    stage_methods = {name: stage_method(ms) for name, ms in specs.items()}  # a broken plug-in fails the trial here
    records = {}
    for name, ms in specs.items():
        peer = stage_methods[name]
        records[name], _ = run_pipeline(context, ms.params, peer=(peer, ms.options) if peer is not None else None,
                                        method=ms)
    method_records = {name: records[name] for name in plan.methods}
    core = specs["core"].params
    core_description = context.description(core.describe)[0] if plan.oracles else None
    oracle_records = {}
    for oracle in plan.oracles:
        oracle_records[oracle], _ = run_pipeline(context, core, oracle=oracle, core=core_description)
    if artifacts_dir is not None:
        write_artifacts(artifacts_dir, scan, truth)
    timing["total"] = time.perf_counter() - t_start
    record = {
        "schema": TRIAL_SCHEMA,
        "trial_id": spec.trial_id,
        "status": "ok",
        "reason": "",
        "spec": spec.to_dict(),
        "view": {"T_world_sensor": view.T_world_sensor.tolist(), "target_feature": view.target_feature,
                 "viewpoint_attempts": views.attempts, "viewpoint_rejection_rate": views.rejection_rate,
                 "valid_fraction": float(np.mean(scan.valid)),
                 "surfaces_seen": int(sum(1 for n in view.surface_pixels.values() if n >= spec.min_view_pixels)),
                 "median_range_m": context.median_range, "constrains_pose": context.constrained,
                 "twin_ambiguous": context.twin_ambiguous},
        "timing_s": timing,
        "methods": method_records,
    }
    if plan.oracles:
        record["oracles"] = oracle_records
    return record


def method_params(name: str, params: dict[str, Any], core: dict[str, Any] | None = None) -> DescribeParams:
    """The core's description parameters for a suite method's mapping (``core``: the ``select`` classifier,
    ``paper``: the paper's; ``params`` applied on top of those of the ``core`` method's mapping ``core``)."""
    return method_core_params(name, params, core).describe


def method_core_params(name: str, params: dict[str, Any], core: dict[str, Any] | None = None) -> CoreParams:
    """All of the core's parameters for a suite method's mapping (see :func:`method_params`)."""
    from harness.methods import method_specs
    from scenes.config import Fields

    methods = {"core": dict(core or {})} if name != "core" else {}
    methods[name] = dict(params or {})
    return method_specs(Fields(methods, "<suite>", "methods"))[name].params


def _key(params: Any) -> Any:
    """A dictionary key for a frozen parameter dataclass (its repr if a field is unhashable)."""
    try:
        hash(params)
        return params
    except TypeError:
        return repr(params)


class TrialContext:
    """One trial's scan, truth and scene, with the truth-side quantities evaluation needs, computed once."""

    def __init__(self, scan: Scan, truth: ScanTruth, prepared: PreparedScene):
        self.scan, self.truth, self.prepared = scan, truth, prepared
        self.median_range = float(np.nanmedian(truth.true_range)) if np.isfinite(truth.true_range).any() else None
        self._apriori_at_truth = None
        self._observable: dict[str, str] | None = None
        # (id(description), LocaliseParams) -> (description, estimate_pose output)
        self.poses: dict[tuple[int, Any], tuple[Any, tuple]] = {}
        self._descriptions: dict[Any, Any] = {}  # DescribeParams -> the core's description
        self._segmentations: dict[Any, Any] = {}  # SegmentationParams -> the core's segmentation
        self._segmentation_sections: dict[int, tuple[np.ndarray, dict[str, Any]]] = {}
        self.object_of = {f.id: o.id for m in (prepared.apriori, prepared.actual) for o in m.objects
                          for f in o.features}
        self.kind_of = kinds_of_features(prepared.apriori)  # altered F1 by kind (change.altered_by_kind)
        self.constrained, self.twin_ambiguous = constrained_view(
            truth, prepared.actual, prepared.apriori, functools.partial(prepared.predictor.predict, scan.sensor),
            changed_features(prepared.change_truth))

    @property
    def apriori_at_truth(self):
        """The a priori model cast from the true pose (observability of missing features)."""
        if self._apriori_at_truth is None:
            self._apriori_at_truth = self.prepared.predictor.predict(self.scan.sensor, self.truth.T_world_sensor)
        return self._apriori_at_truth

    @property
    def observable(self) -> dict[str, str]:
        """Truth label of every feature observable in this trial (the same for every method)."""
        if self._observable is None:
            self._observable = observable_features(self.truth, self.prepared.change_truth, self.apriori_at_truth)
        return self._observable

    def description(self, params: DescribeParams) -> tuple[Any, float | None, float | None]:
        """``(description, segmentation time, classification time)`` of the core with ``params``, computed once
        per trial: a method that shares the parameters reuses it (times None: reported by the first), one that
        shares the segmentation parameters reuses the segmentation (segmentation time None)."""
        key = _key(params)
        if key in self._descriptions:
            return self._descriptions[key], None, None
        segmentation = self._segmentations.get(_key(params.segmentation))
        desc = describe(self.scan, params, segmentation)
        self._descriptions[key] = desc
        self._segmentations.setdefault(_key(params.segmentation), desc.segmentation)
        return (desc, desc.timing_s["segmentation"] if segmentation is None else None,
                desc.timing_s["classification"])

    def segmentation_section(self, labels: np.ndarray) -> dict[str, Any]:
        """The Hoover scores of ``labels``, computed once per label image (methods that share the core's
        segmentation share its scores)."""
        key = id(labels)
        if key not in self._segmentation_sections or self._segmentation_sections[key][0] is not labels:
            self._segmentation_sections[key] = (labels, segmentation_section(labels, self.truth, self.scan.valid))
        return copy.deepcopy(self._segmentation_sections[key][1])


def run_pipeline(ctx: TrialContext, params: CoreParams, oracle: str | None = None, core=None,
                 peer: tuple | None = None, method: MethodSpec | None = None) -> tuple[dict[str, Any], Any]:
    """Run the core's stages on the scan with ``params``, with at most one stage replaced by its oracle or by a
    stage method (``(Peer, options)``; ``method`` its spec), and evaluate each.

    What the stages before the one that differs share with an earlier run of the trial (the description of the
    same describe parameters, the pose of the same description and localise parameters; for oracles, the core's
    description ``core``) is reused: its time is then reported once, by the run that computed it.
    """
    scan, truth, prepared = ctx.scan, ctx.truth, ctx.prepared
    timing: dict[str, float | None] = dict.fromkeys(STAGES[1:])
    replaces = peer[0].replaces if peer is not None else None
    if replaces == "description":
        t0 = time.perf_counter()
        desc = _call(method, peer[0], scan, peer[1])
        timing["segmentation"] = time.perf_counter() - t0  # a primitive detector segments and classifies at once
    elif oracle in ("pose", "pairing") and core is not None:
        desc = core
    elif oracle in ("segmentation", "classification"):
        segmentation = None
        if oracle == "segmentation":
            segmentation = truth_segmentation(scan, truth, core_sigma(scan))
        elif core is not None:
            segmentation = core.segmentation
        desc = describe(scan, params.describe, segmentation)
        timing["segmentation"] = desc.timing_s["segmentation"] if segmentation is None else None
        timing["classification"] = desc.timing_s["classification"]
        if oracle == "classification":
            desc = truth_classification(desc, truth)
    else:
        desc, timing["segmentation"], timing["classification"] = ctx.description(params.describe)
    record: dict[str, Any] = {
        "segmentation": ctx.segmentation_section(desc.labels),
        "classification": classification_section(desc, truth, prepared.actual),
        "pose": None,
        "change": None,
        "timing_s": timing,
    }
    pose_peer = peer if replaces == "pose" else None
    if oracle is None and pose_peer is None:  # the core's localisation of this description: once per trial
        key = (id(desc), _key(params.localise))
        if key in ctx.poses and ctx.poses[key][0] is desc:
            T_est, cov, predicted, pose_record, _ = ctx.poses[key][1]
            pose_record, pose_timing = copy.deepcopy(pose_record), {}  # its time is the first run's
        else:
            found = estimate_pose(ctx, desc, None, params=params.localise)
            ctx.poses[key] = (desc, found)
            T_est, cov, predicted, pose_record, pose_timing = found
    else:
        T_est, cov, predicted, pose_record, pose_timing = estimate_pose(ctx, desc, oracle, pose_peer,
                                                                        params=params.localise, method=method)
    record["pose"] = pose_record
    timing.update(pose_timing)
    if T_est is not None:
        t0 = time.perf_counter()
        if replaces == "change":
            result = _call(method, peer[0], desc, scan, prepared.apriori, T_est, cov, prepared.predictor, peer[1],
                           predicted=predicted)
        else:
            result = detect_changes(desc, scan, prepared.apriori, T_est, cov, predicted=predicted,
                                    predictor=prepared.predictor, params=params.change)
        timing["change"] = time.perf_counter() - t0 - result.timing_s.get("predict", 0.0)
        record["change"] = change_section(result, truth, prepared.change_truth, ctx.apriori_at_truth, ctx.object_of,
                                          observable=ctx.observable, kind_of=ctx.kind_of)
    return record, desc


def _call(method: MethodSpec | None, peer, *args, **kwargs):
    """A stage method's ``run`` (a plug-in's failures and wrong results become :class:`PluginError`)."""
    return call_stage(method, peer, *args, **kwargs) if method is not None else peer.run(*args, **kwargs)


def estimate_pose(ctx: TrialContext, desc, oracle: str | None, peer: tuple | None = None,
                  params: LocaliseParams | None = None, method: MethodSpec | None = None):
    """``(T_world_sensor or None, covariance, predicted image, pose record, timings)``. The ``pose`` oracle
    gives the true pose; ``pairing`` gives the truth correspondences to the pose stage; a registration peer
    (``(Peer, options)``) replaces the core's localisation (``params``, default :class:`LocaliseParams`)."""
    truth = ctx.truth
    if oracle == "pose":
        T = truth.T_world_sensor
        rec = {"rotation_error_deg": 0.0, "translation_error_mm": 0.0, "success": True, "ok": True,
               "constrained": ctx.constrained, "oracle": True, "initial": None}
        return T, np.zeros((6, 6)), None, rec, {}
    if peer is not None:
        result = _call(method, peer[0], desc, ctx.scan, ctx.prepared.apriori, peer[1], ctx.prepared.predictor)
    else:
        pairings = truth_pairings(desc, truth, ctx.prepared.change_truth) if oracle == "pairing" else None
        result = localise(desc, ctx.scan, ctx.prepared.apriori, LocaliseParams() if params is None else params,
                          ctx.prepared.predictor.simulator, pairings=pairings)
    rec = pose_section(result, truth.T_world_sensor, ctx.median_range, ctx.constrained,
                       ctx.prepared.model_points)
    t = result.timing_s
    timing = {"matching": sum(t.get(k, 0.0) for k in ("matching", "pose", "verification")), "icp": t.get("icp")}
    if not result.usable:  # ok, or conditional on one object: change detection judges the rest against it
        return None, None, None, rec, timing
    return result.T_world_sensor, result.cov_T_world_sensor, result.predicted, rec, timing


def write_artifacts(out: Path, scan: Scan, truth: ScanTruth) -> None:
    from sensors.io import save_labels_png, save_npz, save_shaded_png

    out.mkdir(parents=True, exist_ok=True)
    save_npz(out / "scan.npz", scan, truth, compress=True)
    save_shaded_png(out / "shaded.png", scan)
    save_labels_png(out / "labels.png", truth.surface_id)
