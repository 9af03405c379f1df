"""Plug-in methods (DESIGN 11.5): typed stage interfaces, registration by entry point or ``entry:``, the example
package under ``examples/`` run locally and on Dask, plug-in versions in the code identity, and a broken plug-in
recorded as failed trials with a reason naming it, never a crashed run.

The example is made importable by putting its directory on ``sys.path`` (and ``PYTHONPATH``, which the Dask
workers inherit); its installation is stood for by the ``.dist-info`` directory pip would write, made from the
example's own ``pyproject.toml`` (fast, nothing installed into the environment). ``-m slow`` also builds and
installs it for real with pip into a temporary directory.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import inspect
import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import _support
import numpy as np
import pytest
import yaml

import recognition
from harness.execute import _child_record
from harness.methods import ENTRY_POINT_GROUP, PluginError, registered_plugins
from harness.provenance import plugin_versions
from harness.run import RunOptions, run_suite
from harness.suite import load_suite, suite_from_dict
from harness.summary import comparable
from harness.trial import prepare_scene, run_trial
from recognition.interfaces import STAGE_INTERFACES, ChangeDetector, Describer, Localiser, check_stage_result
from recognition.peers import PEERS
from scenes.config import ConfigError

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "harness_plugin_example"
SENSOR = _support.TINY_SENSOR
BROKEN = '''
import recognition


def raises():
    raise RuntimeError("no licence for this method")


def not_a_peer():
    return {"replaces": "change"}


def _dict_change(description, scan, model, T_world_sensor, cov, predictor, options, predicted=None):
    return {"features": {}}


def wrong_type():
    return recognition.Peer("wrong_type", "change", _dict_change, "returns a dict", {})


def _crash(description, scan, model, T_world_sensor, cov, predictor, options, predicted=None):
    return 1 / 0


def crashes():
    return recognition.Peer("crashes", "change", _crash, "raises", {})


def _string_pose(description, scan, model, options, predictor):
    return "a pose"


def bad_pose():
    return recognition.Peer("bad_pose", "pose", _string_pose, "returns a string", {})
'''


def _suite_data(methods: dict, viewpoints: int = 2) -> dict:
    return {"schema": "suite/1", "name": "plug", "seed": 3, "timeout_s": 60, "methods": methods,
            "groups": [{"scene": "mockup", "perturbation": "mockup_perturbation", "perturbation_seeds": [0],
                        "sensor": "tiny_sensor.yaml", "viewpoints": viewpoints, "noise_seeds": [0],
                        "min_view_pixels": 50, "min_view_surfaces": 3}]}


def _suite_file(tmp_path: Path, methods: dict, viewpoints: int = 2) -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    path = tmp_path / "plug.yaml"
    path.write_text(yaml.safe_dump(_suite_data(methods, viewpoints), sort_keys=False))
    return path


def _run(path: Path, out: Path, **kw) -> dict:
    return run_suite(load_suite(str(path)), out, RunOptions(workers=kw.pop("workers", 1), progress=False, **kw),
                     log=open(os.devnull, "w"))


def _records(out: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((out / "trials").glob("*.json"))}


@pytest.fixture()
def example_importable(monkeypatch):
    """The example package importable here and in the Dask workers this test starts."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(EXAMPLE), os.environ.get("PYTHONPATH")) if p))
    importlib.invalidate_caches()


@pytest.fixture()
def example_installed(tmp_path, monkeypatch, example_importable):
    """The example as pip installs it: its distribution's metadata, with the entry points of its pyproject."""
    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]
    info = tmp_path / "site" / f"harness_plugin_example-{project['version']}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n")
    eps = project["entry-points"][ENTRY_POINT_GROUP]
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()))
    (info / "top_level.txt").write_text("harness_plugin_example\n")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    return project


@pytest.fixture(scope="module")
def broken_module(tmp_path_factory):
    d = tmp_path_factory.mktemp("broken")
    (d / "broken_plugins.py").write_text(BROKEN)
    (d / "broken_import.py").write_text("import a_dependency_nobody_installed  # noqa\n\ndef factory():\n    pass\n")
    return d


def _positional(fn) -> int:
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return sum(p.kind in kinds for p in inspect.signature(fn).parameters.values())


def test_the_stage_interfaces_are_the_peers_interfaces(example_importable):
    """Every built-in peer and the example's methods take their stage interface's arguments; results are checked
    against the stage's type."""
    import harness_plugin_example as ex

    assert set(STAGE_INTERFACES) == {"description", "pose", "change"}
    for stage, protocol in STAGE_INTERFACES.items():
        n = _positional(protocol.__call__) - 1  # without self
        runs = [p.run for p in PEERS.values() if p.replaces == stage]
        runs += [f().run for f in (ex.relabel_change, ex.labels_describe) if f().replaces == stage]
        for run in runs:
            assert isinstance(run, protocol)
            inspect.signature(run).bind(*[None] * n)  # accepts the interface's positional arguments
    assert isinstance(ex.detect_relabelled, ChangeDetector) and isinstance(ex.describe_from_labels, Describer)
    assert isinstance(recognition.localise, Localiser)
    assert check_stage_result("change", {"features": {}}) == "returned dict, expected a ChangeResult"
    assert "missing: ok" in check_stage_result("pose", object())


def test_entry_point_discovery_and_a_local_run(example_installed, tmp_path):
    plugins = registered_plugins()
    assert {"relabel_change", "labels_describe"} <= set(plugins)
    suite_path = _suite_file(tmp_path, {"core": {}, "relabel_change": {"min_displacement_m": 0.5}})
    suite = load_suite(str(suite_path))
    spec = suite.specs["relabel_change"]
    assert (spec.kind, spec.stage, spec.entry) == ("plugin", "change", "harness_plugin_example:relabel_change")
    assert spec.distribution == "harness-plugin-example"
    assert plugin_versions(suite.plugins) == (("harness-plugin-example", example_installed["version"]),)

    summary = _run(suite_path, tmp_path / "run")
    assert summary["n_failed"] == 0, summary["failures"]
    assert "relabel_change" in summary["baselines"]
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["code"]["plugins"] == {"harness-plugin-example": "0.1.0"}
    relabelled = 0
    for rec in _records(tmp_path / "run").values():
        assert rec["code"]["plugins"] == {"harness-plugin-example": "0.1.0"}
        core, plug = rec["methods"]["core"], rec["methods"]["relabel_change"]
        assert plug["pose"] == core["pose"] and plug["segmentation"] == core["segmentation"]  # the core's stages
        if core["change"] is not None:
            for a, b in zip(core["change"]["features"], plug["change"]["features"], strict=True):
                relabelled += a["predicted"] == "moved" and b["predicted"] == "unchanged"
    assert relabelled >= 1, "a move under 0.5 m is unchanged for relabel_change"


def test_the_example_runs_by_entry_locally_and_on_dask(example_importable, tmp_path):
    pytest.importorskip("distributed")
    suite_path = _suite_file(tmp_path, {
        "core": {},
        "relabel": {"entry": "harness_plugin_example:relabel_change", "min_displacement_m": 0.5},
        "my_describer": {"entry": "harness_plugin_example:labels_describe", "rule": "paper", "min_pixels": 80}},
        viewpoints=1)
    suite = load_suite(str(suite_path))
    assert suite.specs["my_describer"].stage == "description"
    [(name, version)] = plugin_versions(suite.plugins)
    # no distribution here (or an editable install of it): its sources are hashed
    assert name in ("harness_plugin_example", "harness-plugin-example") and "source " in version, version
    local = _run(suite_path, tmp_path / "local")
    dask = _run(suite_path, tmp_path / "dask", dask_local=1)
    assert local["n_failed"] == dask["n_failed"] == 0, (local["failures"], dask["failures"])
    assert comparable(dask) == comparable(local)
    for rec in _records(tmp_path / "dask").values():
        assert rec["methods"]["my_describer"]["classification"] is not None


@pytest.mark.parametrize("entry, reason", [
    ("broken_plugins:raises", "its factory raised RuntimeError: no licence for this method"),
    ("broken_plugins:not_a_peer", "its factory returned dict, expected a recognition.Peer"),
    ("broken_plugins:wrong_type", "change stage: returned dict, expected a ChangeResult"),
    ("broken_plugins:crashes", "change stage: raised ZeroDivisionError: division by zero"),
    ("broken_plugins:bad_pose", "pose stage: returned str, expected a PoseResult"),
    ("broken_import:factory", "cannot import broken_import: ModuleNotFoundError: No module named "
                              "'a_dependency_nobody_installed'"),
])
def test_a_broken_plugin_is_a_recorded_trial_failure(broken_module, monkeypatch, tmp_path, entry, reason):
    monkeypatch.syspath_prepend(str(broken_module))
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    suite = suite_from_dict(_suite_data({"core": {}, "broken": {"entry": entry}}, 1), str(tmp_path / "s.yaml"),
                            tmp_path)  # read without error: the plug-in's failure is the trials'
    spec = suite.trials[0]
    record = _child_record(spec, suite.plan, prepare_scene(spec, None), None)  # the trial child's recording
    assert record["status"] == "failed"
    assert record["reason"].startswith(f"PluginError: method 'broken' (plug-in {entry})")
    assert reason in record["reason"]
    with pytest.raises(PluginError):
        run_trial(spec, suite.plan, prepare_scene(spec, None))


def test_a_broken_plugin_fails_its_trials_and_the_run_goes_on(broken_module, monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(broken_module))
    path = _suite_file(tmp_path, {"core": {}, "broken": {"entry": "broken_plugins:crashes"}})
    summary = _run(path, tmp_path / "run")
    assert summary["n_trials"] == 2 and summary["n_failed"] == 2
    for rec in _records(tmp_path / "run").values():
        assert rec["status"] == "failed" and "method 'broken'" in rec["reason"] and "ZeroDivisionError" in rec["reason"]


@pytest.mark.parametrize("method, path, message", [
    ({"entry": "harness_plugin_exampel:relabel_change"}, "methods.x.entry",
     "cannot import harness_plugin_exampel: ModuleNotFoundError"),
    ({"entry": "harness_plugin_example:relabel"}, "methods.x.entry", "module harness_plugin_example has no relabel"),
    ({"entry": "harness_plugin_example.relabel_change"}, "methods.x.entry", "expected 'package.module:factory'"),
    ({"entry": "harness_plugin_example:relabel_change", "base": "core"}, "methods.x.entry",
     "give either base"),
    ({"entry": "harness_plugin_example:relabel_change", "min_displacement": 1}, "methods.x",
     "unknown option(s) min_displacement of 'harness_plugin_example:relabel_change' (a change method) "
     "(did you mean min_displacement_m?"),
    ({"entry": "harness_plugin_example:labels_describe", "params": {"segmentation": {"merge_k": 3.0}}},
     "methods.x.params.segmentation", "this method replaces the description stage"),
])
def test_a_wrong_plugin_entry_is_a_config_error(example_importable, tmp_path, method, path, message):
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    with pytest.raises(ConfigError) as info:
        suite_from_dict(_suite_data({"core": {}, "x": method}), "s.yaml", tmp_path)
    assert str(info.value).startswith(f"s.yaml: {path}: ") and message in str(info.value), str(info.value)


def test_plugins_enter_the_configuration_hash(example_installed, tmp_path):
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    a = suite_from_dict(_suite_data({"core": {}}), "s.yaml", tmp_path)
    b = suite_from_dict(_suite_data({"core": {}, "relabel_change": {}}), "s.yaml", tmp_path)
    c = suite_from_dict(_suite_data({"core": {}, "relabel_change": {"min_displacement_m": 0.1}}), "s.yaml", tmp_path)
    assert len({a.config_hash, b.config_hash, c.config_hash}) == 3
    # the factory a registered name stands for is hashed too, not only the name
    b2 = suite_from_dict(_suite_data({"core": {}, "relabel_change": {}}), "s.yaml", tmp_path)
    b2.specs["relabel_change"] = dataclasses.replace(b2.specs["relabel_change"], entry="elsewhere:factory")
    assert b2.config_hash != b.config_hash


def test_the_example_describer_feeds_the_core_classifier(example_importable, tmp_path):
    import harness_plugin_example as ex

    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    suite = suite_from_dict(_suite_data({"core": {}}, 1), "s.yaml", tmp_path)
    spec = suite.trials[0]
    from harness.trial import sensor_for, trial_scan, trial_viewpoints

    prepared = prepare_scene(spec, None)
    view = trial_viewpoints(spec, prepared, sensor_for(spec)).viewpoints[0]
    scan, _ = trial_scan(spec, prepared, sensor_for(spec), view.T_world_sensor)
    desc = ex.describe_from_labels(scan, {"min_pixels": 80})
    assert check_stage_result("description", desc) is None
    sizes = [p.n_pixels for p in desc.patches]
    assert sizes and min(sizes) >= 80 and sizes == sorted(sizes, reverse=True)
    assert {p.label for p in desc.patches} <= {"PLAN", "CYL", "SPH", "CONE", "OTH"}
    assert np.array_equal(np.unique(desc.labels[desc.labels >= 0]), np.arange(len(desc.patches)))


@pytest.mark.slow
def test_the_example_installs_with_pip_and_registers(tmp_path, monkeypatch):
    """The real thing: pip builds the example (setuptools, no network) into a directory that then holds a
    distribution whose entry points the harness finds."""
    setuptools = pytest.importorskip("setuptools")
    if importlib.util.find_spec("wheel") is None and tuple(map(int, setuptools.__version__.split(".")[:2])) < (70, 1):
        pytest.skip(f"setuptools {setuptools.__version__} needs the wheel package to build without network")
    source, target = tmp_path / "src", tmp_path / "site"
    shutil.copytree(EXAMPLE, source)  # (a build writes build/ and *.egg-info beside the sources)
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--disable-pip-version-check", "--target", str(target), str(source)],
                   check=True, timeout=300, capture_output=True)
    monkeypatch.syspath_prepend(str(target))
    plugins = registered_plugins()
    assert plugins["relabel_change"].value == "harness_plugin_example:relabel_change"
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    suite = suite_from_dict(_suite_data({"core": {}, "relabel_change": {}}), "s.yaml", tmp_path)
    assert plugin_versions(suite.plugins) == (("harness-plugin-example", "0.1.0"),)
