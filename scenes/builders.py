"""Builders of semantic objects from a few parameters: pipe runs along a polyline (straight sections,
elbows, reducers), tanks, spherical tanks, cabinets, walls and floors.

Used by the procedural generator, the perturbation engine (new objects) and the hand-made mock-up.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus, box_planes, cylinder_between
from scenes.geometry import rotation_about, unit
from scenes.model import Object


def pipe_run(object_id: str, path: Sequence[Sequence[float]], radius: float, bend_radius: float,
             reducers: dict[int, tuple[float, float]] | None = None, material: str = "metal") -> Object:
    """A pipe run along the polyline ``path`` (M, 3): straight sections joined by torus elbows.

    Parameters
    ----------
    path : corner points in metres; consecutive segments must not be parallel and each must be long
        enough to hold its elbows (``bend_radius * tan(turn / 2)`` at each end).
    radius : pipe radius at the start of the run (metres).
    bend_radius : elbow centre-line radius (metres), larger than the pipe radius.
    reducers : optional ``{segment index: (new radius, length)}``: a conical reducer in the middle of that
        segment, after which the run continues at the new radius.
    """
    P = np.asarray(path, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
        raise ValueError(f"pipe path must have shape (M >= 2, 3), got {P.shape}")
    if bend_radius <= radius:
        raise ValueError(f"bend radius {bend_radius} must exceed the pipe radius {radius}")
    reducers = reducers or {}
    n_seg = len(P) - 1
    dirs = [unit(P[i + 1] - P[i]) for i in range(n_seg)]
    # set-back of each corner: tangent length of the elbow
    setback = [0.0] * (n_seg + 1)
    turns = [0.0] * (n_seg + 1)
    for i in range(1, n_seg):
        turn = math.acos(float(np.clip(dirs[i - 1] @ dirs[i], -1.0, 1.0)))
        if turn < 1e-6 or turn > math.pi - 1e-3:
            raise ValueError(f"pipe path corner {i} is straight or reverses (turn {math.degrees(turn):.1f} deg)")
        turns[i] = turn
        setback[i] = bend_radius * math.tan(turn / 2)
    features: list[Feature] = []
    r = radius
    for i in range(n_seg):
        a = P[i] + dirs[i] * setback[i]
        b = P[i + 1] - dirs[i] * setback[i + 1]
        length = float((b - a) @ dirs[i])
        if length <= 1e-6:
            raise ValueError(f"pipe segment {i} is too short for its elbows")
        if i in reducers:
            r2, red_len = reducers[i]
            side = (length - red_len) / 2
            if side <= 1e-6:
                raise ValueError(f"pipe segment {i} is too short for a reducer of length {red_len}")
            m1, m2 = a + dirs[i] * side, a + dirs[i] * (side + red_len)
            features.append(cylinder_between(f"{object_id}.s{i}a", a, m1, r, material=material))
            features.append(_reducer(f"{object_id}.r{i}", m1, m2, r, r2, material))
            r = r2
            features.append(cylinder_between(f"{object_id}.s{i}b", m2, b, r, material=material))
        else:
            features.append(cylinder_between(f"{object_id}.s{i}", a, b, r, material=material))
        if i + 1 < n_seg:
            features.append(_elbow(f"{object_id}.e{i}", b, dirs[i], dirs[i + 1], bend_radius, turns[i + 1], r,
                                   material))
    return Object(object_id, "pipe_run", tuple(features))


def _elbow(fid: str, start_point, d_in, d_out, bend_radius: float, turn: float, radius: float,
           material: str) -> Torus:
    inward = unit(d_out - (d_out @ d_in) * d_in)
    centre = start_point + bend_radius * inward
    return Torus(fid, centre=centre, axis=unit(np.cross(d_in, d_out)), major_radius=bend_radius,
                 minor_radius=radius, start=-inward, sweep=turn, material=material)


def _reducer(fid: str, p0, p1, r0: float, r1: float, material: str) -> Cone:
    """A frustum from radius ``r0`` at ``p0`` to radius ``r1`` at ``p1`` (either may be larger)."""
    if abs(r0 - r1) < 1e-9:
        raise ValueError("a reducer needs two different radii")
    axis_len = float(np.linalg.norm(np.asarray(p1) - p0))
    d = unit(np.asarray(p1) - p0)
    if r1 < r0:  # apex beyond p1, axis points from apex back towards p0
        p0, p1, r0, r1, d = p1, p0, r1, r0, -d
    tan_a = (r1 - r0) / axis_len
    start = r0 / tan_a
    apex = np.asarray(p0) - d * start
    return Cone(fid, apex=apex, axis=d, half_angle=math.atan(tan_a), start=start, end=start + axis_len,
                material=material)


def tank(object_id: str, base_centre, radius: float, height: float, material: str = "painted") -> Object:
    """A vertical tank standing on the floor: a cylinder body with a hemispherical top."""
    base = np.asarray(base_centre, dtype=np.float64)
    z = np.array([0.0, 0.0, 1.0])
    body = Cylinder(f"{object_id}.body", centre=base + z * height / 2, axis=z, radius=radius, length=height,
                    material=material)
    top = Sphere(f"{object_id}.top", centre=base + z * height, radius=radius, cap_axis=z, cap_height=radius,
                 material=material)
    return Object(object_id, "tank", (body, top))


def sphere_tank(object_id: str, base_centre, radius: float, leg_height: float, material: str = "painted") -> Object:
    """A spherical tank on a cylindrical leg of radius ``radius / 3`` standing on the floor."""
    base = np.asarray(base_centre, dtype=np.float64)
    z = np.array([0.0, 0.0, 1.0])
    leg_r = radius / 3
    leg_top = leg_height + radius - math.sqrt(radius**2 - leg_r**2)  # the leg meets the sphere
    leg = Cylinder(f"{object_id}.leg", centre=base + z * leg_top / 2, axis=z, radius=leg_r, length=leg_top,
                   material=material)
    ball = Sphere(f"{object_id}.ball", centre=base + z * (leg_height + radius), radius=radius, material=material)
    return Object(object_id, "tank", (leg, ball))


def cabinet(object_id: str, base_centre, yaw: float, size: Sequence[float], material: str = "painted") -> Object:
    """A box cabinet standing on the floor, ``size`` = (width, depth, height) in metres, rotated by ``yaw``."""
    w, d, h = (float(s) for s in size)
    R = rotation_about([0, 0, 1], yaw)
    centre = np.asarray(base_centre, dtype=np.float64) + np.array([0, 0, h / 2])
    return Object(object_id, "cabinet", box_planes(object_id, centre, R, (w / 2, d / 2, h / 2), material=material))


def wall(object_id: str, centre, yaw: float, length: float, height: float, thickness: float) -> Object:
    """A wall as a box standing on the floor (six planes), its length along the yawed x axis."""
    R = rotation_about([0, 0, 1], yaw)
    c = np.asarray(centre, dtype=np.float64) + np.array([0, 0, height / 2])
    return Object(object_id, "wall", box_planes(object_id, c, R, (length / 2, thickness / 2, height / 2)))


def floor(object_id: str, size_x: float, size_y: float, centre=(0.0, 0.0, 0.0)) -> Object:
    """A horizontal floor rectangle facing up."""
    return Object(object_id, "floor", (Plane(f"{object_id}.top", centre=centre, normal=[0, 0, 1], u_axis=[1, 0, 0],
                                             half_size=(size_x / 2, size_y / 2)),))
