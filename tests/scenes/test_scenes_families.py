"""The parametric mock-up family and perturbations of every kind on every kind of object."""

import math
import os
import subprocess
import sys

import numpy as np
import pytest

from scenes import ConfigError, SceneModel, builders
from scenes.clearance import ClearanceIndex, object_samples
from scenes.config import parse_yaml
from scenes.features import Cone, Cylinder, Plane, Sphere, Torus
from scenes.generator import FACTORY_GENERATOR, GeneratorConfig, mockup_model
from scenes.geometry import transform_points
from scenes.mjcf import box_of_planes
from scenes.mockup_family import MOCKUP_FAMILY, MockupFamilyConfig, draw_mockup, generate_mockup
from scenes.perturb import (
    FACTORY_BAY_PERTURBATION,
    MOCKUP_PERTURBATION,
    MOVABLE_KINDS,
    NEW_KINDS,
    ChangeTruth,
    PerturbationSpec,
    change_kind,
    perturb,
    scene_key,
    surface_displacement,
)

FAMILY = MockupFamilyConfig()


# -------------------------------------------------------------------------------------------- the mock-up family


def test_members_reproduce_to_the_byte_and_differ_between_seeds():
    assert MockupFamilyConfig.load(MOCKUP_FAMILY) == FAMILY
    a = generate_mockup(FAMILY, 3)
    assert a.name == "mockup_3" and generate_mockup(FAMILY, 3, "m").name == "m"
    assert a.to_yaml() == generate_mockup(MockupFamilyConfig.load(MOCKUP_FAMILY), 3).to_yaml()
    assert a.to_yaml() != generate_mockup(FAMILY, 4).to_yaml()
    assert SceneModel.from_yaml(a.to_yaml()) == a
    today = mockup_model()
    assert [(o.id, o.kind) for o in a.objects] == [(o.id, o.kind) for o in today.objects]
    assert [f.id for f in a.features] == [f.id for f in today.features]


@pytest.mark.parametrize("seed", [-1, 1.5, True])
def test_a_seed_is_a_whole_number(seed):
    with pytest.raises(ValueError, match="seed must be a whole number >= 0"):
        generate_mockup(FAMILY, seed)


def test_thirty_members_are_complete_clear_and_on_the_table():
    sx, sy = FAMILY.table.size
    pipe_a_radii, tank_radii = [], []
    for seed in range(30):
        draw = draw_mockup(FAMILY, seed)
        model = draw.model
        assert draw.skipped == (), seed
        assert {change_kind(o) for o in model.objects} == {"floor", "wall", "pipe_run", "tank", "sphere_tank",
                                                          "cabinet"}
        assert {type(f) for f in model.features} == {Plane, Cylinder, Sphere, Cone, Torus}
        index = ClearanceIndex(FAMILY.clearance / 2, 0.9 * FAMILY.clearance)
        for obj in model.objects:
            if obj.kind == "floor":
                continue
            assert not index.collides(obj), (seed, obj.id)
            index.add(obj)
            pts = object_samples(obj, 0.005)
            assert np.all(np.abs(pts[:, 0]) <= sx / 2 + 1e-9) and np.all(np.abs(pts[:, 1]) <= sy / 2 + 1e-9)
            assert pts[:, 2].min() >= -1e-9 and pts[:, 2].max() <= FAMILY.table.max_height, (seed, obj.id)
        _check_ranges(model)
        pipe_a_radii.append(model.object("pipe_a").features[0].radius)
        tank_radii.append(model.object("tank").features[0].radius)
    # the family holds pipes 20 % thinner and thicker than today's, and narrower and wider tanks
    assert min(pipe_a_radii) < 0.8 * 0.025 < 1.2 * 0.025 < max(pipe_a_radii)
    assert min(tank_radii) < 0.8 * 0.08 < 1.2 * 0.08 < max(tank_radii)


def _within(value, rng) -> bool:
    return rng.low - 1e-12 <= value <= rng.high + 1e-12


def _check_ranges(model):
    """The parameters of a member lie in the ranges of the config."""
    pipe_a, pipe_b, pipe_c = (model.object(k).features for k in ("pipe_a", "pipe_b", "pipe_c"))
    assert _within(pipe_a[0].radius, FAMILY.elbow_pipe.radius)
    elbow = next(f for f in pipe_a if isinstance(f, Torus))
    assert _within(elbow.major_radius / elbow.minor_radius, FAMILY.elbow_pipe.bend_ratio)
    cone = next(f for f in pipe_b if isinstance(f, Cone))
    assert _within(math.degrees(cone.half_angle), FAMILY.reducer_pipe.cone_angle_deg)
    assert _within(pipe_b[-1].radius / pipe_b[0].radius, FAMILY.reducer_pipe.radius_ratio)
    assert _within(math.degrees(math.asin(pipe_c[0].axis[2])), FAMILY.slanted_pipe.slant_deg)
    body, top = model.object("tank").features
    assert _within(body.radius, FAMILY.tank.radius) and _within(body.length, FAMILY.tank.height)
    leg, ball = model.object("sphere").features
    assert _within(ball.radius, FAMILY.sphere_tank.radius)
    _, R, half, _ = box_of_planes(model.object("cabinet").features)
    assert _within(2 * half[2], FAMILY.cabinet.height) and _within(2 * half[0], FAMILY.cabinet.width)
    assert _within(math.degrees(math.atan2(R[1, 0], R[0, 0])), FAMILY.cabinet.yaw_deg)


@pytest.mark.parametrize("text, message", [
    ("schema: mockup_family/2", "unsupported schema 'mockup_family/2'"),
    ("elbow_pipe: {radius: [0.03, 0.02]}", r"elbow_pipe\.radius: expected \[low, high\] with 0 < low <= high"),
    ("elbow_pipe: {radius: 0.03}", r"elbow_pipe\.radius: expected a list of 2 numbers"),
    ("elbow_pipe: {bend_ratio: [0.8, 2]}", r"elbow_pipe\.bend_ratio: must lie strictly between 1 and 10"),
    ("reducer_pipe: {radius_ratio: [0.5, 1.2]}", r"radius_ratio: must lie strictly between 0 and 1"),
    ("slanted_pipe: {slant_deg: [10, 90]}", r"slant_deg: must lie strictly between 0 and 80"),
    ("tank: {x: [0.5, 0.9]}", r"tank\.x: must lie on the table \(\|x\| <= 0\.8\)"),
    ("slanted_pipe: {x: [-0.5, -0.6]}", r"slanted_pipe\.x: expected \[low, high\] with low <= high"),
    ("cabinet: {yaw_deg: [0, 200]}", r"cabinet\.yaw_deg: must lie in \[-180, 180\]"),
    ("cabinet: {width: [0.1, 5.0]}", r"cabinet\.width: must fit on the table"),
    ("wall: {height: [0.5, 0.9]}", r"wall\.height: must stay below the table's max_height \(0\.7\)"),
    ("wall: {thickness: 0.4, inset: 0.2}", r"wall\.thickness: thickness \+ inset must be < half the table"),
    ("wall: {thickness: 0}", r"wall\.thickness: must be > 0"),
    ("table: {size: [0.1, 1.0]}", r"table\.size: each side must be in \[0\.2, 10\] m"),
    ("sphere_tank: {colour: red}", r"sphere_tank: unknown key\(s\) colour"),
    ("tank: [1, 2]", r"tank: expected a mapping, got list"),
    ("clearance: 0", r"clearance: must be > 0"),
    ("max_tries: 0", r"max_tries: must be >= 1"),
    ("pipes: {radius: [0.01, 0.02]}", r"unknown key\(s\) pipes"),
])
def test_family_config_errors_name_file_field_and_reason(text, message):
    with pytest.raises(ConfigError, match=message) as info:
        MockupFamilyConfig.from_dict(parse_yaml(text), "fam.yaml")
    assert str(info.value).startswith("fam.yaml: ") and "\n" not in str(info.value)


def test_family_config_file_errors_name_the_file(tmp_path):
    path = tmp_path / "fam.yaml"
    path.write_text("schema: mockup_family/1\ntank: {radius: [-1, 0.1]}\n")
    with pytest.raises(ConfigError, match=r"tank\.radius: expected") as info:
        MockupFamilyConfig.load(path)
    assert str(info.value).startswith(str(path))
    assert GeneratorConfig.load(FACTORY_GENERATOR).reducer_probability == 0.4  # the exposed default path


# -------------------------------------------------------------------------------------------- perturbations


def _small_model(shift: float = 0.0) -> SceneModel:
    """A small scene with one object of every kind, quick to perturb (4 m x 3 m; 8 cm clearance below)."""
    return SceneModel("small", (
        builders.floor("floor", 4.0, 3.0),
        builders.wall("wall", (0.0, 1.4, 0.0), 0.0, 4.0, 1.5, 0.1),
        builders.pipe_run("pipe", [[-1.5, 0.8, 1.0], [0.5 + shift, 0.8, 1.0], [0.5 + shift, -0.5, 1.0]], 0.05,
                          0.15, reducers={0: (0.035, 0.1)}),
        builders.tank("tank", (1.3, 0.3, 0.0), 0.25, 0.8),
        builders.sphere_tank("ball", (-1.0, -0.5, 0.0), 0.25, 0.3),
        builders.cabinet("cabinet", (1.2, -0.9, 0.0), 0.3, (0.5, 0.4, 0.7)),
    ))


SMALL_SPEC = """
moved: {probability: 0.3, translation: [0.05, 0.3]}
missing: {probability: 0.2}
altered: {probability: 0.3, by_kind: {wall: 0.5}}
section_moved: {probability: 0.5, translation: [0.05, 0.2]}
new: {count: [1, 3], pipe_radius: [0.03, 0.08], length: [0.5, 1.5], box_size: [0.3, 0.6],
      tank_radius: [0.15, 0.3], tank_height: [0.4, 0.8]}
clearance: 0.08
protected_kinds: [floor]
"""


def _spec(text: str = SMALL_SPEC, **changes) -> PerturbationSpec:
    spec = PerturbationSpec.from_dict(parse_yaml(text), "small.yaml")
    return PerturbationSpec(**{**spec.__dict__, **changes})


def test_every_change_is_drawn_for_every_kind_it_applies_to():
    model, spec = _small_model(), _spec()
    seen: set[tuple[str, str]] = set()
    new_kinds: set[str] = set()
    for seed in range(200):
        actual, truth = perturb(model, spec, seed)
        seen |= {(change_kind(o), truth.objects[o.id].label) for o in model.objects}
        new_kinds |= {change_kind(actual.object(oid)) for oid in truth.new_objects}
    for kind in ("cabinet", "tank", "sphere_tank", "pipe_run"):
        assert {(kind, label) for label in ("moved", "missing", "altered", "unchanged")} <= seen, kind
    assert {("wall", "altered"), ("wall", "unchanged")} <= seen
    assert not {("wall", "moved"), ("wall", "missing")} & seen
    assert {label for kind, label in seen if kind == "floor"} == {"unchanged"}
    assert new_kinds == set(NEW_KINDS)


def test_altered_objects_change_only_what_was_drawn():
    """Everything altered: box sides and tank sizes scale by 1 +- [0.2, 0.5], bases stay, features that did
    not change are the a priori ones and labelled unchanged."""
    model = _small_model()
    spec = _spec(moved_probability=0.0, missing_probability=0.0, altered_probability=1.0,
                 altered_by_kind=(("wall", 1.0),), new_count=(0, 0))
    changed_dims: set[tuple[str, int]] = set()
    for seed in range(12):
        actual, truth = perturb(model, spec, seed)
        assert truth.notes == ()
        for obj in model.objects:
            if obj.kind == "floor":
                continue
            after = actual.object(obj.id)
            assert truth.objects[obj.id].label == "altered"
            for f, g in zip(obj.features, after.features, strict=True):
                assert truth.features[f.id].label == ("unchanged" if f is g else "altered"), f.id
                assert (f is g) == (f == g)
            if obj.kind in ("cabinet", "wall"):
                changed_dims |= {(obj.kind, k) for k in _check_box(obj, after)}
            elif obj.kind == "tank":
                _check_tank(obj, after)
            else:  # a pipe run: every radius scaled by one factor
                k = after.features[0].radius / obj.features[0].radius
                assert 0.2 - 1e-9 <= abs(k - 1) <= 0.5 + 1e-9
                for f, g in zip(obj.features, after.features, strict=True):
                    if isinstance(f, Cylinder):
                        assert g.radius == pytest.approx(k * f.radius)
                    elif isinstance(f, Torus):
                        assert g.minor_radius == pytest.approx(k * f.minor_radius)
    assert {("cabinet", 0), ("cabinet", 1), ("cabinet", 2), ("wall", 0), ("wall", 2)} <= changed_dims


def _check_box(before, after) -> set[int]:
    (c0, R0, h0, _), (c1, R1, h1, _) = box_of_planes(before.features), box_of_planes(after.features)
    np.testing.assert_allclose(R1, R0, atol=1e-12)
    np.testing.assert_allclose(c1 - R1[:, 2] * h1[2], c0 - R0[:, 2] * h0[2], atol=1e-12)  # the base stays
    k = h1 / h0
    changed = {i for i in range(3) if abs(k[i] - 1) > 1e-9}
    assert changed and all(0.2 - 1e-9 <= abs(k[i] - 1) <= 0.5 + 1e-9 for i in changed)
    if before.kind == "wall":
        assert 1 not in changed  # a wall's thickness stays
    bottom = [i for i, f in enumerate(before.features) if f.normal[2] < -0.5][0]
    assert (after.features[bottom] is before.features[bottom]) == (changed == {2})  # only the height changed
    return changed


def _check_tank(before, after):
    b0, b1 = before.features[0], after.features[0]
    base0 = b0.centre - [0, 0, b0.length / 2]
    np.testing.assert_allclose(b1.centre - [0, 0, b1.length / 2], base0, atol=1e-12)
    ball0, ball1 = before.features[1], after.features[1]
    kr = ball1.radius / ball0.radius
    assert kr == 1 or 0.2 - 1e-9 <= abs(kr - 1) <= 0.5 + 1e-9
    if ball0.cap_axis is None:  # a spherical tank keeps the gap under its ball
        assert ball1.centre[2] - ball1.radius == pytest.approx(ball0.centre[2] - ball0.radius)
        assert b1.length > 0 and b1.radius == pytest.approx(ball1.radius / 3)
    else:
        np.testing.assert_allclose(ball1.centre, b1.centre + [0, 0, b1.length / 2], atol=1e-12)
        assert kr != 1 or b1.length != b0.length


@pytest.mark.parametrize("seed", range(6))
def test_truth_matches_the_actual_scene_of_every_kind(seed):
    model, spec = _small_model(), _spec()
    actual, truth = perturb(model, spec, seed)
    for f in model.features:
        change = truth.features[f.id]
        if change.label == "missing":
            assert f.id not in {g.id for g in actual.features}
            continue
        g = actual.feature(f.id)
        if change.label == "moved":
            pts, _ = f.sample(200, np.random.default_rng(0))
            np.testing.assert_allclose(g.signed_distance(transform_points(change.transform, pts)), 0, atol=1e-9)
            assert surface_displacement(f, g) >= spec.moved_threshold
        elif change.label == "unchanged":
            assert f == g or surface_displacement(f, g) < spec.moved_threshold
        else:
            assert change.label == "altered" and f != g
    index = ClearanceIndex(spec.clearance / 2, spec.clearance * 0.9)
    walls = {o.id for o in actual.objects if o.kind in ("floor", "wall")}
    for obj in actual.objects:
        if obj.kind != "floor":
            ignore = walls if obj.kind == "wall" else {"floor"} if obj.kind in ("tank", "cabinet") else set()
            assert not index.collides(obj, ignore=ignore), obj.id
            index.add(obj)
    assert ChangeTruth.from_json(truth.to_json()).to_json() == truth.to_json()
    assert SceneModel.from_yaml(actual.to_yaml()) == actual


def test_the_draw_depends_on_the_scene_as_well_as_the_seed():
    a, b = _small_model(), _small_model(shift=0.05)  # the same objects and features, other geometry
    assert [f.id for f in a.features] == [f.id for f in b.features] and scene_key(a) != scene_key(b)
    spec = _spec()

    def pattern(model, seed):
        truth = perturb(model, spec, seed)[1]
        return [c.label for c in truth.objects.values()], len(truth.new_objects)

    differ = sum(pattern(a, s) != pattern(b, s) for s in range(8))
    assert differ >= 4
    # the name is not part of the scene; a model read back from YAML is the same scene
    renamed = SceneModel("other", a.objects)
    assert scene_key(renamed) == scene_key(SceneModel.from_yaml(a.to_yaml())) == scene_key(a)


def test_a_seed_gives_the_same_draw_twice_and_in_another_process():
    model, spec = _small_model(), _spec()
    a1, t1 = perturb(model, spec, 17)
    a2, t2 = perturb(model, spec, 17)
    assert a1.to_yaml() == a2.to_yaml() and t1.to_json() == t2.to_json()
    code = ("from scenes.generator import mockup_model; from scenes.perturb import scene_key; "
            "print(scene_key(mockup_model()))")
    env = {**os.environ, "PYTHONHASHSEED": "4321"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert int(out.stdout) == scene_key(mockup_model())


def test_rates_by_kind_and_protection():
    spec = _spec(moved_probability=0.0, missing_probability=0.0, altered_probability=0.0,
                 section_moved_probability=0.0, altered_by_kind=(("cabinet", 1.0),),
                 new_kinds=(("sphere_tank", 1.0),), new_count=(2, 2))
    model = _small_model()
    new_kinds = set()
    for seed in range(3):
        actual, truth = perturb(model, spec, seed)
        assert {k: c.label for k, c in truth.objects.items() if c.label != "unchanged"} == {"cabinet": "altered"}
        new_kinds |= {change_kind(actual.object(o)) for o in truth.new_objects}
    assert new_kinds == {"sphere_tank"}
    protected = PerturbationSpec(**{**spec.__dict__, "protected_kinds": ("floor", "cabinet")})
    assert protected.rates("cabinet") == (0.0, 0.0, 0.0)
    assert {c.label for c in perturb(model, protected, 0)[1].objects.values()} == {"unchanged"}
    structural = _spec(moved_probability=0.5, missing_probability=0.5, altered_probability=0.0)
    assert structural.rates("wall") == (0.0, 0.0, 0.5) and structural.rates("floor") == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("path", [MOCKUP_PERTURBATION, FACTORY_BAY_PERTURBATION])
def test_shipped_specs_have_the_documented_rates(path):
    spec = PerturbationSpec.load(path)
    for kind in MOVABLE_KINDS:
        assert spec.rates(kind) == (0.15, 0.10, 0.10)
    assert spec.rates("wall") == (0.0, 0.0, 0.05) and spec.rates("floor") == (0.0, 0.0, 0.0)
    assert spec.section_moved_probability == 0.05
    assert dict(spec.new_kinds) == {"pipe_run": 0.4, "cabinet": 0.2, "tank": 0.2, "sphere_tank": 0.2}
    # an older spec without the new keys still loads, and the built-in spec leaves walls alone as before
    old = PerturbationSpec.from_dict(parse_yaml("altered: {probability: 0.1, radius_change: [0.2, 0.5]}"))
    assert old.rates("wall") == PerturbationSpec().rates("wall") == (0.0, 0.0, 0.0)


def test_mockup_family_members_perturb_with_the_mockup_spec():
    spec = PerturbationSpec.load(MOCKUP_PERTURBATION)
    model = generate_mockup(FAMILY, 5)
    actual, truth = perturb(model, spec, 2)
    assert set(truth.objects) == {o.id for o in model.objects} and truth.notes == ()
    assert 1 <= len(truth.new_objects) <= 3


def test_a_member_is_the_same_scene_whatever_the_last_bits_of_its_generator():
    """Members are rounded to 10 decimals (``SceneModel.rounded``): a model whose numbers differ in their last bit
    (another SIMD width; a zero as a tiny number) rounds to the same model, and rounding twice changes nothing."""
    from scenes.families import family_member

    model = family_member("mockup", 1002)
    data = model.to_dict()

    def nudged(v):
        if isinstance(v, float):
            return float(np.nextafter(v, np.inf))
        if isinstance(v, dict):
            return {k: nudged(x) for k, x in v.items()}
        if isinstance(v, list):
            return [nudged(x) for x in v]
        return v

    other = SceneModel.from_dict(nudged(data))
    assert other.to_yaml() != model.to_yaml() and other.rounded().to_yaml() == model.to_yaml()
    assert model.rounded().to_yaml() == model.to_yaml()
