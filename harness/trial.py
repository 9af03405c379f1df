"""One trial: simulate the scan, run every method's recognition stages, evaluate them against the truth.

This is the only place where truth and the core meet, and they meet at arm's length: the core receives
a :class:`sensors.range_image.Scan` (and the a priori model), the evaluation receives the core's output
and the :class:`sensors.range_image.ScanTruth` (DESIGN 10.1).
"""

from __future__ import annotations

import threading
import time
import zlib
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evaluation.patches import classification_section, segmentation_section
from harness.suite import TrialSpec
from recognition.describe import DescribeParams, describe
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


_SCENES: OrderedDict[tuple, PreparedScene] = OrderedDict()
_SCENES_LOCK = threading.Lock()
_SCENES_KEPT = 8


def prepare_scene(spec: TrialSpec, cache_dir: Path | None) -> PreparedScene:
    """Perturb the a priori scene and compile it; cached in-process (the runner prepares it before forking the
    trial's process, so trials of one scene share the work) and, as files, in ``cache_dir``."""
    key = (spec.scene_file, spec.perturbation_file, spec.perturbation_seed)
    with _SCENES_LOCK:
        if key in _SCENES:
            _SCENES.move_to_end(key)
            return _SCENES[key]
        prepared = _prepare(spec, cache_dir)
        _SCENES[key] = prepared
        while len(_SCENES) > _SCENES_KEPT:
            _SCENES.popitem(last=False)
        return prepared


def _prepare(spec: TrialSpec, cache_dir: Path | None) -> PreparedScene:
    key = (spec.scene_file, spec.perturbation_file, spec.perturbation_seed)
    apriori = SceneModel.load(spec.scene_file)
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
        if actual_path is not None:
            from harness.store import write_text_atomic

            write_text_atomic(actual_path, actual.to_yaml())
            write_text_atomic(truth_path, truth.to_json())
    return PreparedScene(apriori, actual, truth, Simulator.from_scene(actual))


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


def run_trial(spec: TrialSpec, methods: dict[str, dict[str, Any]], prepared: PreparedScene,
              artifacts_dir: Path | None = None) -> dict[str, Any]:
    """Run one trial on its prepared scene and return its record (plain JSON data).

    Exceptions propagate to the caller (:mod:`harness.execute` records them as failures).
    """
    t_start = time.perf_counter()
    timing: dict[str, float | None] = dict.fromkeys(STAGES)
    config = sensor_for(spec)
    t0 = time.perf_counter()
    views = sample_viewpoints(prepared.simulator, prepared.actual, config.model, 1, viewpoint_rng(spec),
                              ViewpointSpec(min_surfaces=spec.min_view_surfaces, min_pixels=spec.min_view_pixels))
    if not views.viewpoints:
        raise TrialFailure(f"no acceptable viewpoint in {views.attempts} attempts "
                           f"(rejected: {views.rejected})")
    view = views.viewpoints[0]
    rng = np.random.default_rng([spec.suite_seed, spec.index])
    scan, truth = prepared.simulator.simulate(config, view.T_world_sensor, rng)
    timing["sensor"] = time.perf_counter() - t0
    method_records = {}
    shared_segmentation = None
    for name, params in methods.items():
        method_records[name], desc = run_method(name, params, scan, truth, prepared, shared_segmentation)
        shared_segmentation = desc.segmentation
    if artifacts_dir is not None:
        write_artifacts(artifacts_dir, scan, truth)
    timing["total"] = time.perf_counter() - t_start
    return {
        "schema": TRIAL_SCHEMA,
        "trial_id": spec.trial_id,
        "status": "ok",
        "reason": "",
        "spec": spec.to_dict(),
        "view": {"T_world_sensor": view.T_world_sensor.tolist(), "target_feature": view.target_feature,
                 "viewpoint_attempts": views.attempts, "viewpoint_rejection_rate": views.rejection_rate,
                 "valid_fraction": float(np.mean(scan.valid)),
                 "surfaces_seen": int(sum(1 for n in view.surface_pixels.values() if n >= spec.min_view_pixels))},
        "timing_s": timing,
        "methods": method_records,
    }


def method_params(name: str, params: dict[str, Any]) -> DescribeParams:
    """The core's parameters for a suite method (``core``: the ``select`` classifier, ``paper``: the paper's)."""
    classifier = params.get("classifier", "paper" if name == "paper" else "select")
    unknown = set(params) - {"classifier"}
    if unknown:
        raise ValueError(f"method {name!r}: unknown parameter(s) {', '.join(sorted(unknown))}")
    return DescribeParams(classifier=classifier)


def run_method(name: str, params: dict[str, Any], scan: Scan, truth: ScanTruth, prepared: PreparedScene,
               segmentation=None) -> tuple[dict[str, Any], Any]:
    """Run one method's stages on the scan and evaluate each; a stage not built yet is null.

    ``segmentation`` may be shared between methods that differ only after it (``core`` and ``paper``):
    the first method's segmentation is reused, and its time is reported for both.
    """
    timing: dict[str, float | None] = dict.fromkeys(STAGES[1:])
    desc = describe(scan, method_params(name, params), segmentation)
    timing["segmentation"] = desc.timing_s["segmentation"] if segmentation is None else None
    timing["classification"] = desc.timing_s["classification"]
    record = {
        "segmentation": segmentation_section(desc.labels, truth, scan.valid),
        "classification": classification_section(desc, truth, prepared.actual),
        "pose": None,
        "change": None,
        "timing_s": timing,
    }
    return record, desc


def write_artifacts(out: Path, scan: Scan, truth: ScanTruth) -> None:
    from sensors.io import save_labels_png, save_npz, save_shaded_png

    out.mkdir(parents=True, exist_ok=True)
    save_npz(out / "scan.npz", scan, truth, compress=True)
    save_shaded_png(out / "shaded.png", scan)
    save_labels_png(out / "labels.png", truth.surface_id)
