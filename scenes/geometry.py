"""Small rigid-geometry helpers shared by the whole project.

Conventions (DESIGN section 3): metres and radians; a pose ``T_a_b`` of shape (4, 4) maps
points from frame b to frame a, ``p_a = T_a_b @ p_b``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def check_vector3(v, name: str = "vector") -> np.ndarray:
    """Return ``v`` as a float64 array of shape (3,), or raise ValueError."""
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{name}: expected shape (3,), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: must be finite, got {a.tolist()}")
    return a


def check_points(points, name: str = "points") -> np.ndarray:
    """Return ``points`` as float64 of shape (N, 3), or raise ValueError."""
    a = np.asarray(points, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {a.shape}")
    return a


def check_transform(T, name: str = "transform") -> np.ndarray:
    """Return ``T`` as a float64 rigid transform of shape (4, 4), or raise ValueError."""
    a = np.asarray(T, dtype=np.float64)
    if a.shape != (4, 4):
        raise ValueError(f"{name}: expected shape (4, 4), got {a.shape}")
    R = a[:3, :3]
    if not np.all(np.isfinite(a)) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError(f"{name}: not a rigid transform (rotation part not orthonormal)")
    if not np.allclose(a[3], [0, 0, 0, 1]):
        raise ValueError(f"{name}: last row must be [0, 0, 0, 1]")
    return a


def unit(v: np.ndarray) -> np.ndarray:
    """Normalise vectors along the last axis (zero vectors stay zero)."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


def perpendicular_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit vector ``a`` (3,) to a right-handed orthonormal basis
    ``(e1, e2, a)``, ``e1 = a x x_hat`` (``a x y_hat`` when ``a`` is near ``x_hat``); no ``np.cross``, whose
    per-call overhead dominates in the fits' inner loops."""
    ax, ay, az = float(a[0]), float(a[1]), float(a[2])
    if abs(ax) < 0.9:  # e1 = a x (1, 0, 0)
        e1 = np.array([0.0, az, -ay])
    else:  # e1 = a x (0, 1, 0)
        e1 = np.array([-az, 0.0, ax])
    e1 /= np.sqrt(e1 @ e1)
    e2 = np.array([ay * e1[2] - az * e1[1], az * e1[0] - ax * e1[2], ax * e1[1] - ay * e1[0]])
    return e1, e2


def perpendicular(axis: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit vector ``axis``, chosen deterministically (the first of
    :func:`perpendicular_basis`)."""
    return perpendicular_basis(axis)[0]


def frame_from_z(axis: np.ndarray, x_hint: np.ndarray | None = None) -> np.ndarray:
    """Rotation (3, 3) whose third column is ``axis`` (columns are the frame's x, y, z in the parent)."""
    z = unit(np.asarray(axis, dtype=np.float64))
    x = perpendicular(z) if x_hint is None else unit(np.asarray(x_hint) - np.dot(x_hint, z) * z)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def make_transform(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble a (4, 4) transform from a rotation (3, 3) and a translation (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform of shape (4, 4)."""
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the (4, 4) transform ``T`` to points of shape (..., 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix (3, 3) for a right-handed rotation of ``angle`` radians about ``axis``."""
    return Rotation.from_rotvec(unit(np.asarray(axis, dtype=np.float64)) * angle).as_matrix()


def look_at(position: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """``T_world_sensor`` (4, 4) of an OpenCV-frame sensor at ``position`` looking at ``target``.

    The sensor z axis points at the target, x to the right and y down in the image, with the
    world ``up`` direction appearing upwards. Raises ValueError when the view direction is
    undefined or parallel to ``up``.
    """
    p = check_vector3(position, "position")
    z = check_vector3(target, "target") - p
    if np.linalg.norm(z) < 1e-12:
        raise ValueError("look_at: position and target coincide")
    z = unit(z)
    up = unit(np.asarray(up, dtype=np.float64))
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = perpendicular(z)
    x = unit(x)
    y = np.cross(z, x)
    return make_transform(np.column_stack([x, y, z]), p)


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians) of the rotation matrix ``R`` of shape (3, 3)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))
