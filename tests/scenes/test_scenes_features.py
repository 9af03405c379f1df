"""Scene features: implicit equations, sampling, transforms, finite-surface distance."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenes.features import Cone, Cylinder, Plane, Sphere, Torus, box_planes
from scenes.geometry import (
    look_at,
    make_transform,
    perpendicular,
    perpendicular_basis,
    rotation_about,
    transform_points,
    unit,
)


def _features():
    return [
        Plane("p", centre=[1, 2, 3], normal=unit([1, 1, 0]), u_axis=unit([1, -1, 0]), half_size=(0.5, 2.0)),
        Cylinder("c", centre=[0, 0, 1], axis=unit([1, 2, 3]), radius=0.2, length=3.0),
        Sphere("s", centre=[1, 0, 0], radius=0.7),
        Sphere("cap", centre=[1, 0, 0], radius=0.7, cap_axis=[0, 0, 1], cap_height=0.3),
        Cone("k", apex=[0, 1, 0], axis=unit([0, 1, 1]), half_angle=0.3, start=0.5, end=1.5),
        Torus("t", centre=[0, 0, 0], axis=[0, 0, 1], major_radius=1.0, minor_radius=0.2, start=[1, 0, 0],
              sweep=math.pi / 2),
    ]


@pytest.mark.parametrize("feature", _features(), ids=lambda f: f.id)
def test_samples_satisfy_implicit_equation_and_extent(feature):
    pts, normals = feature.sample(2000, np.random.default_rng(0))
    assert pts.shape == normals.shape == (2000, 3)
    np.testing.assert_allclose(feature.signed_distance(pts), 0, atol=1e-12)
    np.testing.assert_allclose(feature.surface_distance(pts), 0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-12)
    # normals point outward: stepping along them increases the signed distance by the step
    np.testing.assert_allclose(feature.signed_distance(pts + 1e-4 * normals), 1e-4, rtol=1e-3)


@pytest.mark.parametrize("feature", _features(), ids=lambda f: f.id)
def test_sampling_is_area_uniform(feature):
    """Monte Carlo area of a slab of the surface equals its share of samples."""
    pts, _ = feature.sample(40000, np.random.default_rng(1))
    assert feature.area() > 0
    # compare to a dense sample from a different seed: the mean of the points agrees (uniformity)
    pts2, _ = feature.sample(40000, np.random.default_rng(2))
    scale = feature.size()
    np.testing.assert_allclose(pts.mean(axis=0), pts2.mean(axis=0), atol=0.02 * scale)


def test_closed_form_areas():
    f = _features()
    assert f[0].area() == pytest.approx(4 * 0.5 * 2.0)
    assert f[1].area() == pytest.approx(2 * math.pi * 0.2 * 3.0)
    assert f[2].area() == pytest.approx(4 * math.pi * 0.49)
    assert f[3].area() == pytest.approx(2 * math.pi * 0.7 * 0.3)
    assert f[5].area() == pytest.approx(4 * math.pi**2 * 1.0 * 0.2 / 4)


def test_cone_radius_and_distance():
    k = Cone("k", apex=[0, 0, 0], axis=[0, 0, 1], half_angle=math.radians(30), start=1.0, end=2.0)
    assert k.radius_at(2.0) == pytest.approx(2 * math.tan(math.radians(30)))
    # a point on the axis at height h is at distance h sin(alpha) inside the cone
    assert k.signed_distance(np.array([[0, 0, 2.0]]))[0] == pytest.approx(-2 * math.sin(math.radians(30)))


def test_surface_distance_beyond_extent():
    c = Cylinder("c", centre=[0, 0, 0], axis=[0, 0, 1], radius=1.0, length=2.0)
    assert c.surface_distance(np.array([[1.0, 0, 1.5]]))[0] == pytest.approx(0.5)
    t = Torus("t", centre=[0, 0, 0], axis=[0, 0, 1], major_radius=1.0, minor_radius=0.1, start=[1, 0, 0],
              sweep=math.pi / 2)
    # a point on the spine a quarter turn before the start is R * pi/2 outside the arc (approximately)
    p = np.array([[0.0, -1.1, 0.0]])
    assert t.surface_distance(p)[0] == pytest.approx(math.pi / 2, rel=1e-6)


@settings(max_examples=30, deadline=None)
@given(st.floats(-math.pi, math.pi), st.lists(st.floats(-5, 5), min_size=3, max_size=3),
       st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_transformed_features_move_their_samples(angle, t, axis):
    T = make_transform(rotation_about(axis, angle), np.array(t))
    for f in _features():
        g = f.transformed(T)
        pts, _ = f.sample(200, np.random.default_rng(3))
        np.testing.assert_allclose(g.signed_distance(transform_points(T, pts)), 0, atol=1e-9)


def test_box_planes_are_outward_and_closed():
    R = rotation_about([0, 0, 1], 0.4)
    faces = box_planes("b", [1, 2, 3], R, (0.5, 0.25, 1.0))
    assert len(faces) == 6 and len({f.id for f in faces}) == 6
    for f in faces:
        np.testing.assert_allclose(np.linalg.norm(np.cross(f.normal, f.u_axis)), 1.0)
        assert f.signed_distance(np.array([[1.0, 2.0, 3.0]]))[0] < 0  # the centre is behind every face


def test_look_at_is_opencv_frame():
    T = look_at([0, -5, 1], [0, 0, 1])
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)  # z forward
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # y down in the image = world down
    np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0)
    with pytest.raises(ValueError, match="coincide"):
        look_at([0, 0, 0], [0, 0, 0])


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1))
def test_perpendicular_basis_completes_a_right_handed_orthonormal_frame(v):
    a = unit(np.array(v))
    e1, e2 = perpendicular_basis(a)
    frame = np.column_stack([e1, e2, a])
    np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-12)
    assert np.linalg.det(frame) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(e1, unit(np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])), atol=1e-12)
    np.testing.assert_array_equal(perpendicular(a), e1)
