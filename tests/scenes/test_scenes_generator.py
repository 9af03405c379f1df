"""Factory generator and perturbation engine: determinism, validity and truth consistency."""

import numpy as np
import pytest

from harness.cli import main
from scenes import ConfigError, SceneModel
from scenes.clearance import ClearanceIndex
from scenes.config import parse_yaml
from scenes.features import Cone, Cylinder, Torus
from scenes.generator import GeneratorConfig, generate_factory, mockup_model, shipped_scene
from scenes.geometry import transform_points
from scenes.perturb import ChangeTruth, PerturbationSpec, perturb, surface_displacement

SMALL = GeneratorConfig(size=(10.0, 8.0), cabinets=2, tanks=2, spherical_tanks=1, pipe_runs=3)


def test_generation_is_deterministic_to_the_byte(tmp_path):
    a, b = tmp_path / "a.yaml", tmp_path / "b.yaml"
    assert main(["scene", "generate", "--seed", "5", "--out", str(a)]) == 0
    assert main(["scene", "generate", "--seed", "5", "--out", str(b)]) == 0
    assert a.read_bytes() == b.read_bytes()
    assert generate_factory(SMALL, 1).to_yaml() != generate_factory(SMALL, 2).to_yaml()


def test_generated_bay_has_every_kind_of_part_and_no_interpenetration():
    model = generate_factory(GeneratorConfig(), 7)
    kinds = {o.kind for o in model.objects}
    assert {"floor", "wall", "pipe_run", "tank", "cabinet"} <= kinds
    types = {type(f) for f in model.features}
    assert {Cylinder, Torus, Cone} <= types
    index = ClearanceIndex(0.05, 0.09)
    for obj in model.objects:  # walls meet at the corners by design; every other part keeps its clearance
        if obj.kind == "wall":
            index.add(obj)
    for obj in model.objects:
        if obj.kind not in ("floor", "wall"):
            assert not index.collides(obj), obj.id
            index.add(obj)


def test_pipe_runs_are_continuous_with_matching_radii():
    """Consecutive features of a run share an end circle: same centre, same radius."""
    runs = [o for m in (mockup_model(), generate_factory(SMALL, 3)) for o in m.objects if o.kind == "pipe_run"]
    assert any(isinstance(f, Cone) for o in runs for f in o.features)
    for obj in runs:
        for f, g in zip(obj.features, obj.features[1:], strict=False):
            shared = [(p, r) for p, r in _end_circles(f) for q, s in _end_circles(g)
                      if np.allclose(p, q, atol=1e-9) and abs(r - s) < 1e-12]
            assert shared, (f.id, g.id)


def _end_circles(f):
    if isinstance(f, Cylinder):
        return [(p, f.radius) for p in f.endpoints()]
    if isinstance(f, Torus):
        return [(f.spine(a)[0][0], f.minor_radius) for a in (0.0, f.sweep)]
    return [(f.apex + f.axis * d, float(f.radius_at(d))) for d in (f.start, f.end)]


def test_reducer_orientation_is_handled_either_way():
    from scenes.builders import pipe_run

    run = pipe_run("p", [[0, 0, 0], [1, 0, 0]], 0.05, 0.1, reducers={0: (0.08, 0.2)})
    cone = [f for f in run.features if isinstance(f, Cone)][0]
    assert cone.radius_at(cone.start) == pytest.approx(0.05) or cone.radius_at(cone.end) == pytest.approx(0.05)
    assert {round(float(cone.radius_at(d)), 9) for d in (cone.start, cone.end)} == {0.05, 0.08}


def test_shipped_scenes_load():
    for name in ("mockup", "factory_bay"):
        model = SceneModel.load(shipped_scene(name))
        assert len(model.features) > 10
    with pytest.raises(FileNotFoundError, match="no shipped scene 'nope'"):
        shipped_scene("nope")


@pytest.mark.parametrize("seed", range(4))
def test_perturbation_truth_matches_the_actual_scene(seed):
    model = SceneModel.load(shipped_scene("mockup"))
    spec = PerturbationSpec.load(shipped_scene("mockup").with_name("mockup_perturbation.yaml"))
    spec = PerturbationSpec(**{**spec.__dict__, "moved_probability": 0.35, "section_moved_probability": 0.5})
    actual, truth = perturb(model, spec, seed)
    actual_ids = {f.id for f in actual.features}
    for f in model.features:
        change = truth.features[f.id]
        if change.label == "missing":
            assert f.id not in actual_ids
            continue
        g = actual.feature(f.id)
        if change.label == "moved":
            # moved features are where the transform puts them
            pts, _ = f.sample(200, np.random.default_rng(0))
            np.testing.assert_allclose(g.signed_distance(transform_points(change.transform, pts)), 0, atol=1e-9)
            assert surface_displacement(f, g) >= spec.moved_threshold
        elif change.label == "unchanged":
            assert f == g or surface_displacement(f, g) < spec.moved_threshold
        elif change.label == "altered":
            assert f != g
    for fid in truth.new_features:
        assert fid in actual_ids and truth.feature_label(fid) == "new"
    # moved and new parts keep the clearance from every other part
    index = ClearanceIndex(spec.clearance / 2, spec.clearance * 0.9)
    for obj in actual.objects:
        if obj.kind != "floor":
            assert not index.collides(obj, ignore={o.id for o in actual.objects if o.kind == "floor"}), obj.id
            index.add(obj)
    assert ChangeTruth.from_json(truth.to_json()) .to_json() == truth.to_json()


def test_perturbation_is_deterministic_and_labels_spread():
    model = SceneModel.load(shipped_scene("factory_bay"))
    spec = PerturbationSpec()
    a1, t1 = perturb(model, spec, 11)
    a2, t2 = perturb(model, spec, 11)
    assert a1.to_yaml() == a2.to_yaml() and t1.to_json() == t2.to_json()
    labels = set()
    for seed in range(6):
        _, t = perturb(model, spec, seed)
        labels |= {c.label for c in t.objects.values()}
        assert 1 <= len(t.new_objects) <= 3
        assert all(t.objects[o.id].label == "unchanged" for o in model.objects if o.kind in ("floor", "wall"))
    assert {"moved", "missing", "altered", "unchanged"} <= labels


def test_perturbation_cli_writes_actual_and_truth(tmp_path):
    out = tmp_path / "p"
    assert main(["scene", "perturb", str(shipped_scene("mockup")), "--seed", "1", "--out", str(out),
                 "--spec", str(shipped_scene("mockup").with_name("mockup_perturbation.yaml"))]) == 0
    actual = SceneModel.load(out / "actual.yaml")
    truth = ChangeTruth.from_json((out / "truth.json").read_text())
    assert {f.id for f in actual.features} >= set(truth.new_features)


def test_factory_magnitudes_on_the_mockup_give_a_clear_error(tmp_path, capsys):
    # the default spec's new boxes are larger than the mock-up's floor: say so, not numpy's "high - low < 0"
    assert main(["scene", "perturb", str(shipped_scene("mockup")), "--seed", "3", "--out", str(tmp_path / "p")]) == 2
    assert "does not fit the scene's floor" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("text, message", [
    ("moved: {probability: 1.5}", r"moved\.probability: must be <= 1"),
    ("moved: {probability: 0.6}\nmissing: {probability: 0.6}", "probabilities must be <= 1"),
    ("moved: {translation: [0.5, 0.1]}", r"moved\.translation: expected \[low, high\]"),
    ("new: {count: [1, 99]}", r"new\.count"),
    ("teleported: {probability: 0.1}", r"unknown key\(s\) teleported"),
    ("protected_kinds: [floor, moon]", "protected_kinds"),
    ("moved: {by_kind: {wall: 0.1}}", r"moved\.by_kind\.wall: walls are never moved \(a bay's structure\)"),
    ("missing: {by_kind: {wall: 0.1}}", r"missing\.by_kind\.wall: walls are never removed"),
    ("altered: {by_kind: {floor: 0.1}}", r"altered\.by_kind\.floor: the floor never changes"),
    ("altered: {by_kind: {moon: 0.1}}", r"altered\.by_kind: unknown key\(s\) moon"),
    ("altered: {by_kind: {cabinet: 1.5}}", r"altered\.by_kind\.cabinet: must be <= 1"),
    ("altered: {by_kind: [cabinet]}", r"altered\.by_kind: expected a mapping"),
    ("moved: {by_kind: {cabinet: 0.6}}\naltered: {by_kind: {cabinet: 0.5}}",
     "probabilities must be <= 1, got 1.2 for cabinet"),
    ("altered: {size_change: [0.2, 0.95]}", r"altered\.size_change: expected \[low, high\] with 0 <= low <= high"),
    ("new: {kinds: {pipe_run: 0, cabinet: 0}}", r"new\.kinds: needs a kind with a weight > 0"),
    ("new: {kinds: {castle: 1}}", r"new\.kinds: unknown key\(s\) castle"),
    ("new: {tank_radius: [0, 0.5]}", "sizes of new parts must be > 0"),
])
def test_perturbation_spec_errors(text, message):
    with pytest.raises(ConfigError, match=message):
        PerturbationSpec.from_dict(parse_yaml(text), "spec.yaml")


@pytest.mark.parametrize("text, message", [
    ("bay: {size: [1, 5]}", r"bay\.size: each side must be >= 2 m"),
    ("pipes: {runs: 1, vertical: 1, slanted: 1}", "at least vertical"),
    ("pipes: {bend_ratio: [0.5, 2]}", "bend_ratio: must be > 1"),
    ("tanks: {count: 1, spherical: 2}", "spherical: cannot exceed count"),
    ("cabinets: {count: -1}", r"cabinets\.count: must be >= 0"),
])
def test_generator_config_errors(text, message):
    with pytest.raises(ConfigError, match=message):
        GeneratorConfig.from_dict(parse_yaml(text), "gen.yaml")
