"""Suites over scene families, sweeps that run end to end, and the exit code of a run with failed trials."""

import json
import os

import pytest

from harness.cli import main
from harness.commands.bench import EXIT_TRIALS_FAILED
from harness.run import RunOptions, run_suite
from harness.suite import load_suite, suite_from_dict
from harness.trial import apriori_model, prepare_scene, sensor_for, viewpoint_spec
from scenes import ConfigError
from scenes.families import family_member
from sensors.config import load_sensor

SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise:
  range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
  footprint: {rays: 2, radius_px: 0.5, min_return_fraction: 0.5, mixed_threshold_sigma: 3}
"""


def _suite(groups, **top):
    return suite_from_dict({"schema": "suite/1", "name": "t", "seed": 5, "groups": groups, **top})


FACTORY = {"family": "factory", "scene_seeds": {"start": 1000, "count": 3},
           "perturbation": "factory_bay_perturbation", "perturbation_seeds": [0, 1], "sensor": "factory_scanner",
           "viewpoints": 1}


def test_a_family_group_expands_to_one_scene_per_seed_named_in_the_trial_ids():
    suite = _suite([FACTORY])
    assert len(suite.trials) == 6
    assert {t.scene for t in suite.trials} == {"factory-s1000", "factory-s1001", "factory-s1002"}
    assert suite.trials[0].trial_id == "factory-s1000-p0-v0-factory_scanner-n0"
    assert {t.group for t in suite.trials} == {"factory/factory_scanner"}
    listed = _suite([{**FACTORY, "scene_seeds": [1000, 1001, 1002]}])
    assert [t.trial_id for t in listed.trials] == [t.trial_id for t in suite.trials]


def test_the_family_config_enters_the_configuration_hash(tmp_path):
    from scenes.generator import DATA_DIR

    other = tmp_path / "gen.yaml"
    other.write_text((DATA_DIR / "factory_generator.yaml").read_text().replace("count: 4", "count: 3"))
    base = _suite([FACTORY]).config_hash
    assert _suite([FACTORY]).config_hash == base
    changed = _suite([{**FACTORY, "family_config": str(other)}])
    assert changed.config_hash != base
    assert changed.trials[0].family_config == str(other.resolve())


@pytest.mark.parametrize("change, message", [
    ({"scene": "mockup"}, "give either scene"),
    ({"family": "castle"}, "family: must be one of factory, mockup"),
    ({"scene_seeds": None}, "a family needs its scene seeds"),
    ({"scene_seeds": {"start": 3}}, "scene_seeds.count: missing required key"),
    ({"scene_seeds": {"start": 3, "count": 2, "step": 2}}, "unknown"),
    ({"scene_seeds": [1, 1]}, "distinct"),
    ({"family_config": "no_such_generator"}, "family_config: no shipped config named"),
])
def test_family_group_errors_name_the_field(change, message):
    group = {k: v for k, v in {**FACTORY, **change}.items() if v is not None}
    with pytest.raises(ConfigError, match=message):
        _suite([group])


def test_a_generated_scene_is_made_once_and_read_back_identically(tmp_path):
    spec = _suite([FACTORY]).trials[0]
    first = apriori_model(spec, tmp_path)
    saved = list((tmp_path / "scenes").glob("factory-s1000-*.yaml"))
    assert len(saved) == 1
    assert apriori_model(spec, tmp_path).to_yaml() == first.to_yaml() == family_member("factory", 1000).to_yaml()
    assert apriori_model(spec).to_yaml() == first.to_yaml()  # no cache: the same model


def test_noise_scale_scales_sigma_and_leaves_the_rest():
    noise = load_sensor("factory_scanner").noise
    scaled = noise.scaled(1.5)
    assert float(scaled.sigma(7.0, 0.6)) == pytest.approx(1.5 * float(noise.sigma(7.0, 0.6)), rel=1e-12)
    assert scaled.quantisation_step == noise.quantisation_step and scaled.footprint == noise.footprint
    with pytest.raises(ValueError, match="noise scale must be"):
        noise.scaled(0.0)


def test_every_sweepable_parameter_runs_end_to_end(tmp_path):
    from harness.suite import SWEEPABLE

    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    sweeps = {"noise_scale": [0.5, 2.0], "footprint_rays": [1, 3], "max_range": [2.0], "view_distance": [1.2]}
    assert set(sweeps) == set(SWEEPABLE)  # a new sweepable parameter needs its end-to-end run here
    groups = [{"scene": "mockup", "label": f"m-{key}", "perturbation": "mockup_perturbation", "sensor":
               "tiny_sensor.yaml", "viewpoints": 1, "min_view_pixels": 50, "min_view_surfaces": 3,
               "sweep": {key: values}} for key, values in sweeps.items()]
    path = tmp_path / "sweeps.yaml"
    path.write_text(json.dumps({"schema": "suite/1", "name": "sweeps", "seed": 3, "methods": {"core": {}},
                                "groups": groups}))
    suite = load_suite(str(path))
    configs = {t.trial_id: sensor_for(t) for t in suite.trials}
    base = load_sensor(str(tmp_path / "tiny_sensor.yaml"))
    by_value = {next(iter(t.overrides.items())): configs[t.trial_id] for t in suite.trials}
    assert by_value["noise_scale", 2.0].noise.s0_m == pytest.approx(2 * base.noise.s0_m)
    assert by_value["footprint_rays", 3].noise.footprint_rays == 3
    assert by_value["max_range", 2.0].model.max_range == 2.0
    far = next(t for t in suite.trials if "view_distance" in t.overrides)
    assert viewpoint_spec(far).distance_m == pytest.approx((1.08, 1.32))  # +-10 % of 1.2 m
    assert viewpoint_spec(suite.trials[0]).distance_m is None  # the sensor's own band
    summary = run_suite(suite, tmp_path / "run", RunOptions(workers=2, progress=False), log=open(os.devnull, "w"))
    assert summary["n_failed"] == 0, summary["failures"]
    assert set(summary["groups"]) == {"m-noise_scale[noise_scale=0.5]", "m-noise_scale[noise_scale=2]",
                                      "m-footprint_rays[footprint_rays=1]", "m-footprint_rays[footprint_rays=3]",
                                      "m-max_range[max_range=2]", "m-view_distance[view_distance=1.2]"}
    assert all(g["segmentation"] is not None for g in summary["groups"].values())


TWO_TRIALS = """
schema: suite/1
name: two
seed: 3
methods: {core: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    sensor: tiny_sensor.yaml
    viewpoints: 2
    min_view_pixels: 50
    min_view_surfaces: 3
"""


def test_a_run_with_a_failed_trial_exits_with_its_code_after_writing_everything(tmp_path, monkeypatch, capsys):
    import harness.trial as trial

    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    (tmp_path / "two.yaml").write_text(TWO_TRIALS)
    real = trial.run_trial

    def faulty(spec, *args, **kw):
        if spec.viewpoint == 1:
            raise RuntimeError("injected failure")
        return real(spec, *args, **kw)

    monkeypatch.setattr(trial, "run_trial", faulty)
    args = ["bench", "--suite", str(tmp_path / "two.yaml"), "--workers", "1", "--progress", "log"]
    assert main([*args, "--out", str(tmp_path / "a")]) == EXIT_TRIALS_FAILED
    err = capsys.readouterr().err
    assert "1 trial(s) failed" in err and "--allow-failures" in err
    assert (tmp_path / "a" / "summary.json").exists() and (tmp_path / "a" / "report.html").exists()
    assert len(list((tmp_path / "a" / "trials").glob("*.json"))) == 2
    assert main([*args, "--out", str(tmp_path / "b"), "--no-report", "--allow-failures"]) == 0


def test_a_stage_with_nothing_to_show_says_why():
    from reports.render import why_no_figure as why_missing

    failed = {"n_trials": 2, "n_failed": 2, "failures": [{"trial_id": "t", "reason": "no acceptable viewpoint"}]}
    assert why_missing(failed, "pose") == "every trial failed: no acceptable viewpoint"
    unconstrained = {"n_trials": 2, "n_failed": 0, "failures": [], "pose": {"n_constrained": 0}}
    assert why_missing(unconstrained, "pose") == "no trial constrained 6 DOF"
    assert "needs one" in why_missing(unconstrained, "change")


def test_a_prepared_family_scene_is_perturbed(tmp_path):
    spec = _suite([FACTORY]).trials[0]
    prepared = prepare_scene(spec, tmp_path)
    assert prepared.apriori.name == "factory-s1000"
    assert prepared.actual.to_yaml() != prepared.apriori.to_yaml()


def test_dask_batches_keep_the_trials_of_one_scene_together_in_order():
    from harness.execute import scene_batches

    suite = _suite([{**FACTORY, "viewpoints": 3}])  # 3 scenes x 2 perturbation seeds x 3 viewpoints
    batches = scene_batches(list(suite.trials), size=2)
    assert [len(b) for b in batches] == [2, 1] * 6
    assert [t.trial_id for b in batches for t in b] == [t.trial_id for t in suite.trials]
    for b in batches:
        assert len({(t.scene, t.perturbation_seed) for t in b}) == 1


def test_scene_generate_writes_the_member_a_suite_uses(tmp_path):
    out = tmp_path / "m.yaml"
    assert main(["scene", "generate", "--family", "factory", "--seed", "1000", "--out", str(out)]) == 0
    assert out.read_text() == family_member("factory", 1000).to_yaml()
    assert main(["scene", "generate", "--family", "factory", "--mockup", "--out", str(out)]) == 2
