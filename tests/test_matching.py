"""Interpretation-tree matching on synthetic patches fitted from sampled model surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from recognition.classify import PatchClassification
from recognition.describe import SceneDescription, ScenePatch
from recognition.matching import MatchParams, match, model_elements
from recognition.primitives import fit_cylinder, fit_plane, fit_sphere
from recognition.segmentation import SurfaceType
from scenes.features import Cylinder, Plane, Sphere
from scenes.geometry import look_at
from scenes.model import Object, SceneModel


def _model() -> SceneModel:
    floor = Plane("floor", centre=[0, 0, 0], normal=[0, 0, 1], u_axis=[1, 0, 0], half_size=(3, 3))
    wall = Plane("wall", centre=[0, 2, 1], normal=[0, -1, 0], u_axis=[1, 0, 0], half_size=(3, 1))
    side = Plane("side", centre=[-2, 0, 1], normal=[1, 0, 0], u_axis=[0, 1, 0], half_size=(3, 1))
    pipes = [Cylinder(f"pipe{k}", centre=[x, 1.0, 0.5 + 0.3 * k], axis=[1, 0, 0], radius=r, length=2.0)
             for k, (x, r) in enumerate([(0.0, 0.05), (0.2, 0.08), (-0.3, 0.05)])]
    distract = [Cylinder(f"far{k}", centre=[8, 5 + k, 1], axis=[0, 1, 0], radius=r, length=1.5)
                for k, r in enumerate([0.05, 0.08, 0.05])]
    riser = Cylinder("riser", centre=[1.0, 0.5, 1.0], axis=[0, 0, 1], radius=0.06, length=2.0)
    ball = Sphere("ball", centre=[-1.0, 0.8, 0.4], radius=0.15)
    objs = (Object("room", "wall", (floor, wall, side)), Object("pipes", "pipe_run", tuple(pipes)),
            Object("far", "pipe_run", tuple(distract)), Object("riser_run", "pipe_run", (riser,)),
            Object("tank", "tank", (ball,)))
    return SceneModel("synthetic", objs)


def _patch(pid, feature, T_sensor_world, rng, n=600, sigma=3e-4, label=None, eye=None):
    pts, nrm = feature.sample(4 * n, rng)
    front = np.sum((eye - pts) * nrm, axis=1) > 0
    pts = pts[front][:n]
    pts = pts @ T_sensor_world[:3, :3].T + T_sensor_world[:3, 3]
    pts = pts + rng.normal(scale=sigma, size=pts.shape)
    sig = np.full(len(pts), sigma)
    kind = label or feature.truth_class
    fit = {"PLAN": fit_plane, "CYL": fit_cylinder, "SPH": fit_sphere}[kind](pts, sig)
    cls = PatchClassification(kind, {kind: 1.0}, {}, fit, {})
    return ScenePatch(pid, np.arange(len(pts)), pts, sig, SurfaceType.PLANAR, cls, False, False)


def _scene(spurious: bool, seed: int = 0):
    model = _model()
    T_ws = look_at(np.array([0.5, -3.0, 1.6]), np.array([0.0, 0.8, 0.7]))
    T_sw = np.linalg.inv(T_ws)
    rng = np.random.default_rng(seed)
    eye = T_ws[:3, 3]
    seen = ["floor", "wall", "side", "pipe0", "pipe1", "pipe2", "riser", "ball"]
    patches = [_patch(k, model.feature(f), T_sw, rng, eye=eye) for k, f in enumerate(seen)]
    if spurious:  # a cylinder and a plane the model does not have
        extra = [Cylinder("new", centre=[0.5, 0.2, 0.3], axis=[0.6, 0.8, 0], radius=0.07, length=0.8),
                 Plane("board", centre=[1.2, 0.0, 0.8], normal=[-0.6, -0.8, 0], u_axis=[0.8, -0.6, 0],
                       half_size=(0.3, 0.3))]
        patches += [_patch(len(patches) + k, f, T_sw, rng, eye=eye) for k, f in enumerate(extra)]
    desc = SceneDescription(tuple(patches), np.zeros((1, 1), np.int32), None, np.zeros((1, 1)), {})
    return model, desc, T_ws, seen


@pytest.mark.parametrize("spurious", [False, True])
def test_tree_finds_the_right_assignment_among_distractors(spurious):
    model, desc, T_ws, seen = _scene(spurious)
    params = MatchParams(min_pixels=50)
    res = match(desc, model, 1e-3, params)
    assert res.hypotheses
    best = res.hypotheses[0]
    assert best.pose.free_dof == 0
    T = best.pose.T_world_sensor
    assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ T_ws[:3, :3]) - 1) / 2, -1, 1))) < 0.2
    assert np.linalg.norm(T[:3, 3] - T_ws[:3, 3]) < 0.01
    el = res.elements
    got = {desc.patches[res.items[i].patch_index].id: (str(el.feature_id[e]) if e >= 0 else None)
           for i, e in best.pairs}
    for pid, fid in enumerate(seen):
        if pid in got and got[pid] is not None:
            assert got[pid] == fid
    assert sum(v is not None for v in got.values()) >= 6
    if spurious:
        assert got.get(len(seen)) is None and got.get(len(seen) + 1) is None
    assert res.n_nodes <= params.max_nodes


def test_no_items_gives_no_hypotheses():
    model = _model()
    desc = SceneDescription((), np.zeros((1, 1), np.int32), None, np.zeros((1, 1)), {})
    res = match(desc, model, 1e-3)
    assert res.hypotheses == () and res.items == ()


def test_model_elements_cover_faces_caps_and_sides():
    el = model_elements(_model())
    assert set(el.kind) == {"PLAN", "CYL", "SPH"}
    assert len(el.of_kind("CYL")) == 7 and len(el.of_kind("PLAN")) == 3 + 2 * 7
