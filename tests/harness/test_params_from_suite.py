"""The core's parameters from a suite (``methods.<name>.params.<stage>.<field>``, DESIGN 11.5): every ``*Params``
dataclass reachable by introspection, validated with one-line errors, part of the configuration hash, used by the
trial; two methods that differ only in their parameters scored on the very same scans."""

from __future__ import annotations

import dataclasses
import importlib
import json
import os
import pkgutil
from pathlib import Path

import _support
import pytest
import yaml

import recognition
from harness.cli import main
from harness.params import core_params, params_tree
from harness.run import RunOptions, run_suite
from harness.suite import load_suite, suite_from_dict
from harness.trial import method_params, prepare_scene, run_trial
from recognition.interfaces import CLASSIFIER_PARAMS, PARAM_STAGES, CoreParams
from scenes.config import ConfigError

SENSOR = _support.TINY_SENSOR

#: a value for every stage (the core still runs well with them)
EVERY_STAGE = {
    "segmentation": {"merge_k": 2.5},
    "classify": {"temperature": 1.5},
    "describe": {"min_classify_pixels": 25},
    "match": {"max_nodes": 3000},
    "localise": {"max_verify": 5, "icp": {"max_iterations": 25}},
    "change": {"k_sigma": 3.5},
}


def _suite(tmp_path: Path, methods: dict, viewpoints: int = 1, name: str = "tiny") -> Path:
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    data = {"schema": "suite/1", "name": name, "seed": 3, "timeout_s": 60, "methods": methods,
            "groups": [{"scene": "mockup", "perturbation": "mockup_perturbation", "perturbation_seeds": [0],
                        "sensor": "tiny_sensor.yaml", "viewpoints": viewpoints, "noise_seeds": [0],
                        "min_view_pixels": 50, "min_view_surfaces": 3}]}
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _run(path: Path, out: Path, **kw) -> dict:
    return run_suite(load_suite(str(path)), out, RunOptions(workers=kw.pop("workers", 1), progress=False, **kw),
                     log=open(os.devnull, "w"))


def _records(out: Path) -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in sorted((out / "trials").glob("*.json"))}


def _params_classes() -> set[type]:
    """Every ``*Params`` dataclass of the core (its peers' options are dictionaries, not these)."""
    found = set()
    for info in pkgutil.walk_packages(recognition.__path__, "recognition."):
        if info.name.startswith("recognition.peers"):
            continue
        module = importlib.import_module(info.name)
        for obj in vars(module).values():
            if (isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__name__.endswith("Params")
                    and obj.__module__ == info.name):
                found.add(obj)
    return found


def _reachable() -> set[type]:
    """The dataclasses a suite's ``params`` reaches: from CoreParams down, and every classifier's."""
    seen: set[type] = set()
    todo = [CoreParams(), *(cls() for cls in CLASSIFIER_PARAMS.values())]
    while todo:
        obj = todo.pop()
        if type(obj) in seen:
            continue
        seen.add(type(obj))
        todo += [v for f in dataclasses.fields(obj) if dataclasses.is_dataclass(v := getattr(obj, f.name))]
    return seen


def test_every_params_dataclass_of_the_core_is_reachable_from_a_suite():
    missing = {c.__qualname__ for c in _params_classes() - _reachable()}
    assert not missing, f"*Params not reachable from methods.<name>.params (nest them in CoreParams' tree): {missing}"
    assert set(PARAM_STAGES) == {"segmentation", "classify", "describe", "match", "localise", "change"}


@pytest.mark.parametrize("classifier", ["select", "paper"])
def test_every_field_is_reachable_by_its_documented_name(classifier):
    """The whole tree of fields, with their defaults, through YAML and back: the defaults again (so every field
    of every stage, found by introspection, is accepted under its name)."""
    tree = yaml.safe_load(yaml.safe_dump(params_tree(CoreParams(describe=recognition.DescribeParams(
        classifier=classifier)))))
    got = core_params(tree, classifier)
    default = CoreParams(describe=recognition.DescribeParams(classifier=classifier))
    assert got.describe.classifier_params == CLASSIFIER_PARAMS[classifier]()
    assert dataclasses.replace(got.describe, classifier_params=None) == default.describe
    assert (got.localise, got.change) == (default.localise, default.change)
    assert "merge_k" in tree["segmentation"] and "max_iterations" in tree["localise"]["icp"]


def test_params_build_the_stages_dataclasses():
    p = core_params(EVERY_STAGE, "select")
    assert p.describe.segmentation.merge_k == 2.5 and isinstance(p.describe.segmentation.merge_k, float)
    assert p.describe.classifier_params == recognition.SelectParams(temperature=1.5)
    assert p.describe.min_classify_pixels == 25
    assert p.localise.match.max_nodes == 3000
    # nested defaults start from the enclosing dataclass's value, not the nested class's own defaults
    assert p.localise.match.max_hypotheses == recognition.LocaliseParams().match.max_hypotheses
    assert p.localise.icp.max_iterations == 25 and p.localise.icp_screen == recognition.LocaliseParams().icp_screen
    assert p.localise.max_verify == 5 and p.change.k_sigma == 3.5
    assert core_params({"segmentation": {"merge_k": 3}}, "paper").describe.classifier == "paper"
    # the gallery's and the benches' way in
    assert method_params("core", {"params": {"segmentation": {"merge_k": 4}}}).segmentation.merge_k == 4.0


def test_a_suite_with_params_for_every_stage_runs_and_has_another_hash(tmp_path, monkeypatch):
    plain = _suite(tmp_path / "a", {"core": {"classifier": "select"}})
    tuned = _suite(tmp_path / "b", {"core": {"classifier": "select", "params": EVERY_STAGE}})
    assert load_suite(str(plain)).config_hash != load_suite(str(tuned)).config_hash
    summary = _run(tuned, tmp_path / "run")
    assert summary["n_failed"] == 0, summary["failures"]
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["suite_config"]["methods"]["core"]["params"] == EVERY_STAGE
    assert run["config_hash"] == load_suite(str(tuned)).config_hash

    # and the parameters reach the stages (the trial run in this process, its stages spied on)
    import harness.trial as trial

    seen = {}

    def spy(name, fn, pick):
        def wrapper(*args, **kwargs):
            seen[name] = pick(args, kwargs)
            return fn(*args, **kwargs)
        monkeypatch.setattr(trial, name, wrapper)

    spy("describe", trial.describe, lambda a, k: a[1])
    spy("localise", trial.localise, lambda a, k: a[3])
    spy("detect_changes", trial.detect_changes, lambda a, k: k["params"])
    suite = load_suite(str(tuned))
    spec = suite.trials[0]
    record = run_trial(spec, suite.plan, prepare_scene(spec, None))
    assert record["methods"]["core"]["change"] is not None
    assert seen["describe"] == core_params(EVERY_STAGE).describe
    assert seen["localise"] == core_params(EVERY_STAGE).localise
    assert seen["detect_changes"] == recognition.ChangeParams(k_sigma=3.5)


def test_two_methods_differing_only_in_params_run_on_the_same_scans(tmp_path):
    """core against a variant with another merge threshold (segmentation) and one with another change threshold
    (its description and pose are the core's, reused): one run, the same views and scans; the core's figures
    are those of a run without the variants."""
    alone = _suite(tmp_path / "a", {"core": {}}, viewpoints=2)
    ab = _suite(tmp_path / "b", {"core": {}, "core_merge50": {"base": "core", "params": {"segmentation": {
        "merge_k": 50.0}}}, "core_k2": {"base": "core", "params": {"change": {"k_sigma": 2.0}}}}, viewpoints=2)
    s_alone, s_ab = _run(alone, tmp_path / "ra"), _run(ab, tmp_path / "rb")
    assert s_alone["n_failed"] == s_ab["n_failed"] == 0, s_ab["failures"]
    assert set(s_ab["baselines"]) == {"core_merge50", "core_k2"}
    ra, rb = _records(tmp_path / "ra"), _records(tmp_path / "rb")
    assert ra.keys() == rb.keys() and len(rb) == 2
    differ = 0
    for tid, rec in rb.items():
        assert rec["view"] == ra[tid]["view"]  # the same viewpoint and scan (valid fraction, ranges) for all
        core, merged, k2 = (rec["methods"][m] for m in ("core", "core_merge50", "core_k2"))
        strip = {k: v for k, v in core.items() if k != "timing_s"}
        assert strip == {k: v for k, v in ra[tid]["methods"]["core"].items() if k != "timing_s"}
        differ += merged["segmentation"] != core["segmentation"]
        # core_k2 shares the core's description and pose: the same figures, computed once (times None)
        assert k2["segmentation"] == core["segmentation"] and k2["pose"] == core["pose"]
        assert all(k2["timing_s"][s] is None for s in ("segmentation", "classification", "matching", "icp"))
        assert (k2["change"] is None) == (core["change"] is None)
    assert differ >= 1, "merge_k 50 should merge some surfaces of these views"


def test_methods_inherit_the_core_params_and_paper_keeps_its_classifier(tmp_path):
    suite = load_suite(str(_suite(tmp_path, {
        "core": {"params": {"segmentation": {"merge_k": 3.0}, "classify": {"temperature": 2.0}}},
        "paper": {},
        "variant": {"base": "core", "params": {"change": {"k_sigma": 2.0}}},
        "paper_soft": {"base": "paper", "params": {"classify": {"zero_rule": "soft"}}},
        "diff_change": {"k_sigma": 3.0}})))
    s = suite.specs
    assert [m for m in suite.plan.method_specs()][0] == "core"
    assert s["paper"].params.describe.classifier == "paper"
    assert s["paper"].params.describe.segmentation.merge_k == 3.0  # shares the core's segmentation
    assert s["paper"].params.describe.classifier_params is None  # the select classifier's are not inherited
    assert s["variant"].params.describe == s["core"].params.describe
    assert s["variant"].params.change.k_sigma == 2.0 and s["core"].params.change.k_sigma == 4.0
    assert s["paper_soft"].params.describe.classifier_params == recognition.PaperParams(zero_rule="soft")
    assert s["diff_change"].kind == "peer" and s["diff_change"].options == {"k_sigma": 3.0}
    assert s["diff_change"].params.describe == s["core"].params.describe


@pytest.mark.parametrize("methods, path, message", [
    ({"core": {"segmentation": {"merge_k": 4.0}}}, "methods.core",
     "unknown key(s) segmentation (the core's parameters go under params: {segmentation: ...})"),
    ({"core": {"params": {"segmentation": {"merge_kk": 4.0}}}}, "methods.core.params.segmentation",
     "unknown key(s) merge_kk of SegmentationParams (did you mean merge_k? known: "),
    ({"core": {"params": {"segmentaton": {}}}}, "methods.core.params",
     "unknown stage(s) segmentaton (did you mean segmentation? known: change, classify, describe, localise, "
     "match, segmentation)"),
    ({"core": {"params": {"segmentation": {"merge_k": "big"}}}}, "methods.core.params.segmentation.merge_k",
     "expected a number, got 'big'"),
    ({"core": {"params": {"localise": {"icp": {"max_iterations": 2.5}}}}},
     "methods.core.params.localise.icp.max_iterations", "expected an integer, got 2.5"),
    ({"core": {"params": {"localise": {"use_icp": "yes"}}}}, "methods.core.params.localise.use_icp",
     "expected true or false"),
    ({"core": {"params": {"segmentation": {"merge_k": -1}}}}, "methods.core.params.segmentation.merge_k",
     "merge_k must be"),  # the dataclass's own __post_init__ check, one line naming the field
    ({"core": {"params": {"change": {"k_sigma": 0}}}}, "methods.core.params.change.k_sigma", "k_sigma must be > 0"),
    ({"core": {"params": {"classify": {"margin": 0.3}}}}, "methods.core.params.classify",
     "unknown key(s) margin of SelectParams"),
    ({"core": {"params": {"localise": {"match": {}}}}}, "methods.core.params.localise",
     "unknown key(s) match of LocaliseParams"),
    ({"core": {"params": {"describe": {"classifier": "paper"}}}}, "methods.core.params.describe",
     "unknown key(s) classifier of DescribeParams"),
    ({"core": {"params": [1]}}, "methods.core.params", "expected a mapping of stages"),
    ({"core": {}, "core_k4": {"params": {}}}, "methods.core_k4",
     "unknown method (known: core, paper"),
    ({"core": {}, "mine": {"base": "core_k4"}}, "methods.mine.base", "unknown method 'core_k4'"),
    ({"core": {}, "diff_change": {"params": {"change": {"k_sigma": 3.0}}}}, "methods.diff_change.params.change",
     "this method replaces the change stage"),
    ({"core": {}, "diff_change": {"k_sigmaa": 3.0}}, "methods.diff_change",
     "unknown option(s) k_sigmaa of 'diff_change' (a change method) (did you mean k_sigma?"),
    ({"paper": {}}, "methods", "the suite must run the 'core' method"),
])
def test_bad_params_give_one_line_naming_the_field(tmp_path, methods, path, message):
    data = yaml.safe_load(_suite(tmp_path, {"core": {}}).read_text())
    data["methods"] = methods
    with pytest.raises(ConfigError) as info:
        suite_from_dict(data, "suite.yaml", base=tmp_path)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"suite.yaml: {path}: "), text
    assert message in text, text


def test_the_cli_says_it_in_one_line_with_exit_code_2(tmp_path, capsys):
    path = _suite(tmp_path, {"core": {"params": {"segmentation": {"merge_kk": 4.0}}}})
    assert main(["bench", "--suite", str(path), "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "methods.core.params.segmentation: unknown key(s) merge_kk" in err
    assert "merge_k" in err.split("known:")[1] and "window" in err.split("known:")[1]
