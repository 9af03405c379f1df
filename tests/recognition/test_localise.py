"""Localisation end to end: the shipped mock-up scanned by the simulator, recovered with no pose prior."""

from __future__ import annotations

import _support
import numpy as np
import pytest

from evaluation.pose import changed_features, constrains_pose, pose_section
from recognition.localisation import LocaliseParams, PoseResult, coarse_sensor, localise
from sensors.models import PinholeCamera, ScanningLaser


@pytest.mark.parametrize("sensor", [
    PinholeCamera.from_fov(64, 48, 40.0, min_range=0.3, max_range=3.0),
    ScanningLaser(64, 48, -0.7, 0.7, -0.5, 0.5, 0.5, 20.0),
])
def test_coarse_sensor_rays_are_the_full_sensor_rays(sensor):
    cs, o = coarse_sensor(sensor, 4)
    full = sensor.ray_directions()[o::4, o::4]
    assert np.allclose(cs.ray_directions(), full, atol=1e-12)


def test_params_are_validated():
    with pytest.raises(ValueError, match="min_confidence"):
        LocaliseParams(min_confidence=2.0)
    with pytest.raises(ValueError, match="slide_steps"):
        LocaliseParams(slide_steps=-1)
    with pytest.raises(ValueError, match="max_free_without_one"):
        LocaliseParams(max_free_without_one=7)
    with pytest.raises(ValueError, match="conditional_max_free"):
        LocaliseParams(conditional_max_free=-1)


@pytest.mark.slow
def test_full_pipeline_recovers_mockup_pose():
    from harness.suite import load_suite
    from harness.trial import prepare_scene, sensor_for
    from recognition.describe import describe
    from scenes.geometry import look_at
    from sensors.simulate import Simulator

    spec = next(t for t in load_suite("smoke").trials if t.scene == "mockup")
    p = prepare_scene(spec, None)
    cfg = sensor_for(spec)
    T_true = look_at(np.array([0.3, -1.1, 0.9]), np.array([0.0, 0.2, 0.15]))
    scan, truth = p.simulator.simulate(cfg, T_true, np.random.default_rng(3))
    assert constrains_pose(truth, p.actual)
    desc = describe(scan)
    sim = Simulator.from_scene(p.apriori)
    res = localise(desc, scan, p.apriori, model_simulator=sim)
    assert isinstance(res, PoseResult)
    assert res.ok, res.reason
    sec = pose_section(res, truth.T_world_sensor, float(np.nanmedian(truth.true_range)), True, None)
    assert sec["success"]
    assert sec["rotation_error_deg"] < 0.1 and sec["translation_error_mm"] < 1.0
    assert res.free_dof == 0 and 0.4 <= res.confidence <= 1.0
    assert res.predicted is not None and res.predicted.range.shape == scan.range.shape
    # deterministic
    again = localise(desc, scan, p.apriori, model_simulator=sim)
    assert np.array_equal(again.T_world_sensor, res.T_world_sensor)


def test_changed_features_are_the_moved_altered_and_new_ones():
    """Only the unchanged part of the model can locate the sensor before the pose is known: moved, altered
    (another radius: the invariants no longer match) and new features are excluded; missing ones are not in
    the actual scene at all."""
    from scenes.perturb import Change, ChangeTruth

    ct = ChangeTruth(features={"a.s0": Change("unchanged"), "b.s0": Change("moved", np.eye(4), 0.1),
                               "c.s0": Change("altered"), "d.s0": Change("missing")},
                     objects={}, new_features=("n.s0",))
    assert changed_features(ct) == {"b.s0", "c.s0", "n.s0"}


@pytest.mark.slow
def test_a_patch_the_interpretation_leaves_unmatched_does_not_pull_icp():
    """The default suite's mock-up trial whose sphere is 47 mm instead of the model's 60 mm (altered), seen
    beside the table, a wall and two pipes that fix the pose: the closed form is right, and ICP must keep it
    (on every scan point it slid 14.5 mm along the pipes, pulling the sphere's points onto the model's)."""
    from harness.suite import load_suite
    from harness.trial import sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import describe
    from sensors.simulate import Simulator

    spec = next(t for t in load_suite("classic").trials if t.trial_id == "mockup-p2-v4-mockup_laser-n0")
    p = first_phase_scene(spec, "mockup-p2")
    assert p.change_truth.features["sphere.ball"].label == "altered"
    cfg = sensor_for(spec)
    scan, truth = trial_scan(spec, p, cfg, trial_viewpoints(spec, p, cfg).viewpoints[0].T_world_sensor)
    res = localise(describe(scan), scan, p.apriori, model_simulator=Simulator.from_scene(p.apriori))
    sec = pose_section(res, truth.T_world_sensor, float(np.nanmedian(truth.true_range)), True, None)
    assert sec["translation_error_mm"] < 1.0 and sec["rotation_error_deg"] < 0.05, sec


def test_agreement_lets_a_missing_object_be_seen_through_but_not_a_whole_wall():
    """Pixels behind the prediction (a model pipe that is missing, the wall behind it seen) neither agree
    nor disagree, up to ``seen_through`` of a patch; a pose that predicts a wall in front of everything
    still disagrees on the rest."""
    from types import SimpleNamespace

    from recognition.localisation import VerifyParams, agreement

    shape = (20, 20)
    labels = np.zeros(shape, np.int32)
    desc = SimpleNamespace(labels=labels, sigma=np.full(shape, 1e-3),
                           patches=(SimpleNamespace(id=0, n_pixels=400),))
    scan = SimpleNamespace(range=np.full(shape, 2.0))
    pred_range = np.full(shape, 2.0)
    pred_range[:, :6] = 1.5  # a pipe predicted in front of 30 % of the wall, missing from the scene
    pred = SimpleNamespace(stride=1, offset=0, range=pred_range)
    score, _ = agreement(desc, scan, pred, VerifyParams(stride=1))
    assert score == pytest.approx(1.0)
    score, _ = agreement(desc, scan, pred, VerifyParams(stride=1, seen_through=0.0))
    assert score == pytest.approx(0.7)
    wall = SimpleNamespace(stride=1, offset=0, range=np.full(shape, 1.0))  # everything predicted in front
    score, _ = agreement(desc, scan, wall, VerifyParams(stride=1))
    assert score == pytest.approx(0.0)
    with pytest.raises(ValueError, match="seen_through"):
        VerifyParams(seen_through=1.0)


def test_free_translation_only_for_one_pure_translation():
    from recognition.localisation.localise import free_translation

    t = np.zeros((6, 1))
    t[3:, 0] = [0.0, -2.0, 0.0]  # a (scaled) translation along -y
    np.testing.assert_allclose(free_translation(1, t), [0.0, -1.0, 0.0])
    r = np.zeros((6, 1))
    r[2, 0] = r[4, 0] = 1.0  # a rotation about z with a translation: a screw, not a slide
    assert free_translation(1, r) is None
    assert free_translation(2, np.hstack([t, t])) is None
    assert free_translation(0, np.zeros((6, 0))) is None


def test_slide_along_finds_the_agreement_peak_within_the_model_extent():
    from recognition.localisation.localise import slide_along

    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 1.5]
    d = np.array([0.0, 1.0, 0.0])
    points = np.array([[0.0, -4.0, 0.0], [5.0, 8.0, 3.0]])  # the model spans y in [-4, 8]
    calls = []

    def score(Ts):  # a peak at y = 6.3, flat 0.5 elsewhere (as an agreement along a bay)
        calls.append(Ts[1, 3])
        return 0.5 + 0.4 * max(0.0, 1.0 - abs(Ts[1, 3] - 6.3) / 0.6)

    out = slide_along(T, d, points, score, 32)
    assert abs(out[1, 3] - 6.3) <= 0.375 / 4 + 1e-9  # within a quarter of the coarse step (12 m / 32)
    np.testing.assert_array_equal(out[:3, :3], T[:3, :3])
    assert out[0, 3] == 1.0 and out[2, 3] == 1.5
    assert min(calls) >= -4.0 - 1e-9 and max(calls) <= 8.0 + 0.375 + 1e-9
    # no peak: the unslid pose is kept
    np.testing.assert_array_equal(slide_along(T, d, points, lambda Ts: 0.5, 32), T)


@pytest.mark.slow
def test_a_pose_free_along_a_wall_is_not_claimed():
    """Kinect-like view of a floor, a wall and a pipe run along it (the elbow and the next section too
    small or merged to be paired): the pairs leave the sensor free along the wall. Slid along it by
    agreement, the pose is right (1 mm), but reported underconstrained, not ok. (Segmented without the
    border reassignment, with which a pipe section pairs and fixes the pose: 0.26 deg, 11 mm, ok.)

    The search runs without the width test: with it, the wall patch has fewer candidates and comes first in
    the search order, and the 20 partial assignments handed on, which all score alike, are the first found:
    its patch paired with the floor, the floor's with walls, 90-180 deg off. The right one is not among
    them, and sliding those puts the sensor 0.8 m off, not ok either. What this test pins is the sliding.

    Since c8864fb the partial assignments that score alike are ordered by their pairs (a tie rule, so that the
    floating-point path does not order them), not as found, and the right one is no longer among the first
    slid: the pose ends 0.8 m off along the wall (and ICP finds too few pairs to refine it), still not claimed.
    The sliding itself is pinned by test_slide_along_finds_the_agreement_peak_within_the_model_extent."""
    from dataclasses import replace

    from harness.suite import load_suite
    from harness.trial import sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import DescribeParams, describe
    from sensors.simulate import Simulator

    spec = next(t for t in load_suite("classic").trials if t.trial_id == "factory_bay-p0-v2-kinect_like-n0")
    p = first_phase_scene(spec, "factory_bay-p0")
    cfg = sensor_for(spec)
    scan, truth = trial_scan(spec, p, cfg, trial_viewpoints(spec, p, cfg).viewpoints[0].T_world_sensor)
    dp = DescribeParams()
    desc = describe(scan, replace(dp, segmentation=replace(dp.segmentation, reassign_rounds=0)))
    sim = Simulator.from_scene(p.apriori)
    median_range = float(np.nanmedian(truth.true_range))
    lp = LocaliseParams()
    lp = replace(lp, match=replace(lp.match, width_test=False))
    res = localise(desc, scan, p.apriori, lp, model_simulator=sim)
    sec = pose_section(res, truth.T_world_sensor, median_range, True, None)
    assert not res.ok and not sec["success"], (res.reason, sec)
    off = localise(desc, scan, p.apriori, replace(lp, slide_steps=0), model_simulator=sim)
    assert pose_section(off, truth.T_world_sensor, median_range, True, None)["translation_error_mm"] > 500.0


def first_phase_scene(spec, name: str):
    """The trial's scene with the perturbation the first phase drew for it (``tests/data/first_phase_draws``,
    written by the perturbation engine of commit 0b5908a): the cases these tests pin were found on those draws,
    which the scene-dependent draws of today no longer give."""

    from harness.trial import PreparedScene, apriori_model
    from recognition.localisation.prediction import ModelPredictor
    from scenes.model import SceneModel
    from scenes.perturb import ChangeTruth
    from sensors.simulate import Simulator

    d = _support.DATA / "first_phase_draws" / name
    apriori = apriori_model(spec)
    actual = SceneModel.load(d / "actual.yaml")
    truth = ChangeTruth.from_json((d / "truth.json").read_text(encoding="utf-8"))
    return PreparedScene(apriori, actual, truth, Simulator.from_scene(actual), ModelPredictor(apriori))


@pytest.mark.slow
def test_a_corner_of_a_bay_that_other_corners_look_like_is_ambiguous_not_ok():
    """Calibration's factory bay seen into a corner (the floor and two walls, no wall's end): the main search
    spent its 20 hypotheses without the corner the sensor faces and returned ok, 90 deg and 10.7 m off, at
    confidence 0.85 (at 725e914); the other interpretations of the winner's three patches
    (``LocaliseParams.max_reinterpretations``) include that corner, whose agreement is the winner's: the pose is
    ambiguous."""
    from harness.suite import load_suite
    from harness.trial import prepare_scene, sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import describe

    spec = next(t for t in load_suite("calibration").trials
                if t.trial_id == "factory-s2005-p10-v0-factory_scanner-n0")
    p = prepare_scene(spec, None)
    cfg = sensor_for(spec)
    scan, truth = trial_scan(spec, p, cfg, trial_viewpoints(spec, p, cfg).viewpoints[0].T_world_sensor)
    res = localise(describe(scan), scan, p.apriori, model_simulator=p.predictor.simulator)
    sec = pose_section(res, truth.T_world_sensor, float(np.nanmedian(truth.true_range)), True, None)
    assert not res.ok and res.reason.startswith("ambiguous"), (res.reason, sec)
    assert min(_support.angle_deg(a.T_world_sensor, truth.T_world_sensor) for a in res.alternatives) < 1.0 \
        or sec["success"]



def _room_scan(cabinets: list[tuple[str, float]]):
    """A floor, a wall 3 m ahead and cabinets against it (``(id, x)``), seen noise-free by a camera 1.2 m up
    looking at the wall: the scan, the model's prediction from the true pose, the model and that pose."""
    from recognition.localisation.prediction import predict
    from scenes import builders
    from scenes.model import SceneModel
    from sensors.noise import NoiseModel
    from sensors.range_image import Scan
    from sensors.simulate import Simulator

    objects = [builders.floor("floor", 12.0, 12.0), builders.wall("wall", (0.0, 3.1, 0.0), 0.0, 10.0, 2.5, 0.2)]
    objects += [builders.cabinet(oid, (x, 2.6, 0.0), 0.0, (0.8, 0.6, 1.5)) for oid, x in cabinets]
    model = SceneModel("room", tuple(objects))
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # x right, y down (-z), z forward (+y)
    T[:3, 3] = [0.0, -1.0, 1.2]
    cam = PinholeCamera.from_fov(160, 120, 70.0, min_range=0.3, max_range=20.0)
    sim = Simulator.from_scene(model)
    pred = predict(sim, cam, T, 1)
    scan = Scan(range=pred.range, points=pred.points_sensor(), sensor=cam, noise=NoiseModel(enabled=False))
    return scan, pred, model, T


@pytest.mark.parametrize("cabinets, rests_on", [([("cab_a", -1.5)], "cab_a"),
                                                 ([("cab_a", -1.5), ("cab_b", 1.5)], "")])
def test_icp_says_which_movable_object_alone_fixes_the_pose(cabinets, rests_on):
    """A floor and a wall fix all but the translation along the wall; one cabinet fixes that too, alone: had it
    moved, the pose would have moved with it, so the ICP reports the direction left free without it. With two
    cabinets no one object carries a direction (issue 34: ok poses 6-11 deg off that a changed object fixed)."""
    from recognition.localisation.icp import IcpParams, icp_refine

    scan, pred, model, T = _room_scan(cabinets)
    ir = icp_refine(scan, pred, model, T, IcpParams())
    assert ir.ok and ir.free_dof == 0, ir
    assert ir.resting_on == rests_on
    assert (ir.free_dof_without_one > 0) == bool(rests_on)


def test_a_pose_resting_on_one_movable_object_is_not_ok_but_conditional_on_it(monkeypatch):
    """The verdict reads the ICP's leave-one-object-out: the same view is ok while the rest of it fixes the
    pose without any one object, and not ok, saying which object it rests on, once it does not: the pose with
    that object moved along what it alone fixes explains the data as well (issue 34: a mock-up pose 16 mm off,
    ok at 0.94, resting on a tank moved 8 mm). Such a pose is conditional on the object and usable for change
    detection while the rest fixes enough (``conditional_max_free``); one failing another check is not."""
    import importlib
    from dataclasses import replace

    from recognition.describe import describe
    from sensors.simulate import Simulator

    localise_module = importlib.import_module("recognition.localisation.localise")  # (the package exports the function)

    scan, _, model, T = _room_scan([("cab_a", -1.5), ("cab_b", 1.5)])
    desc, sim = describe(scan), Simulator.from_scene(model)
    res = localise(desc, scan, model, model_simulator=sim)
    assert res.ok and res.conditional_on == "" and res.usable, res.reason
    real = localise_module.icp_refine
    free_without = {"k": 1}

    def resting(*args, **kwargs):  # the same refinement, said to rest on cab_a for k DOF
        return replace(real(*args, **kwargs), free_dof_without_one=free_without["k"], resting_on="cab_a")

    monkeypatch.setattr(localise_module, "icp_refine", resting)
    for k in (1, 3, 4):
        free_without["k"] = k
        res = localise(desc, scan, model, model_simulator=sim)
        assert not res.ok and res.reason.startswith(f"pose rests on cab_a alone: {k} DOF free without it"), res.reason
        assert res.conditional_on == ("cab_a" if k <= 3 else "") and res.usable == (k <= 3)
        assert np.allclose(res.T_world_sensor, T, atol=1e-3)
    loose = localise(desc, scan, model, LocaliseParams(max_free_without_one=4), model_simulator=sim)
    assert loose.ok and loose.conditional_on == "" and loose.usable
    free_without["k"] = 1  # not pinned within a tolerance of 1e-9 deg: not ok for that, so conditional on nothing
    strict = localise(desc, scan, model, LocaliseParams(pin_angle_deg=1e-9, pin_rel=1e-9), model_simulator=sim)
    assert not strict.ok and strict.conditional_on == "" and not strict.usable, strict.reason


def test_icp_counts_the_directions_the_rest_fixes_no_better_than_a_tolerance():
    """Without one movable object, a direction is loose when the rest fixes it no better than the tolerance: with
    two cabinets no one object frees a direction (0.1 rad), but against a tolerance of 1e-9 deg and 1e-9 of the
    range every direction the rest leaves any spread is loose, and against 60 deg and 100 % none is; the
    count never falls below the free one, and without a tolerance it is the free one."""
    from recognition.localisation.icp import IcpParams, icp_refine
    from sensors.noise import NoiseModel
    from sensors.range_image import Scan

    scan, pred, model, T = _room_scan([("cab_a", -1.5), ("cab_b", 1.5)])
    g = np.random.default_rng(0)
    noisy = scan.range + g.normal(0.0, 0.002, scan.range.shape)
    rays = scan.points / scan.range[..., None]
    scan = Scan(range=noisy, points=rays * noisy[..., None], sensor=scan.sensor, noise=NoiseModel(enabled=False))
    base = icp_refine(scan, pred, model, T, IcpParams())
    assert base.ok and base.free_dof_without_one == 0 and base.resting_on == ""
    assert (base.loose_without_one, base.loose_on) == (base.free_dof_without_one, base.resting_on)
    tight = icp_refine(scan, pred, model, T, IcpParams(), tolerance=(1e-9, 1e-9))
    assert tight.loose_without_one == 6 and tight.loose_on in ("cab_a", "cab_b")
    assert tight.free_dof_without_one == base.free_dof_without_one
    wide = icp_refine(scan, pred, model, T, IcpParams(), tolerance=(60.0, 1.0))
    assert wide.loose_without_one == 0 and wide.loose_on == ""


def test_a_pose_the_rest_fixes_only_loosely_without_one_object_is_conditional_on_it(monkeypatch):
    """``rest_within_tolerance``: the ICP is given the success tolerance an ok pose claims (``pin_angle_deg``,
    ``pin_rel``), and a pose whose other surfaces fix a direction no better than that without one object is not
    ok but conditional on it, and usable (issue 34: a Kinect-like pose 5.3 deg off at confidence 0.91, on a
    moved pipe run that the rest of its view fixed to about 5 deg). Off, the ICP gets no tolerance."""
    import importlib
    from dataclasses import replace

    from recognition.describe import describe
    from sensors.simulate import Simulator

    localise_module = importlib.import_module("recognition.localisation.localise")
    scan, _, model, T = _room_scan([("cab_a", -1.5), ("cab_b", 1.5)])
    desc, sim = describe(scan), Simulator.from_scene(model)
    real = localise_module.icp_refine
    seen = []

    def loose(*args, **kwargs):  # the same refinement, said to be fixed only loosely without cab_b
        seen.append(args[6] if len(args) > 6 else kwargs.get("tolerance"))
        return replace(real(*args, **kwargs), loose_without_one=1, loose_on="cab_b")

    monkeypatch.setattr(localise_module, "icp_refine", loose)
    params = LocaliseParams(pin_angle_deg=1.0, pin_rel=0.01)
    res = localise(desc, scan, model, params, model_simulator=sim)
    assert (1.0, 0.01) in seen
    assert not res.ok and res.conditional_on == "cab_b" and res.usable, res.reason
    assert res.reason.startswith("pose rests on cab_b alone: without it the rest fixes 1 DOF no better than 1 deg")
    seen.clear()
    localise(desc, scan, model, replace(params, rest_within_tolerance=False), model_simulator=sim)
    assert None in seen and (1.0, 0.01) not in seen


def _alternatives_in_a_room_with_a_moved_cabinet(name: str):
    """A room (a floor, a wall, six cabinets) whose cabinet ``cab_a`` stands 10 cm nearer the camera than the
    model has it, seen from the true pose ``T``; the alternative ``localise.<name>`` finds from ``T`` and from the
    pose the cabinet holds (the camera 10 cm further along y). Returns ``(right, held_alt, T, held, params)``."""
    import importlib

    from recognition.describe import describe
    from recognition.localisation.prediction import predict
    from scenes import builders
    from scenes.model import SceneModel
    from sensors.noise import NoiseModel
    from sensors.range_image import Scan
    from sensors.simulate import Simulator

    localise_module = importlib.import_module("recognition.localisation.localise")
    ask = getattr(localise_module, name)

    def room(cab_a_y: float) -> SceneModel:
        objects = [builders.floor("floor", 12.0, 12.0), builders.wall("wall", (0.0, 3.1, 0.0), 0.0, 10.0, 2.5, 0.2),
                   builders.cabinet("cab_a", (-0.4, cab_a_y, 0.0), 0.0, (0.6, 0.6, 1.5))]
        objects += [builders.cabinet(f"cab_{k}", (x, 2.6, 0.0), 0.4 * x, (0.5, 0.4, 0.5 + 0.3 * k))
                    for k, x in enumerate((-2.2, -1.3, 0.6, 1.5, 2.4))]
        return SceneModel("room", tuple(objects))

    actual, model = room(2.5), room(2.6)  # cab_a stands 10 cm nearer the camera than the model has it
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # x right, y down (-z), z forward (+y)
    T[:3, 3] = [0.0, -1.0, 1.2]
    cam = PinholeCamera.from_fov(160, 120, 70.0, min_range=0.3, max_range=20.0)
    seen = predict(Simulator.from_scene(actual), cam, T, 1)
    scan = Scan(range=seen.range, points=seen.points_sensor(), sensor=cam, noise=NoiseModel(enabled=False))
    desc, sim = describe(scan), Simulator.from_scene(model)
    params = LocaliseParams()
    held = T.copy()
    held[:3, 3] += [0.0, 0.1, 0.0]  # the camera 10 cm further along y: cab_a where the model has it
    found = []
    for T_final in (T, held):
        timing = {"verification": 0.0, "icp": 0.0}
        final = localise_module._verified(desc, scan, sim, T_final, params, timing)
        found.append(ask(desc, scan, model, sim, final, params, timing, 3.0))
    return found[0], found[1], T, held, params


def test_the_pose_the_unexplained_patches_ask_for_is_an_alternative():
    """Issue 34: a moved cabinet can hold a pose, and the unchanged surfaces are then the ones left unexplained.
    The patches a pose leaves unexplained are registered alone: from the right pose they are the moved cabinet,
    whose pose misplaces the wall and the floor (well separated: the verdict stands); from the pose the cabinet
    holds they are the wall, the floor and the other cabinet, whose pose is the true one (the data prefer it:
    not separated, so the held pose cannot be called ok)."""
    right, held_alt, T, held, params = _alternatives_in_a_room_with_a_moved_cabinet("_disagreeing_alternative")
    assert right is not None and held_alt is not None
    assert right.separation > params.separation_z  # the cabinet's pose misplaces the rest: the right pose stands
    off = np.linalg.norm(held_alt.T_world_sensor[:3, 3] - T[:3, 3])
    assert off < 0.5 * np.linalg.norm(held[:3, 3] - T[:3, 3])  # the rest's pose is near the true one...
    assert held_alt.separation < params.separation_z  # ... and the data do not prefer the held pose to it


def test_the_pose_the_unexplained_wall_asks_for_is_an_alternative():
    """The same room. From the pose the cabinet holds, the wall and the floor are left unexplained: the stable
    structure's alternative (the wall registered alone in the directions it fixes, then the whole view) is near
    the true pose and the held pose is not separated from it; the moved cabinet's patches count on neither side.
    From the right pose only the moved cabinet disagrees, which is not stable structure: no such alternative."""
    right, held_alt, T, _, params = _alternatives_in_a_room_with_a_moved_cabinet("_stable_alternative")
    assert right is None
    assert held_alt is not None
    assert np.linalg.norm(held_alt.T_world_sensor[:3, 3] - T[:3, 3]) < 0.02
    assert held_alt.separation < params.separation_z


def test_icp_on_a_wall_alone_moves_the_pose_only_in_the_directions_the_wall_fixes():
    """A wall's points registered from a pose 10 cm off along its normal and 20 cm along it: the pose comes onto
    the wall (its normal offset and tilts fixed) and keeps the 20 cm along it, which a wall cannot fix - an
    unconstrained ICP would drift there until nothing corresponds."""
    from recognition.localisation.icp import icp_fixed_directions
    from recognition.localisation.prediction import predict
    from scenes import builders
    from scenes.model import SceneModel
    from sensors.noise import NoiseModel
    from sensors.range_image import Scan
    from sensors.simulate import Simulator

    model = SceneModel("room", (builders.floor("floor", 12.0, 12.0),
                                builders.wall("wall", (0.0, 3.1, 0.0), 0.0, 10.0, 2.5, 0.2)))
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # looking along +y at the wall
    T[:3, 3] = [0.0, -1.0, 1.2]
    cam = PinholeCamera.from_fov(160, 120, 70.0, min_range=0.3, max_range=20.0)
    sim = Simulator.from_scene(model)
    seen = predict(sim, cam, T, 1)
    scan = Scan(range=seen.range, points=seen.points_sensor(), sensor=cam, noise=NoiseModel(enabled=False))
    wall = np.array([s.feature_id.startswith("wall") for s in seen.surfaces] + [False])[seen.surface_id]
    start = T.copy()
    start[:3, 3] += [0.2, 0.1, 0.0]  # 20 cm along the wall, 10 cm towards it
    res = icp_fixed_directions(scan, predict(sim, cam, start, 2), model, start, wall, reach_m=0.5)
    assert res.ok and res.free_dof == 3
    assert res.T_world_sensor[1, 3] == pytest.approx(T[1, 3], abs=1e-3)  # onto the wall
    assert res.T_world_sensor[0, 3] == pytest.approx(start[0, 3], abs=1e-3)  # along it: where it started
    assert np.allclose(res.T_world_sensor[:3, :3], T[:3, :3], atol=1e-3)


def test_the_separation_leaves_out_the_patches_of_the_one_object_that_most_favours_a_side():
    """Patches 1 and 2 are one moved tank's (and patch 3 sees its old place): together they favour A; patch 4, a
    wall, favours B. Patch by patch, leaving out one (patch 1) keeps A ahead; by object, the tank's three
    patches go and B is ahead; B's one unit, the lone patch 4, goes too."""
    from types import SimpleNamespace

    from recognition.localisation.localise import agreement_separation

    desc = SimpleNamespace(patches=[SimpleNamespace(id=k, n_pixels=1000) for k in range(1, 7)])
    a = {1: 1.0, 2: 1.0, 3: 1.0, 4: 0.0, 5: 0.9, 6: 0.9}
    b = {1: 0.1, 2: 0.2, 3: 0.3, 4: 1.0, 5: 1.0, 6: 1.0}
    objects = {1: frozenset({"tank"}), 2: frozenset({"tank"}), 3: frozenset({"tank", "cab"})}
    d_patch, _ = agreement_separation(desc, a, b, leave_out=1)
    assert d_patch == pytest.approx((0.8 + 0.7 - 1.0 - 0.1 - 0.1) / 5)
    d_object, _ = agreement_separation(desc, a, b, objects=objects)
    assert d_object == pytest.approx((-0.1 - 0.1) / 2)
    assert d_patch > 0 > d_object
