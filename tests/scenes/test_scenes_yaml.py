"""Scene YAML: exact round trips and one clear error per kind of bad input."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.cli import main
from scenes import ConfigError, SceneModel
from scenes.features import Cone, Cylinder, Sphere, Torus
from scenes.generator import GeneratorConfig, generate_factory, mockup_model
from scenes.geometry import perpendicular, unit
from scenes.model import Object

finite = st.floats(-50, 50, allow_nan=False, allow_infinity=False)
positive = st.floats(1e-3, 10, allow_nan=False)
direction = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1).map(unit)


@st.composite
def scene_models(draw):
    objects = []
    for i in range(draw(st.integers(1, 4))):
        feats = []
        for j in range(draw(st.integers(1, 3))):
            kind = draw(st.sampled_from(["cyl", "sph", "cone", "torus"]))
            fid = f"o{i}.f{j}"
            centre = draw(st.lists(finite, min_size=3, max_size=3))
            if kind == "cyl":
                feats.append(Cylinder(fid, centre=centre, axis=draw(direction), radius=draw(positive),
                                      length=draw(positive)))
            elif kind == "sph":
                r = draw(positive)
                feats.append(Sphere(fid, centre=centre, radius=r, cap_axis=draw(direction),
                                    cap_height=draw(st.floats(0.01, 2.0)) * r))
            elif kind == "cone":
                start = draw(st.floats(0, 5))
                feats.append(Cone(fid, apex=centre, axis=draw(direction), half_angle=draw(st.floats(0.01, 1.5)),
                                  start=start, end=start + draw(positive)))
            else:
                axis = draw(direction)
                across = np.cross(axis, draw(direction))
                # a nearly parallel draw leaves a cross product too small to normalise exactly
                start = unit(across) if np.linalg.norm(across) >= 0.5 else perpendicular(axis)
                major = draw(positive)
                feats.append(Torus(fid, centre=centre, axis=axis, major_radius=major,
                                   minor_radius=major * draw(st.floats(0.01, 0.9)), start=start,
                                   sweep=draw(st.floats(0.01, 2 * math.pi))))
        objects.append(Object(f"o{i}", draw(st.sampled_from(["pipe_run", "tank", "structure"])), tuple(feats)))
    return SceneModel("h", tuple(objects))


@settings(max_examples=60, deadline=None)
@given(scene_models())
def test_yaml_round_trip_is_exact(model):
    text = model.to_yaml()
    again = SceneModel.from_yaml(text)
    assert again == model
    assert again.to_yaml() == text


def test_shipped_and_generated_models_round_trip(tmp_path):
    for model in (mockup_model(), generate_factory(GeneratorConfig(pipe_runs=3, cabinets=2, tanks=1), 3)):
        path = tmp_path / "m.yaml"
        model.save(path)
        assert SceneModel.load(path) == model


GOOD = """
schema: scene/1
name: t
objects:
  - id: pipe
    kind: pipe_run
    features:
      - {type: cylinder, id: pipe.s0, centre: [0, 0, 1], axis: [1, 0, 0], radius: 0.1, length: 2}
      - {type: torus, id: pipe.e0, centre: [0, 0, 0], axis: [0, 0, 1], major_radius: 1, minor_radius: 0.1,
         start: [1, 0, 0], sweep_deg: 90}
"""


@pytest.mark.parametrize("old, new, message", [
    ("radius: 0.1,", "radius: -1,", r"objects\[0\]\.features\[0\]\.radius: must be > 0, got -1"),
    ("axis: [1, 0, 0]", "axis: [0, 0, 0]", r"features\[0\]\.axis: must be a non-zero vector"),
    ("axis: [1, 0, 0]", "axis: [1, 1, 0]", r"features\[0\]\.axis: must be a unit vector"),
    ("id: pipe.e0", "id: pipe.s0", r"features\[1\]\.id: duplicate id 'pipe.s0'"),
    ("sweep_deg: 90", "sweep_deg: 400", r"features\[1\]\.sweep_deg: must be <= 360"),
    ("length: 2}", "length: 2, colour: red}", r"features\[0\]: unknown key\(s\) colour"),
    ("length: 2}", "}", r"features\[0\]\.length: missing required key"),
    ("type: cylinder", "type: blob", r"features\[0\]\.type: must be one of"),
    ("radius: 0.1,", "radius: .nan,", r"radius: must be finite"),
    ("radius: 0.1,", "radius: [1],", r"radius: expected a number"),
    ("kind: pipe_run", "kind: spaceship", r"objects\[0\]\.kind: must be one of"),
    ("minor_radius: 0.1", "minor_radius: 2", r"minor_radius: must be smaller than major_radius"),
    ("start: [1, 0, 0]", "start: [0, 0, 1]", r"start: must be perpendicular to axis"),
])
def test_validation_errors_name_file_field_and_reason(tmp_path, old, new, message):
    assert old in GOOD
    path = tmp_path / "bad.yaml"
    path.write_text(GOOD.replace(old, new, 1))
    with pytest.raises(ConfigError, match=message) as info:
        SceneModel.load(path)
    assert str(info.value).startswith(str(path))


def test_malformed_yaml_and_wrong_root(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("objects: [\n  - {id: a")
    with pytest.raises(ConfigError, match="malformed YAML"):
        SceneModel.load(path)
    path.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping, got list"):
        SceneModel.load(path)
    path.write_text("!!python/object/apply:os.system ['echo unsafe']\n")
    with pytest.raises(ConfigError, match="malformed YAML"):
        SceneModel.load(path)
    with pytest.raises(ConfigError, match="cannot read file"):
        SceneModel.load(tmp_path / "missing.yaml")


def test_cli_reports_bad_scene_with_exit_code_2(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(GOOD.replace("radius: 0.1,", "radius: 0,"))
    assert main(["scene", "mjcf", str(path), "--out", str(tmp_path / "x.xml")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("harness: error:") and "radius: must be > 0" in err and "Traceback" not in err
