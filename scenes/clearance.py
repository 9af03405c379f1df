"""Interpenetration tests between objects, on dense surface samples (used when placing parts).

Two objects interpenetrate (or touch) when a surface sample of one lies within ``clearance`` of a
sample of the other, or inside the other's solid. Samples are drawn with a fixed seed, so the test
is deterministic.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from scenes.features import Cylinder, Sphere
from scenes.mjcf import box_of_planes
from scenes.model import Object

_MAX_SAMPLES = 40_000


def object_samples(obj: Object, spacing: float) -> np.ndarray:
    """Surface samples (N, 3) of every feature of ``obj``, about one per ``spacing``² (capped per feature)."""
    rng = np.random.default_rng(12345)
    pts = []
    for f in obj.features:
        n = int(min(_MAX_SAMPLES, max(16, np.ceil(f.area() / spacing**2))))
        pts.append(f.sample(n, rng)[0])
    return np.concatenate(pts)


def inside_solids(obj: Object, points: np.ndarray) -> np.ndarray:
    """True for points strictly inside a cylinder, sphere or box solid of ``obj``."""
    inside = np.zeros(len(points), dtype=bool)
    box = box_of_planes(obj.features)
    if box is not None:
        centre, R, half, _ = box
        inside |= np.all(np.abs((points - centre) @ R) < half, axis=1)
    for f in obj.features:
        if isinstance(f, Cylinder):
            h = (points - f.centre) @ f.axis
            inside |= (f.signed_distance(points) < 0) & (np.abs(h) < f.length / 2)
        elif isinstance(f, Sphere):
            inside |= f.signed_distance(points) < 0
    return inside


class ClearanceIndex:
    """Samples of placed objects, one KD-tree per object, to test candidates quickly.

    Parameters
    ----------
    spacing : sample spacing in metres; ``clearance`` should exceed it.
    clearance : minimum gap between different objects (metres).
    """

    def __init__(self, spacing: float, clearance: float):
        if clearance <= 0 or spacing <= 0:
            raise ValueError("spacing and clearance must be > 0")
        self.spacing, self.clearance = spacing, clearance
        self._placed: dict[str, tuple[Object, np.ndarray, cKDTree]] = {}

    def add(self, obj: Object) -> None:
        pts = object_samples(obj, self.spacing)
        self._placed[obj.id] = (obj, pts, cKDTree(pts))

    def remove(self, object_id: str) -> None:
        self._placed.pop(object_id, None)

    def collides(self, obj: Object, ignore: frozenset[str] | set[str] = frozenset()) -> bool:
        """True when ``obj`` comes closer than the clearance to, or enters, any placed object not in ``ignore``."""
        pts = None
        for oid, (other, other_pts, tree) in self._placed.items():
            if oid in ignore or oid == obj.id:
                continue
            if pts is None:
                pts = object_samples(obj, self.spacing)
            d, _ = tree.query(pts, distance_upper_bound=self.clearance)
            if np.any(np.isfinite(d)):
                return True
            # containment either way (a small part wholly inside a tank, or a tank swallowing a part)
            if inside_solids(other, pts).any() or inside_solids(obj, other_pts).any():
                return True
        return False
