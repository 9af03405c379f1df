"""Step 9b of the segmentation, elbow joins (:mod:`recognition.segmentation.elbows`): adjacent patches that one
ring torus fits, and no cylinder, join; a pipe and its elbow, two pieces of one pipe and two planes do not."""

from __future__ import annotations

import numpy as np
import pytest

from recognition.segmentation import SegmentationParams, SurfaceType
from recognition.segmentation.elbows import _join_elbow_pieces
from recognition.segmentation.grid import _State

SIGMA = 0.004  # metres: Kinect-like noise at about 1.5 m


def _run_image(len_a: float, len_b: float, seed: int, r: float = 0.1, bend: float = 0.25, rows: int = 40,
               cols_per_m: float = 160.0, sigma: float = SIGMA):
    """An organised image of the front half of a pipe run at z = 3 m: a pipe of ``len_a`` along x, its 90 deg
    elbow of bend radius ``bend`` in the plane z = 3 m, a pipe of ``len_b`` along y; rows go around the tube
    (-1.2 to 1.2 rad from the sensor's side), columns along the run. Returns the points (H, W, 3) with radial
    noise ``sigma`` and the part of each pixel (0, 1, 2: first pipe, elbow, second pipe)."""
    rng = np.random.default_rng(seed)
    arc = 0.5 * np.pi * bend
    s = np.linspace(0.0, len_a + arc + len_b, int(round((len_a + arc + len_b) * cols_per_m)))
    phi = np.linspace(-1.2, 1.2, rows)
    S_, P_ = np.meshgrid(s, phi)
    part = np.digitize(S_, [len_a, len_a + arc])
    th = np.clip((S_ - len_a) / bend, 0.0, 0.5 * np.pi)
    centre = np.where((part == 0)[..., None], np.stack([S_, 0 * S_, 0 * S_], -1),
                      np.where((part == 1)[..., None],
                               np.stack([len_a + bend * np.sin(th), bend - bend * np.cos(th), 0 * S_], -1),
                               np.stack([len_a + bend + 0 * S_, bend + S_ - len_a - arc, 0 * S_], -1)))
    tangent = np.stack([np.cos(th), np.sin(th), 0 * th], -1)
    towards_sensor = np.array([0.0, 0.0, -1.0])
    radial = np.cos(P_)[..., None] * towards_sensor + np.sin(P_)[..., None] * np.cross(tangent, towards_sensor)
    x = centre + [0.0, 0.0, 3.0] + (r + rng.normal(0.0, sigma, S_.shape))[..., None] * radial
    return x, part


def _join(points: np.ndarray, labels: np.ndarray, params: SegmentationParams | None = None):
    params = SegmentationParams() if params is None else params
    X = points.reshape(-1, 3)
    st = _State(X=X, U=X / np.linalg.norm(X, axis=1, keepdims=True), S=np.full(len(X), SIGMA),
                hk=np.full(len(X), int(SurfaceType.NONE), np.int64))
    h, w = labels.shape
    return _join_elbow_pieces(labels.astype(np.int32), st, params, np.zeros((h, w - 1), bool),
                              np.zeros((h - 1, w), bool))


@pytest.mark.parametrize("seed", range(3))
def test_the_inner_and_outer_sides_of_an_elbow_join(seed):
    """An elbow left as its inner and outer side (the hyperbolic and the elliptic half, which no quadric
    joins), and as three pieces along its arc, becomes one patch."""
    x, _ = _run_image(0.0, 0.0, seed)
    h, w = x.shape[:2]
    sides = np.where(np.arange(h)[:, None] < h // 2, 0, 1) * np.ones((1, w), int)
    assert np.unique(_join(x, sides)).tolist() == [0]
    thirds = np.minimum(3 * np.arange(w) // w, 2)[None, :] * np.ones((h, 1), int)
    assert np.unique(_join(x, thirds)).tolist() == [0]
    assert np.unique(_join(x, thirds, SegmentationParams(torus_join_k=None))).tolist() == [0, 1, 2]


@pytest.mark.parametrize("seed", range(3))
def test_a_pipe_and_its_elbow_stay_apart(seed):
    """Their union bends at one end only: neither a torus nor a cylinder fits it."""
    x, part = _run_image(0.6, 0.0, seed)
    np.testing.assert_array_equal(_join(x, part), part)


@pytest.mark.parametrize("seed", range(3))
def test_two_pieces_of_a_straight_pipe_are_left_to_merging(seed):
    """A cylinder fits their union: a straight tube, not an elbow (a torus of a wide bend fits it as well)."""
    x, _ = _run_image(1.0, 0.0, seed)
    x = x[:, : x.shape[1] * 1 // 2]  # the straight part only (the elbow starts at 1 m of ~1.39)
    h, w = x.shape[:2]
    halves = (np.arange(w) >= w // 2)[None, :] * np.ones((h, 1), int)
    np.testing.assert_array_equal(_join(x, halves), halves)


def test_two_planes_are_not_tried():
    """Planar patches (a box's faces at a crease) are skipped before any fit."""
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 60), np.linspace(-0.3, 0.3, 40))
    z = 3.0 + np.abs(u) + np.random.default_rng(0).normal(0.0, SIGMA, u.shape)
    x = np.stack([u, v, z], -1)
    faces = (u > 0).astype(int)
    np.testing.assert_array_equal(_join(x, faces), faces)


def test_params_are_validated():
    with pytest.raises(ValueError, match="torus_join_k"):
        SegmentationParams(torus_join_k=0.0)
    with pytest.raises(ValueError, match="torus_join_cylinder_ratio"):
        SegmentationParams(torus_join_cylinder_ratio=0.5)
    with pytest.raises(ValueError, match="torus_join_fit_points"):
        SegmentationParams(torus_join_fit_points=5)
