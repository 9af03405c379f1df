"""Poses that the repeated structure of the model makes look alike (DESIGN 11.6).

A bay holds identical cabinets, walls of one size, pipe runs of one radius: a view that shows one of them can be
explained by the sensor standing before any of its twins, and the interpretation tree need not have produced
that hypothesis (its budget, a missed elbow). :func:`twin_poses` makes them explicitly: for a feature ``f`` the
winning pose pairs with a patch and every other feature ``g`` of the same shape (:func:`shape_key`), the rigid
map ``S`` that carries ``f``'s frame onto one of ``g``'s (a plane's two in-plane turns, a cylinder's two axis
directions, a sphere's centre) gives the pose ``S T`` under which the data show ``g`` where they showed ``f``.
The localisation verifies them like any alternative; the winner must be separated from them.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from scenes.features import Cylinder, Feature, Plane, Sphere
from scenes.model import SceneModel

__all__ = ["shape_key", "feature_frames", "twin_poses"]


def shape_key(f: Feature, tol_m: float = 0.005) -> tuple | None:
    """What makes two features twins: their type and dimensions rounded to ``tol_m``; None for the types whose
    frame is not defined here (cones, tori)."""
    def q(x: float) -> int:
        return int(round(float(x) / tol_m))

    if isinstance(f, Plane):
        return ("plane", *sorted(q(h) for h in f.half_size))
    if isinstance(f, Cylinder):
        return ("cylinder", q(f.radius), q(f.length))
    if isinstance(f, Sphere):
        return ("sphere", q(f.radius))
    return None


def _frame(origin: np.ndarray, z: np.ndarray, x: np.ndarray) -> np.ndarray:
    z = z / np.linalg.norm(z)
    x = x - (x @ z) * z
    x = x / np.linalg.norm(x)
    F = np.eye(4)
    F[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    F[:3, 3] = origin
    return F


def _reference(z: np.ndarray) -> np.ndarray:
    """A direction not along ``z``: world z, or world x for a vertical ``z`` (so a feature's frame about its
    axis is fixed by the world, the same for twins)."""
    ref = np.array([0.0, 0.0, 1.0])
    return ref if abs(float(ref @ z)) < 0.9 * float(np.linalg.norm(z)) else np.array([1.0, 0.0, 0.0])


def feature_frames(f: Feature) -> list[np.ndarray]:
    """The frames (4, 4) ``world <- feature`` a twin may be aligned with: a plane's (centre, normal, ``±u``), a
    cylinder's (centre, ``±axis``), a sphere's centre with the world axes; [] for other types."""
    if isinstance(f, Plane):
        return [_frame(f.centre, f.normal, f.u_axis), _frame(f.centre, f.normal, -f.u_axis)]
    if isinstance(f, Cylinder):
        x = _reference(f.axis)
        return [_frame(f.centre, f.axis, x), _frame(f.centre, -f.axis, x)]
    if isinstance(f, Sphere):
        F = np.eye(4)
        F[:3, 3] = f.centre
        return [F]
    return []


def twin_poses(T_world_sensor: np.ndarray, matched: Iterable[str], model: SceneModel) -> list[np.ndarray]:
    """The poses ``S T`` (4, 4) that put a twin of each feature of ``matched`` (ids the pose pairs with patches)
    where the pose puts that feature, in a fixed order (model order of the matched features, then of their
    twins, then of the twins' frames). Aligning a feature with its own other frame is left out only for the
    identity map."""
    T = np.asarray(T_world_sensor, dtype=np.float64)
    by_key: dict[tuple, list[Feature]] = {}
    for g in model.features:
        k = shape_key(g)
        if k is not None:
            by_key.setdefault(k, []).append(g)
    wanted = set(matched)
    out: list[np.ndarray] = []
    for f in model.features:
        k = shape_key(f)
        if f.id not in wanted or k is None:
            continue
        F_inv = np.linalg.inv(feature_frames(f)[0])
        for g in by_key[k]:
            for G in feature_frames(g):
                S = G @ F_inv
                if g.id == f.id and np.allclose(S, np.eye(4), atol=1e-9):
                    continue
                out.append(S @ T)
    return out
