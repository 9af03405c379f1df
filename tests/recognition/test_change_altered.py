"""``altered`` for every kind the perturbation alters (issue #34 item 2): hand-made scenes seen from a known pose,
with the truth segmentation and classification (oracles) so that the change stage alone is tested; the
statistical tests on their own; and ``change.altered_by_kind`` in the summary."""

import math

import numpy as np
import pytest

from evaluation.aggregate import aggregate_change
from evaluation.oracles import truth_classification, truth_segmentation
from recognition.change import ChangeParams, detect_changes
from recognition.change.detection import _agrees, _same_place, _same_shape
from recognition.change.extent import GROWN, SHRUNK, _stretch, extent_changes, outgrows, ray_hits, return_expected
from recognition.describe import core_sigma, describe
from recognition.localisation import ModelPredictor
from scenes import builders
from scenes.features import Cylinder, Plane, Sphere, Torus
from scenes.geometry import look_at
from scenes.model import SceneModel
from sensors.config import sensor_from_yaml
from sensors.simulate import Simulator

SENSOR = """
schema: sensor/1
name: test_cam
pinhole: {width: 320, height: 240, fov_deg: 60.0, min_range: 0.3, max_range: 12.0}
noise:
  range: {model: ray, s0_m: 3.0e-4, s2_per_m: 5.0e-5, max_incidence_deg: 80}
"""


def _labels(apriori_part, actual_part):
    """Change labels of the features of a scene of a floor, a wall and one part (a priori and actual), seen
    from the front and above with the true pose."""
    floor = builders.floor("floor", 8.0, 6.0)
    wall = builders.wall("wall", (0.0, 2.0, 0.0), 0.0, 8.0, 3.0, 0.2)
    apriori = SceneModel("t", (floor, wall, apriori_part))
    actual = SceneModel("t", (floor, wall, actual_part))
    T = look_at([0.5, -4.0, 2.4], [0.0, 0.5, 0.6])
    scan, truth = Simulator.from_scene(actual).simulate(sensor_from_yaml(SENSOR), T, np.random.default_rng(0))
    desc = truth_classification(describe(scan, segmentation=truth_segmentation(scan, truth, core_sigma(scan))), truth)
    result = detect_changes(desc, scan, apriori, truth.T_world_sensor, predictor=ModelPredictor(apriori))
    seen = {fid: r.label for fid, r in result.features.items() if r.label != "unobserved"}
    return seen, result


def _cabinet(size):
    return builders.cabinet("cab", (-1.0, 0.3, 0.0), 0.3, size)


def _tank(radius, height):
    return builders.tank("tank", (1.0, 0.5, 0.0), radius, height)


def _sphere_tank(radius):
    return builders.sphere_tank("sph", (1.0, 0.5, 0.0), radius, 0.5)


@pytest.mark.parametrize("part", [_cabinet((0.8, 0.5, 0.9)), _tank(0.4, 1.0), _sphere_tank(0.4)],
                         ids=["cabinet", "tank", "sphere_tank"])
def test_an_unchanged_part_stays_unchanged(part):
    seen, result = _labels(part, part)
    assert seen and set(seen.values()) == {"unchanged"}, seen
    assert result.new_patches == ()


@pytest.mark.parametrize("height", [1.2, 0.65], ids=["taller", "shorter"])
def test_a_cabinet_of_another_height_is_altered(height):
    """Its front face reaches beyond the model's top edge (taller) or ends before it where the wall behind shows
    (shorter); the top, found displaced along its normal, was altered with it - never moved or unchanged."""
    seen, result = _labels(_cabinet((0.8, 0.5, 0.9)), _cabinet((0.8, 0.5, height)))
    assert seen["cab.yn"] == "altered", result.features["cab.yn"]
    assert result.features["cab.yn"].reason.startswith("extent differs")
    assert (GROWN if height > 0.9 else SHRUNK) in result.features["cab.yn"].reason
    assert seen["cab.zp"] == "altered"
    assert result.objects["cab"] == "altered"
    assert seen["wall.yn"] == seen["floor.top"] == "unchanged"


def test_a_wider_cabinet_is_altered():
    seen, result = _labels(_cabinet((0.8, 0.5, 0.9)), _cabinet((1.1, 0.5, 0.9)))
    assert seen["cab.yn"] == "altered" and "grown" in result.features["cab.yn"].reason
    assert result.objects["cab"] == "altered"


@pytest.mark.parametrize(("radius", "height"), [(0.55, 1.0), (0.3, 1.0), (0.4, 1.35), (0.4, 0.7)],
                         ids=["wider", "narrower", "taller", "shorter"])
def test_a_tank_of_another_radius_or_height_is_altered(radius, height):
    seen, result = _labels(_tank(0.4, 1.0), _tank(radius, height))
    assert seen["tank.body"] == "altered", result.features["tank.body"]
    assert seen["tank.top"] == "altered", result.features["tank.top"]
    assert result.objects["tank"] == "altered"


@pytest.mark.parametrize("radius", [0.55, 0.3], ids=["larger", "smaller"])
def test_a_spherical_tank_of_another_radius_is_altered_not_missing(radius):
    """The ball keeps its base: its centre moves by the radius change, and it is still the same ball."""
    seen, result = _labels(_sphere_tank(0.4), _sphere_tank(radius))
    assert seen["sph.ball"] == "altered", result.features["sph.ball"]
    assert result.objects["sph"] == "altered"


def test_shape_parameters_agree_disagree_or_say_nothing_within_the_margin():
    """A fitted value agrees within max(tolerance, k sigma), disagrees beyond that bound times 1 + margin, and in
    between says nothing (no verdict on a coin flip at the bound)."""
    p = ChangeParams(shape_k_sigma=4.0, shape_margin=0.25)
    assert _agrees(1.05, 1.0, 0.001, 0.1, p) is True
    assert _agrees(1.11, 1.0, 0.001, 0.1, p) is None  # within 0.1 * 1.25
    assert _agrees(1.2, 1.0, 0.001, 0.1, p) is False
    assert _agrees(1.2, 1.0, 0.06, 0.1, p) is True  # 4 sigma = 0.24: the fit cannot tell
    assert _agrees(math.nan, 1.0, 0.001, 0.1, p) is None
    elbow = Torus("run.e0", centre=np.zeros(3), axis=np.array([0, 0, 1.0]), major_radius=0.3, minor_radius=0.1,
                  start=np.array([1.0, 0, 0]), sweep=np.pi / 2)
    fit = {"torus_centre": np.array([0.005, 0, 0]), "torus_axis": np.array([0, 0, 1.0]), "major_radius": 0.31,
           "minor_radius": 0.14, "minor_radius_sigma": 0.002}
    assert _same_place(elbow, fit, 0.01) and _same_shape(elbow, fit, p) is False  # an elbow of another pipe radius
    assert _same_shape(elbow, {**fit, "minor_radius": 0.102}, p) is True
    cone_fit = {"apex": np.zeros(3), "axis": np.array([0, 0, 1.0]), "half_angle": math.radians(20),
                "half_angle_sigma": math.radians(0.2)}
    from scenes.features import Cone

    cone = Cone("run.r0", apex=np.zeros(3), axis=np.array([0, 0, 1.0]), half_angle=math.radians(14), start=0.2,
                end=0.4)
    assert _same_shape(cone, cone_fit, p) is False
    assert _same_shape(cone, {**cone_fit, "half_angle_sigma": math.radians(3)}, p) is True


def test_a_ball_of_another_radius_on_its_base_and_a_cap_on_a_longer_body_are_in_place():
    ball = Sphere("b", centre=np.array([0, 0, 1.0]), radius=0.4)
    grown = {"centre": np.array([0, 0, 1.15]), "radius": 0.55}
    assert _same_place(ball, grown, 0.01)
    assert not _same_place(ball, {"centre": np.array([0.3, 0, 1.0]), "radius": 0.41}, 0.01)  # moved aside
    assert not _same_place(ball, {"centre": np.array([0, 0, 19.0]), "radius": 18.0}, 0.01)  # a flat face's fit
    cap = Sphere("t", centre=np.array([0, 0, 1.0]), radius=0.4, cap_axis=np.array([0, 0, 1.0]), cap_height=0.4)
    assert _same_place(cap, {"centre": np.array([0, 0, 1.35]), "radius": 0.4}, 0.01)


def test_extent_changes_of_a_plane_from_pixels():
    """The edge logic on its own: pixels beyond the +u edge on the face's plane grow it; the face's explained
    pixels ending before the -u edge with the background past it shrink it; both at once on one axis is a
    slide (no verdict)."""
    face = Plane("f", centre=np.zeros(3), normal=np.array([0, 0, 1.0]), u_axis=np.array([1.0, 0, 0]),
                 half_size=(0.5, 0.5))
    origin = np.array([0, 0, 3.0])
    xs, ys = np.meshgrid(np.linspace(-0.9, 0.9, 91), np.linspace(-0.45, 0.45, 46))
    targets = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    rays = (targets - origin) / np.linalg.norm(targets - origin, axis=1, keepdims=True)
    assert np.allclose(ray_hits(face, origin, rays), targets)
    n = len(targets)
    margin, allowance = np.full(n, 0.01), np.full(n, 0.005)
    inside = np.flatnonzero(np.abs(xs.ravel()) <= 0.5)
    x = xs.ravel()

    def edges(found, revealed, candidates):
        return extent_changes(face, origin, rays, targets, margin, allowance, found, revealed, inside, candidates,
                              20, 0.5, 0.05)

    grown = edges(inside, np.zeros(0, int), np.flatnonzero(x > 0.6))
    assert [(e.axis, e.side, e.kind) for e in grown] == [(0, 1, GROWN)] and grown[0].amount_m == pytest.approx(0.25,
                                                                                                             abs=0.02)
    found = inside[x[inside] > -0.3]
    shrunk = edges(found, inside[x[inside] <= -0.3], np.zeros(0, int))
    assert [(e.axis, e.side, e.kind) for e in shrunk] == [(0, -1, SHRUNK)]
    assert shrunk[0].amount_m == pytest.approx(0.2, abs=0.03)
    assert edges(found, inside[x[inside] <= -0.3], np.flatnonzero(x > 0.6)) == []  # a slide along u
    assert edges(inside, np.zeros(0, int), np.zeros(0, int)) == []


def test_a_footprint_stretches_along_the_incidence_plane_only():
    """On the plane z = 0 a ray at incidence i in the x-z plane: a footprint across it lengthens by 1 / cos i along
    x, not along y; in between by sqrt(1 + (a.e)² tan² i); cos i is held at 0.2 or more. On a cylinder the same
    along its axis, with the radial normal at the hit."""
    face = Plane("f", centre=np.zeros(3), normal=np.array([0, 0, 1.0]), u_axis=np.array([1.0, 0, 0]),
                 half_size=(1.0, 1.0))
    for deg in (0.0, 30.0, 60.0, 85.0):
        i = math.radians(deg)
        ray = np.array([[math.sin(i), 0.0, -math.cos(i)]])
        hit = ray_hits(face, np.array([0, 0, 1.0]), ray)
        cos = max(math.cos(i), 0.2)
        diag = np.array([1.0, 1.0, 0]) / math.sqrt(2)
        along_x, along_y, along_diag = _stretch(face, ray, hit, [np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), diag])
        assert along_x[0] == pytest.approx(1 / cos)
        assert along_y[0] == pytest.approx(1.0)
        assert along_diag[0] == pytest.approx(math.sqrt(1 + 0.5 * (1 / cos**2 - 1)))
    pipe = Cylinder("p", centre=np.zeros(3), axis=np.array([0, 0, 1.0]), radius=0.5, length=2.0)
    i = math.radians(60)
    ray = np.array([[-math.cos(i), 0.0, math.sin(i)]])  # meets the side at x = 0.5 from (2.5, 0, z0)
    origin = np.array([2.5, 0.0, -2.0 * math.tan(i)])
    hit = ray_hits(pipe, origin, ray)
    assert hit[0] == pytest.approx([0.5, 0.0, 0.0], abs=1e-9)
    assert _stretch(pipe, ray, hit, [pipe.axis])[0, 0] == pytest.approx(1 / math.cos(i))


def test_an_edge_margin_is_stretched_along_the_incidence_plane_only():
    """A face seen obliquely along v (about 76 deg incidence), a margin of 0.05 m across the ray: a strip grown
    0.1 m beyond its +u edge moves that edge (the footprint is not stretched along u), the same strip beyond its +v
    edge does not (along v the margin is about 4.7 times longer there, 0.24 m); a strip 0.3-0.4 m beyond it does."""
    face = Plane("f", centre=np.zeros(3), normal=np.array([0, 0, 1.0]), u_axis=np.array([1.0, 0, 0]),
                 half_size=(0.5, 0.5))
    origin = np.array([0.0, -4.0, 1.0])
    xs, ys = np.meshgrid(np.linspace(-0.9, 0.9, 73), np.linspace(-0.9, 0.9, 73))
    targets = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    rays = (targets - origin) / np.linalg.norm(targets - origin, axis=1, keepdims=True)
    n = len(targets)
    x, y = xs.ravel(), ys.ravel()
    inside = np.flatnonzero((np.abs(x) <= 0.5) & (np.abs(y) <= 0.5))
    across = np.full(n, 0.05)

    def edges(cand):
        return extent_changes(face, origin, rays, targets, across, np.full(n, 0.005), inside, np.zeros(0, int),
                              inside, cand, 20, 0.5, 0.05)

    grown = edges(np.flatnonzero((x > 0.55) & (x <= 0.6) & (np.abs(y) <= 0.5)))
    assert [(e.axis, e.side, e.kind) for e in grown] == [(0, 1, GROWN)]
    assert edges(np.flatnonzero((y > 0.55) & (y <= 0.6) & (np.abs(x) <= 0.5))) == []
    further = edges(np.flatnonzero((y > 0.8) & (y <= 0.9) & (np.abs(x) <= 0.5)))  # beyond 0.05 / cos i
    assert [(e.axis, e.side, e.kind) for e in further] == [(1, 1, GROWN)]


def test_a_patch_outgrows_a_face_only_when_it_is_larger_along_some_direction():
    """Points of a patch on a 1.0 x 0.5 face's plane: a part of the face, or the whole face turned within its
    plane (whose own axes would see its diagonal), does not outgrow it; a 1.3 x 0.5 or a 1.0 x 0.7 rectangle
    does, whatever its turn, at 5 % tolerance and a 1 cm margin; a thin diagonal strip across the face (longer
    than its side, in its own frame) does not."""
    face = Plane("f", centre=np.zeros(3), normal=np.array([0, 0, 1.0]), u_axis=np.array([1.0, 0, 0]),
                 half_size=(0.5, 0.25))
    rng = np.random.default_rng(0)

    def rect(a, b, turn=0.0, n=4000):
        xy = (rng.uniform(-0.5, 0.5, (n, 2)) * [a, b]) @ np.array([[np.cos(turn), np.sin(turn)],
                                                                  [-np.sin(turn), np.cos(turn)]])
        return np.column_stack([xy, np.full(n, 0.3)])  # on a parallel plane, displaced along the normal

    def grows(pts, normal=(0, 0, 1.0)):
        return outgrows(face, pts, np.array(normal), 0.01, 0.05)

    assert not grows(rect(1.0, 0.5))
    assert not grows(rect(0.6, 0.3))
    assert not grows(rect(1.0, 0.5, turn=0.5))
    assert not grows(rect(1.0, 0.5), normal=(0, 0, -1.0))  # a normal fitted the other way round
    for turn in (0.0, 0.3, 1.2):
        assert grows(rect(1.3, 0.5, turn)) and grows(rect(1.0, 0.7, turn))
    t = rng.uniform(-0.5, 0.5, 4000)
    strip = np.column_stack([t * 1.0, t * 0.5 + rng.normal(0, 0.005, t.size), np.zeros(t.size)])
    assert np.ptp(strip[:, :2] @ np.array([2.0, 1.0]) / np.sqrt(5.0)) > 1.05  # longer than the face's side
    assert not grows(strip)


def test_a_return_is_expected_from_a_surface_met_squarely_not_at_grazing_incidence():
    face = Plane("f", centre=np.zeros(3), normal=np.array([0, 0, 1.0]), u_axis=np.array([1.0, 0, 0]),
                 half_size=(0.5, 0.5))
    origin = np.array([0, 0, 1.0])
    angles = np.radians([0.0, 30.0, 60.0, 85.0, 100.0])  # from the normal; the last one points away
    rays = np.column_stack([np.sin(angles), np.zeros(5), -np.cos(angles)])
    expected = return_expected(face, origin, rays, np.cos(np.radians(75.0)))
    assert expected.tolist() == [True, True, True, False, False]


def test_no_return_shows_absence_only_where_nothing_near_borders_it():
    """Pixels without data where the model shows a surface in range: silent (nothing there) in a wide region -
    not in a thin strip (a face at grazing incidence drops out so), not where their region borders a return
    nearer than twice the least range (something in the blind zone may hide what lies behind), and not where the
    model's surface is outside the range limits."""
    from types import SimpleNamespace

    from recognition.change.detection import _no_return

    rng = np.full((40, 60), 2.0)
    rng[2:12, 2:12] = np.nan  # nothing there
    rng[20:30, 20:30] = np.nan  # a blind-zone occluder: its rim returns at 0.45 m
    rng[20:30, 30] = 0.45
    rng[2:12, 40:50] = np.nan  # no return where the model's surface is beyond the range limit
    rng[34:36, 2:40] = np.nan  # a strip two pixels wide
    predicted = np.full(rng.shape, 2.0)
    predicted[2:12, 40:50] = 30.0
    scan = SimpleNamespace(range=rng, valid=np.isfinite(rng),
                           sensor=SimpleNamespace(min_range=0.3, max_range=20.0))
    silent = _no_return(scan, SimpleNamespace(range=predicted), clearance=2.0)
    expected = np.zeros(rng.shape, bool)
    expected[2:12, 2:12] = True
    assert np.array_equal(silent, expected)
    assert _no_return(scan, SimpleNamespace(range=predicted), clearance=1.0)[20:30, 20:30].all()


def test_a_shortened_wall_with_nothing_behind_its_new_end_is_altered():
    """A wall 3 m shorter at each end, seen from inside the room: past its new ends there is no surface at all
    (no data), within the sensor's range and away from grazing incidence, so the wall ends where the model says
    it goes on: shrunk, altered. The unchanged wall stays unchanged."""
    floor = builders.floor("floor", 14.0, 6.0)
    cab = builders.cabinet("cab", (0.0, 0.5, 0.0), 0.0, (0.8, 0.5, 0.9))
    T = look_at([0.0, -4.0, 1.6], [0.0, 2.0, 1.2])

    def labels(length):
        apriori = SceneModel("t", (floor, builders.wall("wall", (0.0, 2.0, 0.0), 0.0, 12.0, 3.0, 0.2), cab))
        actual = SceneModel("t", (floor, builders.wall("wall", (0.0, 2.0, 0.0), 0.0, length, 3.0, 0.2), cab))
        scan, truth = Simulator.from_scene(actual).simulate(sensor_from_yaml(SENSOR), T, np.random.default_rng(0))
        desc = truth_classification(describe(scan, segmentation=truth_segmentation(scan, truth, core_sigma(scan))),
                                    truth)
        return detect_changes(desc, scan, apriori, truth.T_world_sensor, predictor=ModelPredictor(apriori))

    assert labels(12.0).features["wall.yn"].label == "unchanged"
    shortened = labels(6.0).features["wall.yn"]
    assert shortened.label == "altered" and SHRUNK in shortened.reason, shortened


def test_a_cabinet_larger_every_way_is_altered_not_moved():
    """Wider, deeper and taller about its base: every face it shows is found displaced along its normal (none in
    place to show an edge moved) and larger than the model's face: a resize, not a move."""
    seen, result = _labels(_cabinet((0.8, 0.5, 0.9)), _cabinet((1.1, 0.9, 1.2)))
    assert seen["cab.yn"] == "altered", result.features["cab.yn"]
    assert result.features["cab.yn"].reason == "found displaced, larger than the model's face"
    assert result.objects["cab"] == "altered"
    assert "moved" not in seen.values()


def test_an_unchanged_cabinet_whose_faces_one_patch_merges_is_unchanged(monkeypatch):
    """Its front and side faces segmented as one patch across their crease: the merged patch's plane fits
    neither face, so tight matching finds the front's fit off. Every point of the patch is explained where it is:
    it shows no face displaced (``changed_unexplained_fraction``), and with no displaced patch to confirm the fit's
    disagreement the front is where the model has it - unchanged, neither moved nor missing."""
    import evaluation.oracles as oracles

    part = builders.cabinet("cab", (-1.0, 0.3, 0.0), 0.6, (0.8, 0.5, 0.9))
    regions_of = oracles.truth_regions

    def merged(truth, valid):
        regions = regions_of(truth, valid)
        names = [s.feature_id for s in truth.surfaces]
        sid = np.where(regions >= 0, truth.surface_id, -1)
        front, side = (np.isin(sid, [i for i, n in enumerate(names) if n == fid]) for fid in ("cab.yn", "cab.xn"))
        assert front.sum() > 200 and side.sum() > 200  # both faces in view
        regions[side] = regions[front][0]
        return regions

    monkeypatch.setattr(oracles, "truth_regions", merged)
    seen, result = _labels(part, part)
    assert seen["cab.yn"] == seen["cab.xn"] == "unchanged", result.features["cab.yn"]
    assert result.new_patches == ()


def test_a_fit_on_a_patch_the_model_explains_alters_nothing():
    """A pipe section's patch fitted with a radius 16 % over the model's, 10 sigma off, alters it - unless every
    point of the patch lies on the model's surface within the allowance (``in_place``): then the data show no
    change, and the fit's disagreement is its own bias (a Kinect-like pipe at 2 m fits 0.117 m for 0.101 m)."""
    from recognition.change.detection import _altered_by_patches
    from scenes.features import Cylinder

    f = Cylinder("run.s0", centre=np.zeros(3), axis=np.array([0, 0, 1.0]), radius=0.101, length=1.6)
    prims = {7: {"point": np.zeros(3), "axis": np.array([0, 0, 1.0]), "radius": 0.117, "radius_sigma": 0.0016,
                 "axis_sigma": 0.01}}
    params = ChangeParams()
    assert _altered_by_patches(f, [7], prims, {7: 500}, params) == [7]
    assert _altered_by_patches(f, [7], prims, {7: 500}, params, in_place=frozenset({7})) == []


def test_altered_by_kind_appears_in_the_change_summary():
    rows = [{"feature": "cab.zp", "truth": "altered", "predicted": "altered", "kind": "cabinet"},
            {"feature": "cab.yn", "truth": "altered", "predicted": "moved", "kind": "cabinet"},
            {"feature": "tank.body", "truth": "unchanged", "predicted": "altered", "kind": "tank"},
            {"feature": "pipe.s0", "truth": "unchanged", "predicted": "unchanged", "kind": "pipe_run"},
            {"feature": "new0.s0", "truth": "new", "predicted": "new"}]
    out = aggregate_change([{"features": rows, "objects": [], "displacement_error_mm": []}])
    by_kind = out["altered_by_kind"]
    assert set(by_kind) == {"cabinet", "tank"}  # kinds with an altered feature in the truth or the prediction
    assert by_kind["cabinet"] == {"precision": 1.0, "recall": 0.5, "f1": pytest.approx(2 / 3), "support": 2}
    assert by_kind["tank"]["f1"] == 0.0 and by_kind["tank"]["support"] == 0
    assert out["false_alarm_rate"] == 0.5 and out["n_unchanged"] == 2
    # each new figure is declared once (direction, tolerance rule), its counts as informative
    from evaluation import metrics

    assert metrics.declaration(("change", "altered_by_kind", "cabinet", "f1")).direction == "higher"
    assert metrics.declaration(("change", "false_alarm_rate")).direction == "lower"
    assert isinstance(metrics.declaration(("change", "altered_by_kind", "tank", "support")), metrics.Informative)
    assert metrics.undeclared({"change": out}) == []
    # records without kinds (written before they were recorded) give null, never a made-up figure
    old = [{k: v for k, v in r.items() if k != "kind"} for r in rows]
    assert aggregate_change([{"features": old, "objects": [], "displacement_error_mm": []}])["altered_by_kind"] is None
