"""Hostile configuration inputs: every public config entry point answers with a ConfigError naming the source
(and the field), or a valid object; never a hang, a traceback from deep inside, or an unsafe YAML load.

Entry points: scenes (``SceneModel.from_yaml`` / ``load``), generator configs, perturbation specs, suites
(``suite_from_dict`` / ``load_suite``) and sensors (``sensor_from_yaml``). Documents are attacked three ways:
random YAML text, random plain-data trees in place of the document, and one hostile value (wrong type, NaN,
inf, absurd size, deep nesting, an alias bomb) or an unknown key planted at a random place of a valid shipped
document.
"""

from __future__ import annotations

import copy
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from harness.suite import MAX_TRIALS, load_suite, suite_from_dict
from scenes.config import ConfigError, dump_yaml, load_yaml, parse_yaml
from scenes.generator import DATA_DIR, GeneratorConfig
from scenes.model import SceneModel
from scenes.perturb import PerturbationSpec
from sensors.config import PRESET_DIR, sensor_from_yaml

ROOT = Path(__file__).resolve().parents[2]
SUITE_DIR = ROOT / "harness" / "suites"
SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])

#: A YAML "billion laughs": a few hundred bytes whose aliases expand to 10^9 shared list elements.
ALIAS_BOMB = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"a{i + 1}: &a{i + 1} [{', '.join([f'*a{i}'] * 10)}]\n" for i in range(8))


def _scene(data: Any) -> Any:
    return SceneModel.from_yaml(dump_yaml(data), "hostile_scene.yaml")


def _suite(data: Any) -> Any:
    return suite_from_dict(data, "hostile_suite.yaml", base=SUITE_DIR)


def _sensor(data: Any) -> Any:
    return sensor_from_yaml(dump_yaml(data), "hostile_sensor.yaml")


#: entry point name -> (parse plain data, the source name it must report, a valid shipped document)
ENTRY_POINTS: dict[str, tuple[Callable[[Any], Any], str, Any]] = {
    "scene": (_scene, "hostile_scene.yaml", load_yaml(DATA_DIR / "mockup.yaml")),
    "generator": (lambda d: GeneratorConfig.from_dict(d, "hostile_generator.yaml"), "hostile_generator.yaml",
                  load_yaml(DATA_DIR / "factory_generator.yaml")),
    "perturbation": (lambda d: PerturbationSpec.from_dict(d, "hostile_perturbation.yaml"),
                     "hostile_perturbation.yaml", load_yaml(DATA_DIR / "factory_bay_perturbation.yaml")),
    "suite": (_suite, "hostile_suite.yaml", load_yaml(SUITE_DIR / "smoke.yaml")),
    "sensor": (_sensor, "hostile_sensor.yaml", load_yaml(PRESET_DIR / "mockup_laser.yaml")),
}

HOSTILE_VALUES = [None, True, 0, -1, 10**30, -(10**30), 1e308, -1e308, float("nan"), float("inf"), float("-inf"),
                  5e-324, "", "x" * 10_000, "\u202e\x7f", [], {}, [None], [float("nan")] * 3, {"k": "v"},
                  [[[[[[[[[[1]]]]]]]]]], list(range(1000)), "1.0", "NaN", "1e3"]


def _paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Every path (tuple of keys / indices) to a value inside ``doc``."""
    out = [prefix] if prefix else []
    if isinstance(doc, dict):
        for k, v in doc.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc[:6]):  # a few items of long lists are enough
            out += _paths(v, (*prefix, i))
    return out


def _mappings(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Paths of every mapping inside ``doc`` (the root is ``()``)."""
    out = [prefix] if isinstance(doc, dict) else []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc[:6]) if isinstance(doc, list) else ()
    for k, v in items:
        out += _mappings(v, (*prefix, k))
    return out


def _set(doc: Any, path: tuple, value: Any) -> Any:
    doc = copy.deepcopy(doc)
    target = doc
    for k in path[:-1]:
        target = target[k]
    target[path[-1]] = value
    return doc


def _check(name: str, data: Any, time_limit_s: float = 10.0) -> Any:
    """Call the entry point; a ConfigError must name the source; anything else than success fails the test."""
    parse, source, _ = ENTRY_POINTS[name]
    t0 = time.perf_counter()
    try:
        result = parse(data)
    except ConfigError as exc:
        assert source in str(exc), f"error does not name its file: {exc}"
        assert len(str(exc)) < 2000, f"unbounded error message ({len(str(exc))} characters)"
        result = exc
    elapsed = time.perf_counter() - t0
    assert elapsed < time_limit_s, f"{name} took {elapsed:.1f} s on a hostile input"
    return result


# -------------------------------------------------------------------------------------------- the originals


@pytest.mark.parametrize("name", ENTRY_POINTS)
def test_shipped_documents_are_valid(name):
    """The baseline for the mutations below: the unmodified documents parse."""
    parse, _, doc = ENTRY_POINTS[name]
    assert not isinstance(_check(name, doc), ConfigError)


# -------------------------------------------------------------------------------------------- random inputs

_leaf = st.one_of(st.none(), st.booleans(), st.integers(), st.floats(allow_nan=True, allow_infinity=True),
                  st.text(max_size=20))
_tree = st.recursive(_leaf, lambda kids: st.one_of(st.lists(kids, max_size=4),
                                                   st.dictionaries(st.text(max_size=10), kids, max_size=4)),
                     max_leaves=30)


@pytest.mark.parametrize("name", ENTRY_POINTS)
@SETTINGS
@given(data=_tree)
def test_random_documents(name, data):
    _check(name, data)


@SETTINGS
@given(text=st.text(max_size=200))
def test_random_yaml_text_parses_or_is_a_config_error(text):
    try:
        parse_yaml(text, "random.yaml")
    except ConfigError as exc:
        assert str(exc).startswith("random.yaml")


@pytest.mark.parametrize("name", ENTRY_POINTS)
@SETTINGS
@given(data=st.data())
def test_one_hostile_value_anywhere(name, data):
    """A valid document with one value replaced: accepted (then it is a valid object) or a ConfigError naming
    the file and the field."""
    _, _, doc = ENTRY_POINTS[name]
    path = data.draw(st.sampled_from(_paths(doc)), label="path")
    value = data.draw(st.sampled_from(HOSTILE_VALUES), label="value")
    result = _check(name, _set(doc, path, value))
    if isinstance(result, ConfigError) and isinstance(path[-1], str):
        assert result.path, f"error names no field: {result}"


@pytest.mark.parametrize("name", ENTRY_POINTS)
@SETTINGS
@given(data=st.data())
def test_unknown_key_anywhere_is_named(name, data):
    _, _, doc = ENTRY_POINTS[name]
    where = data.draw(st.sampled_from(_mappings(doc)), label="mapping")
    key = data.draw(st.sampled_from(["colour", "radius_m", "enabled_", "x" * 300, "Schema"]), label="key")
    target = copy.deepcopy(doc)
    node = target
    for k in where:
        node = node[k]
    node[key] = 1
    result = _check(name, target)
    assert isinstance(result, ConfigError), f"unknown key {key!r} at {where} accepted"
    assert key[:40] in str(result) or "unknown" in str(result)


# -------------------------------------------------------------------------------------------- named attacks


@pytest.mark.parametrize("name", ENTRY_POINTS)
def test_alias_bomb_in_every_field_is_rejected_fast(name):
    """The bomb's 10^9 elements are never walked: not by validation, not by an error message (bounded repr),
    not by the suite's configuration hash."""
    _, _, doc = ENTRY_POINTS[name]
    bomb = parse_yaml(ALIAS_BOMB)["a8"]
    paths = _paths(doc)
    for path in paths[::max(1, len(paths) // 25)]:  # about 25 places per document (all of them: the slow test)
        result = _check(name, _set(doc, path, bomb), time_limit_s=2.0)
        assert isinstance(result, ConfigError), f"alias bomb accepted at {path}"


@pytest.mark.slow
@pytest.mark.parametrize("name", ENTRY_POINTS)
def test_alias_bomb_in_every_single_field(name):
    _, _, doc = ENTRY_POINTS[name]
    bomb = parse_yaml(ALIAS_BOMB)["a8"]
    for path in _paths(doc):
        assert isinstance(_check(name, _set(doc, path, bomb), time_limit_s=2.0), ConfigError), path


@pytest.mark.parametrize("text, reason", [
    ("a: " + "9" * 5000, "malformed YAML"),                      # an int beyond Python's conversion limit
    ("[" * 50_000, "nesting too deep"),
    ("{a: " * 3000 + "1" + "}" * 3000, "nesting too deep"),
    ("!!python/object/apply:os.system ['touch /tmp/pwned']", "could not determine a constructor"),
    ("!!python/name:os.system", "could not determine a constructor"),
    ("a: \x00", "malformed YAML"),
    ("a: [1, 2", "malformed YAML"),
    ("\t- x", "malformed YAML"),
])
def test_malformed_yaml_text(text, reason):
    with pytest.raises(ConfigError, match=re.escape(reason)) as info:
        parse_yaml(text, "bad.yaml")
    assert str(info.value).startswith("bad.yaml")


def test_files_that_are_not_text(tmp_path):
    binary = tmp_path / "scene.yaml"
    binary.write_bytes(b"\xff\xfe\x00\x01" * 100)
    with pytest.raises(ConfigError, match="not a UTF-8 text file"):
        SceneModel.load(binary)
    with pytest.raises(ConfigError, match="cannot read file"):
        SceneModel.load(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="cannot read file"):
        SceneModel.load(tmp_path)  # a directory
    bad = tmp_path / "suite.yaml"
    bad.write_text("groups: [")
    with pytest.raises(ConfigError, match=re.escape(str(bad))):
        load_suite(str(bad))


@pytest.mark.parametrize("edit, match", [
    ({"width": 100_000, "height": 100_000}, "pixels is more than"),
    ({"width": 10**40}, "pixels is more than"),
    ({"width": 2**70}, "pixels is more than"),
    ({"height": 2**70 * 1.0}, "expected an integer"),
    ({"fov_deg": 5e-324}, "field of view too small"),
    ({"fov_deg": 1e-320}, "fx must be finite"),
    ({"max_range": float("inf")}, "must be finite"),
    ({"min_range": float("nan")}, "must be finite"),
    ({"fov_deg": [40.0, 30.0, 20.0]}, "expected a number or [horizontal, vertical]"),
])
def test_absurd_sensor_sizes(edit, match):
    doc = copy.deepcopy(ENTRY_POINTS["sensor"][2])
    doc["pinhole"].update(edit)
    result = _check("sensor", doc)
    assert isinstance(result, ConfigError) and match in str(result), result


def test_a_suite_that_would_expand_to_billions_of_trials_is_refused_before_expanding():
    doc = copy.deepcopy(ENTRY_POINTS["suite"][2])
    doc["groups"][0] |= {"perturbation_seeds": list(range(10_000)), "viewpoints": 10_000,
                         "noise_seeds": list(range(100))}
    result = _check("suite", doc, time_limit_s=5.0)
    assert isinstance(result, ConfigError) and f"more than the {MAX_TRIALS}" in str(result)
    assert "groups[0]" in str(result)


def test_method_parameters_are_validated_with_the_suite():
    doc = copy.deepcopy(ENTRY_POINTS["suite"][2])
    doc["methods"]["core"] = {"classifer": "select"}
    assert "methods.core: unknown key(s) classifer" in str(_check("suite", doc))
    doc["methods"]["core"] = {"classifier": ["select"]}
    assert "methods.core.classifier" in str(_check("suite", doc))


def test_yaml_is_only_read_with_the_safe_loader():
    """No module of the project calls an unsafe YAML loader (the one reader is scenes.config.parse_yaml)."""
    unsafe = re.compile(r"yaml\.(load|load_all|unsafe_load|unsafe_load_all|full_load|full_load_all)\s*\(|"
                        r"Loader\s*=|yaml\.(Unsafe|Full)?Loader\b")
    offenders = []
    for package in ("scenes", "sensors", "recognition", "evaluation", "reports", "harness"):
        for path in (ROOT / package).rglob("*.py"):
            for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
                if unsafe.search(line):
                    offenders.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not offenders, offenders
    assert "yaml.safe_load(" in (ROOT / "scenes" / "config.py").read_text(encoding="utf-8")
