"""Surface features of the a priori model: planes, cylinders, spheres, cones and torus sections.

Each feature is a frozen dataclass: an ``id``, its parameters (world frame, metres, radians) and
its finite extent. Every feature gives

* ``signed_distance(points)`` - the implicit surface's distance (positive outside), shape (N,);
* ``sample(n, rng)`` - area-uniform points on its finite surface with outward unit normals;
* ``truth_class`` - the paper's class of its main surface: PLAN, CYL, SPH, CONE or OTH (elbows);
* ``parts`` - its surfaces as seen by a sensor (a cylinder's side and its two caps, for example);
* ``transformed(T)`` - the same feature moved by a rigid transform of shape (4, 4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar

import numpy as np

from scenes.geometry import frame_from_z, transform_points, unit

TRUTH_CLASSES = ("PLAN", "CYL", "SPH", "CONE", "OTH")
MATERIALS = ("matte", "painted", "metal", "glossy")


def degrees_exact(rad: float) -> float:
    """Degrees ``d`` with ``radians(d) == rad`` when such a double exists near ``degrees(rad)``."""
    d = math.degrees(rad)
    if math.radians(d) == rad:
        return d
    up, down = d, d
    for _ in range(8):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, -math.inf)
        for cand in (up, down):
            if math.radians(cand) == rad:
                return cand
    return d


def yaml_exact_angle(rad: float) -> float:
    """``rad`` moved by at most a few ulps onto a value that YAML's degrees represent exactly
    (``radians(d)`` for a double ``d``), so that models round-trip through YAML bit for bit. Idempotent."""
    return math.radians(degrees_exact(rad))


def _vec(v) -> np.ndarray:
    a = np.array(v, dtype=np.float64)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Feature:
    """Base class: an identified surface feature with a material tag (for specular dropouts)."""

    id: str
    material: str = field(default="matte", kw_only=True)

    type_name: ClassVar[str] = ""
    truth_class: ClassVar[str] = "OTH"
    parts: ClassVar[tuple[str, ...]] = ("surface",)
    part_classes: ClassVar[tuple[str, ...]] = ("OTH",)

    # Helpers for equality of dataclasses holding numpy arrays.
    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
                if a is None or b is None or not np.array_equal(a, b):
                    return False
            elif a != b:
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def with_id(self, new_id: str) -> Feature:
        return replace(self, id=new_id)

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def surface_distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (N,) of points to the finite surface: the implicit distance combined with how
        far the point lies beyond the feature's extent (exact near the surface, approximate far away)."""
        points = np.asarray(points, dtype=np.float64)
        return np.hypot(self.signed_distance(points), self._extent_excess(points))

    def _extent_excess(self, points: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def transformed(self, T: np.ndarray) -> Feature:
        raise NotImplementedError

    def area(self) -> float:
        raise NotImplementedError

    def size(self) -> float:
        """A characteristic size in metres (used for mesh tolerances and clearances)."""
        raise NotImplementedError

    def sample_spacing(self, spacing: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """About one sample per ``spacing``² of area (at least 16)."""
        n = max(16, int(math.ceil(self.area() / spacing**2)))
        return self.sample(n, rng)


def _rot(T: np.ndarray, v: np.ndarray) -> np.ndarray:
    return _vec(T[:3, :3] @ v)


def _pt(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return _vec(transform_points(T, p))


@dataclass(frozen=True, eq=False, kw_only=True)
class Plane(Feature):
    """A rectangle: ``centre``, unit ``normal``, in-plane unit ``u_axis`` and ``half_size`` (along u, v).

    ``v = normal x u_axis``. The normal points to the side the surface is seen from (outward).
    """

    centre: np.ndarray
    normal: np.ndarray
    u_axis: np.ndarray
    half_size: tuple[float, float]

    type_name: ClassVar[str] = "plane"
    truth_class: ClassVar[str] = "PLAN"
    parts: ClassVar[tuple[str, ...]] = ("face",)
    part_classes: ClassVar[tuple[str, ...]] = ("PLAN",)

    def __post_init__(self):
        for name in ("centre", "normal", "u_axis"):
            object.__setattr__(self, name, _vec(getattr(self, name)))
        object.__setattr__(self, "half_size", (float(self.half_size[0]), float(self.half_size[1])))

    @property
    def v_axis(self) -> np.ndarray:
        return np.cross(self.normal, self.u_axis)

    def signed_distance(self, points):
        return (np.asarray(points) - self.centre) @ self.normal

    def sample(self, n, rng):
        s = rng.uniform(-1, 1, size=(n, 2)) * np.array(self.half_size)
        pts = self.centre + s[:, :1] * self.u_axis + s[:, 1:] * self.v_axis
        return pts, np.broadcast_to(self.normal, pts.shape).copy()

    def transformed(self, T):
        return replace(self, centre=_pt(T, self.centre), normal=_rot(T, self.normal),
                       u_axis=_rot(T, self.u_axis))

    def _extent_excess(self, points):
        w = points - self.centre
        eu = np.maximum(np.abs(w @ self.u_axis) - self.half_size[0], 0.0)
        ev = np.maximum(np.abs(w @ self.v_axis) - self.half_size[1], 0.0)
        return np.hypot(eu, ev)

    def area(self):
        return 4.0 * self.half_size[0] * self.half_size[1]

    def size(self):
        return 2.0 * max(self.half_size)

    def corners(self) -> np.ndarray:
        """The four corners, shape (4, 3)."""
        hu, hv = self.half_size
        signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
        return self.centre + signs[:, :1] * hu * self.u_axis + signs[:, 1:] * hv * self.v_axis


@dataclass(frozen=True, eq=False, kw_only=True)
class Cylinder(Feature):
    """A finite right circular cylinder: ``centre`` of its axis segment, unit ``axis``, ``radius``, ``length``.

    Its parts are the side (class CYL) and the two flat caps (class PLAN), at
    ``centre -/+ axis * length / 2`` (``cap_start``, ``cap_end``).
    """

    centre: np.ndarray
    axis: np.ndarray
    radius: float
    length: float

    type_name: ClassVar[str] = "cylinder"
    truth_class: ClassVar[str] = "CYL"
    parts: ClassVar[tuple[str, ...]] = ("side", "cap_start", "cap_end")
    part_classes: ClassVar[tuple[str, ...]] = ("CYL", "PLAN", "PLAN")

    def __post_init__(self):
        for name in ("centre", "axis"):
            object.__setattr__(self, name, _vec(getattr(self, name)))
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "length", float(self.length))

    def signed_distance(self, points):
        w = np.asarray(points) - self.centre
        h = w @ self.axis
        return np.linalg.norm(w - h[:, None] * self.axis, axis=1) - self.radius

    def sample(self, n, rng):
        R = frame_from_z(self.axis)
        theta = rng.uniform(0, 2 * np.pi, n)
        h = rng.uniform(-self.length / 2, self.length / 2, n)
        radial = np.cos(theta)[:, None] * R[:, 0] + np.sin(theta)[:, None] * R[:, 1]
        return self.centre + h[:, None] * self.axis + self.radius * radial, radial

    def transformed(self, T):
        return replace(self, centre=_pt(T, self.centre), axis=_rot(T, self.axis))

    def _extent_excess(self, points):
        return np.maximum(np.abs((points - self.centre) @ self.axis) - self.length / 2, 0.0)

    def area(self):
        return 2 * np.pi * self.radius * self.length

    def size(self):
        return max(2 * self.radius, self.length)

    def endpoints(self) -> np.ndarray:
        """Centres of the start and end caps, shape (2, 3)."""
        return self.centre + np.outer([-0.5, 0.5], self.axis) * self.length


@dataclass(frozen=True, eq=False, kw_only=True)
class Sphere(Feature):
    """A sphere, or a spherical cap (tank ends): ``centre``, ``radius``.

    With ``cap_axis`` set, only the cap ``(p - centre) . cap_axis >= radius - cap_height`` exists
    (``cap_height = radius``: a hemisphere; ``2 radius``: the whole sphere).
    """

    centre: np.ndarray
    radius: float
    cap_axis: np.ndarray | None = None
    cap_height: float | None = None

    type_name: ClassVar[str] = "sphere"
    truth_class: ClassVar[str] = "SPH"
    part_classes: ClassVar[tuple[str, ...]] = ("SPH",)

    def __post_init__(self):
        object.__setattr__(self, "centre", _vec(self.centre))
        object.__setattr__(self, "radius", float(self.radius))
        if self.cap_axis is not None:
            object.__setattr__(self, "cap_axis", _vec(self.cap_axis))
            object.__setattr__(self, "cap_height", float(self.cap_height if self.cap_height is not None
                                                         else self.radius))
        else:
            object.__setattr__(self, "cap_height", None)

    @property
    def is_cap(self) -> bool:
        return self.cap_axis is not None and self.cap_height < 2 * self.radius

    def signed_distance(self, points):
        return np.linalg.norm(np.asarray(points) - self.centre, axis=1) - self.radius

    def sample(self, n, rng):
        axis = self.cap_axis if self.cap_axis is not None else np.array([0.0, 0.0, 1.0])
        height = self.cap_height if self.cap_axis is not None else 2 * self.radius
        R = frame_from_z(axis)
        z = rng.uniform(1 - height / self.radius, 1, n)  # Archimedes: uniform in height is area-uniform
        phi = rng.uniform(0, 2 * np.pi, n)
        rho = np.sqrt(np.clip(1 - z**2, 0, None))
        d = (rho * np.cos(phi))[:, None] * R[:, 0] + (rho * np.sin(phi))[:, None] * R[:, 1] + z[:, None] * R[:, 2]
        return self.centre + self.radius * d, d

    def transformed(self, T):
        cap = None if self.cap_axis is None else _rot(T, self.cap_axis)
        return replace(self, centre=_pt(T, self.centre), cap_axis=cap)

    def _extent_excess(self, points):
        if self.cap_axis is None:
            return np.zeros(len(points))
        return np.maximum((self.radius - self.cap_height) - (points - self.centre) @ self.cap_axis, 0.0)

    def area(self):
        height = self.cap_height if self.cap_axis is not None else 2 * self.radius
        return 2 * np.pi * self.radius * height

    def size(self):
        return 2 * self.radius


@dataclass(frozen=True, eq=False, kw_only=True)
class Cone(Feature):
    """A conical frustum (pipe reducer): ``apex``, unit ``axis`` pointing from the apex into the cone,
    ``half_angle`` (radians, in (0, pi/2)), and the extent ``start < end`` as distances from the apex
    along the axis (radius at distance d is ``d tan(half_angle)``)."""

    apex: np.ndarray
    axis: np.ndarray
    half_angle: float
    start: float
    end: float

    type_name: ClassVar[str] = "cone"
    truth_class: ClassVar[str] = "CONE"
    parts: ClassVar[tuple[str, ...]] = ("side",)
    part_classes: ClassVar[tuple[str, ...]] = ("CONE",)

    def __post_init__(self):
        for name in ("apex", "axis"):
            object.__setattr__(self, name, _vec(getattr(self, name)))
        for name in ("half_angle", "start", "end"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "half_angle", yaml_exact_angle(self.half_angle))

    def radius_at(self, d):
        return np.asarray(d) * math.tan(self.half_angle)

    def signed_distance(self, points):
        w = np.asarray(points) - self.apex
        h = w @ self.axis
        rho = np.linalg.norm(w - h[:, None] * self.axis, axis=1)
        return rho * math.cos(self.half_angle) - h * math.sin(self.half_angle)

    def sample(self, n, rng):
        R = frame_from_z(self.axis)
        d = np.sqrt(rng.uniform(self.start**2, self.end**2, n))  # area element grows with d
        phi = rng.uniform(0, 2 * np.pi, n)
        radial = np.cos(phi)[:, None] * R[:, 0] + np.sin(phi)[:, None] * R[:, 1]
        pts = self.apex + d[:, None] * self.axis + self.radius_at(d)[:, None] * radial
        ca, sa = math.cos(self.half_angle), math.sin(self.half_angle)
        return pts, radial * ca - self.axis * sa

    def transformed(self, T):
        return replace(self, apex=_pt(T, self.apex), axis=_rot(T, self.axis))

    def _extent_excess(self, points):
        h = (points - self.apex) @ self.axis
        return np.maximum(np.maximum(self.start - h, h - self.end), 0.0)

    def area(self):
        slant = 1.0 / math.cos(self.half_angle)
        return math.pi * math.tan(self.half_angle) * slant * (self.end**2 - self.start**2)

    def size(self):
        return max(2 * float(self.radius_at(self.end)), self.end - self.start)


@dataclass(frozen=True, eq=False, kw_only=True)
class Torus(Feature):
    """A torus section (pipe elbow): ``centre``, unit ``axis`` (normal of the bend plane),
    ``major_radius`` (bend radius), ``minor_radius`` (pipe radius), unit ``start`` direction (from the
    centre to the start of the section, perpendicular to the axis) and ``sweep`` (radians, in (0, 2 pi]),
    turning right-handed about ``axis``."""

    centre: np.ndarray
    axis: np.ndarray
    major_radius: float
    minor_radius: float
    start: np.ndarray
    sweep: float

    type_name: ClassVar[str] = "torus"
    truth_class: ClassVar[str] = "OTH"
    part_classes: ClassVar[tuple[str, ...]] = ("OTH",)

    def __post_init__(self):
        for name in ("centre", "axis", "start"):
            object.__setattr__(self, name, _vec(getattr(self, name)))
        for name in ("major_radius", "minor_radius", "sweep"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "sweep", yaml_exact_angle(self.sweep))

    def spine(self, angle) -> tuple[np.ndarray, np.ndarray]:
        """Points (N, 3) on the centre circle at ``angle`` (N,) from ``start`` and their unit tangents."""
        angle = np.atleast_1d(np.asarray(angle, dtype=float))
        e1, e2 = self.start, np.cross(self.axis, self.start)
        radial = np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2
        tangent = -np.sin(angle)[:, None] * e1 + np.cos(angle)[:, None] * e2
        return self.centre + self.major_radius * radial, tangent

    def signed_distance(self, points):
        w = np.asarray(points) - self.centre
        h = w @ self.axis
        rho = np.linalg.norm(w - h[:, None] * self.axis, axis=1)
        return np.hypot(rho - self.major_radius, h) - self.minor_radius

    def sample(self, n, rng):
        R, r = self.major_radius, self.minor_radius
        out_t, out_p = [], []
        count = 0
        while count < n:  # rejection: area element is proportional to R + r cos(psi)
            m = 2 * (n - count) + 16
            t = rng.uniform(0, self.sweep, m)
            psi = rng.uniform(0, 2 * np.pi, m)
            keep = rng.uniform(0, R + r, m) < R + r * np.cos(psi)
            out_t.append(t[keep])
            out_p.append(psi[keep])
            count += int(keep.sum())
        t = np.concatenate(out_t)[:n]
        psi = np.concatenate(out_p)[:n]
        e1, e2 = self.start, np.cross(self.axis, self.start)
        radial = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2
        normal = np.cos(psi)[:, None] * radial + np.sin(psi)[:, None] * self.axis
        return self.centre + R * radial + r * normal, normal

    def transformed(self, T):
        return replace(self, centre=_pt(T, self.centre), axis=_rot(T, self.axis), start=_rot(T, self.start))

    def _extent_excess(self, points):
        w = points - self.centre
        angle = np.mod(np.arctan2(w @ np.cross(self.axis, self.start), w @ self.start), 2 * np.pi)
        outside = np.minimum(np.maximum(angle - self.sweep, 0.0), 2 * np.pi - angle)  # angular distance to the arc
        outside = np.where(angle <= self.sweep, 0.0, outside)
        return outside * self.major_radius

    def area(self):
        return 2 * np.pi * self.minor_radius * self.major_radius * self.sweep

    def size(self):
        return 2 * (self.major_radius + self.minor_radius)


FEATURE_TYPES: dict[str, type[Feature]] = {cls.type_name: cls for cls in (Plane, Cylinder, Sphere, Cone, Torus)}


def feature_axis(feature: Feature) -> np.ndarray | None:
    """The feature's principal direction (plane normal; cylinder, cone, torus axis), or None for spheres."""
    if isinstance(feature, Plane):
        return feature.normal
    if isinstance(feature, Cylinder | Cone | Torus):
        return feature.axis
    return None


def cylinder_between(feature_id: str, p0, p1, radius: float, **kw: Any) -> Cylinder:
    """A cylinder from end point ``p0`` to end point ``p1``."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.linalg.norm(d))
    return Cylinder(feature_id, centre=(p0 + p1) / 2, axis=unit(d), radius=radius, length=length, **kw)


def box_planes(prefix: str, centre, R: np.ndarray, half: tuple[float, float, float],
               **kw: Any) -> tuple[Plane, ...]:
    """The six outward faces of a box with rotation ``R`` (columns = box axes) and half extents ``half``.

    Faces are named ``{prefix}.xp``, ``.xn``, ``.yp``, ``.yn``, ``.zp``, ``.zn``.
    """
    centre = np.asarray(centre, float)
    out = []
    for k, name in enumerate("xyz"):
        a, b = (k + 1) % 3, (k + 2) % 3
        for sign, tag in ((1.0, "p"), (-1.0, "n")):
            n = sign * R[:, k]
            out.append(Plane(f"{prefix}.{name}{tag}", centre=centre + n * half[k], normal=n, u_axis=R[:, a],
                             half_size=(half[a], half[b]), **kw))
    return tuple(out)


__all__ = [
    "TRUTH_CLASSES", "MATERIALS", "Feature", "Plane", "Cylinder", "Sphere", "Cone", "Torus", "FEATURE_TYPES",
    "feature_axis", "cylinder_between", "box_planes",
]
