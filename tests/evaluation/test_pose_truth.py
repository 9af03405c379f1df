"""What counts as a constrained view (evaluation.pose): a view that a twin pose of the model's symmetric or
repeated structure explains as well is not decided by any data, however fine."""

import numpy as np
import pytest

from evaluation.pose import constrains_pose, twin_ambiguous
from recognition.localisation.prediction import predict
from scenes import builders
from scenes.model import SceneModel
from sensors.config import SensorConfig
from sensors.models import PinholeCamera
from sensors.noise import NoiseModel
from sensors.simulate import Simulator


def _look_at(eye, target) -> np.ndarray:
    """``T_world_sensor`` of a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def _corner_view(extra: bool):
    """A cabinet off the centre of a floor larger than the view, seen from above one of its corners 2.5 m away
    (three faces and the floor), with or without a second, smaller cabinet beside it: the truth, the model, the
    simulator and the camera."""
    c = np.array([3.0, 2.0, 0.0])
    objects = [builders.floor("floor", 40.0, 40.0), builders.cabinet("cab", tuple(c), 0.0, (0.8, 0.6, 1.2))]
    if extra:
        objects.append(builders.cabinet("small", tuple(c + [0.9, 0.0, 0.0]), 0.0, (0.3, 0.3, 0.5)))
    model = SceneModel("corner", tuple(objects))
    cam = PinholeCamera.from_fov(160, 120, 60.0, min_range=0.3, max_range=20.0)
    T = _look_at(c + [-1.6, -1.4, 2.4], c + [0.0, 0.0, 0.5])
    sim = Simulator.from_scene(model)
    _, truth = sim.simulate(SensorConfig(cam, NoiseModel(enabled=False)), T, np.random.default_rng(0))
    return truth, model, sim, cam


@pytest.mark.parametrize("extra, expected", [(False, True), (True, False)])
def test_a_symmetric_view_is_twin_ambiguous_and_an_asymmetric_one_is_not(extra, expected):
    """Turned by 180 deg about the cabinet's vertical axis, the camera sees the same corner of the same box on
    the same endless floor: ambiguous. A second cabinet on one side breaks the symmetry (the turned pose
    would show it on the other side)."""
    truth, model, sim, cam = _corner_view(extra)
    assert twin_ambiguous(truth, model, lambda T, s: predict(sim, cam, T, s)) is expected


def test_twins_come_only_from_the_features_that_can_locate_the_sensor():
    """With the cabinet's faces excluded (had the perturbation moved it, it could not locate the sensor), the
    twins are the floor's alone: turned about the floor's centre, the sensor would see the cabinet elsewhere, so
    the image decides and the view is not ambiguous."""
    truth, model, sim, cam = _corner_view(False)
    faces = {f.id for f in model.features if f.id.startswith("cab.")}
    assert len(faces) >= 5
    assert not twin_ambiguous(truth, model, lambda T, s: predict(sim, cam, T, s), exclude=faces)


def _wall_table_pipe(flags: np.ndarray | None = None):
    """A wall, a floor and a table (two parallel normals), which leave the pose free along the wall, and a pipe
    crossing that direction, 300 truth pixels each (surface ids 0-3, the pipe 3) of a 30 x 40 image: the truth
    (``flags`` per pixel, none set by default) and the model."""
    from scenes.features import Cylinder, Plane
    from scenes.mjcf import Surface
    from scenes.model import Object
    from sensors.range_image import ScanTruth

    def plane(fid, c, n):
        return Plane(fid, centre=np.array(c), normal=np.array(n), u_axis=np.array([1.0, 0, 0]), half_size=(2, 1))

    feats = [plane("wall.yn", [0, 2.0, 1.0], [0, -1.0, 0]), plane("floor.top", [0, 0, 0.0], [0, 0, 1.0]),
             plane("table.top", [0, 1.0, 0.5], [0, 0, 1.0]),
             Cylinder("pipe.s0", centre=np.array([0, 1.8, 1.2]), axis=np.array([0, 0, 1.0]), radius=0.05, length=1.0)]
    model = SceneModel("m", tuple(Object(f.id.split(".")[0], "thing", (f,)) for f in feats))
    surfaces = tuple(Surface(i, f.id, "side" if isinstance(f, Cylinder) else "face",
                             "CYL" if isinstance(f, Cylinder) else "PLAN") for i, f in enumerate(feats))
    sid = np.repeat(np.arange(4), 300).reshape(30, 40)
    T = np.eye(4)
    T[:3, 3] = [0, -2.0, 1.0]
    truth = ScanTruth(T_world_sensor=T, sigma=np.zeros((30, 40)), surface_id=sid, normals=np.zeros((30, 40, 3)),
                      surfaces=surfaces, true_range=np.ones((30, 40)),
                      flags=np.zeros((30, 40), np.uint8) if flags is None else flags)
    return truth, model


def test_a_moved_feature_does_not_count_towards_constraining_the_pose():
    """The pipe fixes the direction along the wall, unless the perturbation moved it (it cannot locate the
    sensor then)."""
    truth, model = _wall_table_pipe()
    assert constrains_pose(truth, model)
    assert not constrains_pose(truth, model, exclude={"pipe.s0"})


def test_a_surface_without_returns_does_not_constrain_the_pose():
    """Nor does the pipe when the sensor returned nothing from it (closer than its minimum range: a mock-up trial
    counted a pipe 0.2 m away, 83785 pixels all dropouts, and the view as constrained)."""
    from sensors.range_image import FLAG_DROPOUT

    flags = np.zeros((30, 40), np.uint8)
    assert constrains_pose(*_wall_table_pipe(flags))
    pipe = _wall_table_pipe()[0].surface_id == 3
    flags[pipe] = FLAG_DROPOUT
    truth, model = _wall_table_pipe(flags)
    assert not constrains_pose(truth, model)
    flags[pipe & (np.arange(40)[None, :] < 20)] = 0  # 150 pixels measured: under the 200 of a region
    assert not constrains_pose(*_wall_table_pipe(flags))
