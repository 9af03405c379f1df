"""The a priori scene model: objects (semantic entities) grouping surface features, and its YAML form.

YAML layout (angles in degrees with a ``_deg`` suffix, lengths in metres)::

    schema: scene/1
    name: mockup
    objects:
      - id: pipe_a
        kind: pipe_run
        features:
          - {type: cylinder, id: pipe_a.s0, centre: [0, 0, 0.2], axis: [1, 0, 0], radius: 0.02, length: 0.4}
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from scenes.config import ConfigError, Fields, dump_yaml, load_yaml, parse_yaml, show
from scenes.features import FEATURE_TYPES, MATERIALS, Cone, Cylinder, Feature, Plane, Sphere, Torus, degrees_exact

SCHEMA = "scene/1"
OBJECT_KINDS = ("floor", "wall", "pipe_run", "tank", "cabinet", "structure")


@dataclass(frozen=True)
class Object:
    """A semantic entity (pipe run, tank, wall, cabinet, floor) made of surface features."""

    id: str
    kind: str
    features: tuple[Feature, ...]

    def transformed(self, T: np.ndarray) -> Object:
        return Object(self.id, self.kind, tuple(f.transformed(T) for f in self.features))


@dataclass(frozen=True)
class SceneModel:
    """Objects and their features; feature and object ids are unique across the model."""

    name: str
    objects: tuple[Object, ...]

    def __post_init__(self):
        seen: dict[str, str] = {}
        for i, obj in enumerate(self.objects):
            if obj.id in seen:
                raise ConfigError("", f"objects[{i}].id", f"duplicate id {obj.id!r}")
            seen[obj.id] = "object"
            for j, f in enumerate(obj.features):
                if f.id in seen:
                    raise ConfigError("", f"objects[{i}].features[{j}].id", f"duplicate id {f.id!r}")
                seen[f.id] = "feature"

    @cached_property
    def features(self) -> tuple[Feature, ...]:
        return tuple(f for obj in self.objects for f in obj.features)

    @cached_property
    def _feature_object(self) -> dict[str, str]:
        return {f.id: obj.id for obj in self.objects for f in obj.features}

    def feature(self, feature_id: str) -> Feature:
        for f in self.features:
            if f.id == feature_id:
                return f
        raise KeyError(feature_id)

    def object(self, object_id: str) -> Object:
        for obj in self.objects:
            if obj.id == object_id:
                return obj
        raise KeyError(object_id)

    def object_of(self, feature_id: str) -> str:
        """Id of the object that holds feature ``feature_id``."""
        return self._feature_object[feature_id]

    def replace_objects(self, objects: Iterable[Object]) -> SceneModel:
        return SceneModel(self.name, tuple(objects))

    def rounded(self, decimals: int = 10) -> SceneModel:
        """This model with every number rounded to ``decimals`` places (0.1 nm for the default 10; -0.0 as 0.0).

        A generator's or a perturbation's last bits follow the floating-point path (numpy's SIMD width: a pipe
        0.637873032448587 m long on one machine, 0.6378730324485871 m on another; a cross product's zero as
        1e-17); rounded, a scene is the same scene on every machine (``python -m harness.bench.stability``)."""
        def r(value: Any) -> Any:
            if isinstance(value, float):
                return round(value, decimals) + 0.0
            if isinstance(value, dict):
                return {k: r(v) for k, v in value.items()}
            if isinstance(value, (list, tuple)):
                return [r(v) for v in value]
            return value

        return SceneModel.from_dict(r(self.to_dict()), self.name)

    # -- YAML -----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {"schema": SCHEMA, "name": self.name,
                "objects": [{"id": o.id, "kind": o.kind, "features": [feature_to_dict(f) for f in o.features]}
                            for o in self.objects]}

    def to_yaml(self) -> str:
        return dump_yaml(self.to_dict())

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.to_yaml(), encoding="utf-8")

    @staticmethod
    def from_dict(data: Any, source: str = "<scene>") -> SceneModel:
        root = Fields(data, source)
        schema = root.string("schema", SCHEMA)
        if schema != SCHEMA:
            raise root.error("schema", f"unsupported schema {schema!r} (expected {SCHEMA!r})")
        name = root.string("name", "scene")
        objects = []
        ids: set[str] = set()
        for o in root.list_of_fields("objects"):
            oid = o.string("id")
            _check_new_id(o, "id", oid, ids)
            kind = o.string("kind", choices=OBJECT_KINDS)
            feats = []
            for f in o.list_of_fields("features"):
                feat = feature_from_fields(f)
                _check_new_id(f, "id", feat.id, ids)
                feats.append(feat)
            if not feats:
                raise o.error("features", "an object needs at least one feature")
            o.check_unknown()
            objects.append(Object(oid, kind, tuple(feats)))
        root.check_unknown()
        return SceneModel(name, tuple(objects))

    @staticmethod
    def from_yaml(text: str, source: str = "<string>") -> SceneModel:
        return SceneModel.from_dict(parse_yaml(text, source), source)

    @staticmethod
    def load(path: str | Path) -> SceneModel:
        return SceneModel.from_dict(load_yaml(path), str(path))


def _check_new_id(f: Fields, key: str, value: str, ids: set[str]) -> None:
    if value in ids:
        raise f.error(key, f"duplicate id {value!r}")
    ids.add(value)


def _list(v: np.ndarray) -> list[float]:
    return [float(x) for x in v]


def feature_to_dict(f: Feature) -> dict[str, Any]:
    """Plain-data form of a feature (YAML schema ``scene/1``)."""
    d: dict[str, Any] = {"type": f.type_name, "id": f.id}
    if isinstance(f, Plane):
        d |= {"centre": _list(f.centre), "normal": _list(f.normal), "u_axis": _list(f.u_axis),
              "half_size": [float(f.half_size[0]), float(f.half_size[1])]}
    elif isinstance(f, Cylinder):
        d |= {"centre": _list(f.centre), "axis": _list(f.axis), "radius": f.radius, "length": f.length}
    elif isinstance(f, Sphere):
        d |= {"centre": _list(f.centre), "radius": f.radius}
        if f.cap_axis is not None:
            d |= {"cap_axis": _list(f.cap_axis), "cap_height": f.cap_height}
    elif isinstance(f, Cone):
        d |= {"apex": _list(f.apex), "axis": _list(f.axis), "half_angle_deg": degrees_exact(f.half_angle),
              "start": f.start, "end": f.end}
    elif isinstance(f, Torus):
        d |= {"centre": _list(f.centre), "axis": _list(f.axis), "major_radius": f.major_radius,
              "minor_radius": f.minor_radius, "start": _list(f.start), "sweep_deg": degrees_exact(f.sweep)}
    if f.material != "matte":
        d["material"] = f.material
    return d


def _perpendicular(f: Fields, key: str, v: np.ndarray, to: np.ndarray, other: str) -> None:
    if abs(float(v @ to)) > 1e-6:
        raise f.error(key, f"must be perpendicular to {other} (dot product {float(v @ to):.3g})")


def feature_from_fields(f: Fields) -> Feature:
    """Build and validate one feature from its YAML mapping."""
    type_name = f.string("type", choices=FEATURE_TYPES)
    fid = f.string("id")
    material = f.string("material", "matte", choices=MATERIALS)
    if type_name == "plane":
        normal = f.vector("normal", unit_norm=True)
        u_axis = f.vector("u_axis", unit_norm=True)
        _perpendicular(f, "u_axis", u_axis, normal, "normal")
        half = f.raw("half_size")
        if not isinstance(half, list) or len(half) != 2:
            raise f.error("half_size", f"expected a list of 2 numbers, got {show(half)}")
        hs = tuple(Fields({"h": h}, f.source, f.child_path("half_size")).number("h", positive=True) for h in half)
        feat: Feature = Plane(fid, centre=f.vector("centre"), normal=normal, u_axis=u_axis, half_size=hs,
                              material=material)
    elif type_name == "cylinder":
        feat = Cylinder(fid, centre=f.vector("centre"), axis=f.vector("axis", unit_norm=True),
                        radius=f.number("radius", positive=True), length=f.number("length", positive=True),
                        material=material)
    elif type_name == "sphere":
        radius = f.number("radius", positive=True)
        cap_axis = f.vector("cap_axis", unit_norm=True) if f.has("cap_axis") else None
        cap_height = None
        if cap_axis is not None:
            cap_height = f.number("cap_height", positive=True, max=2 * radius)
        elif f.has("cap_height"):
            raise f.error("cap_height", "cap_height needs cap_axis")
        feat = Sphere(fid, centre=f.vector("centre"), radius=radius, cap_axis=cap_axis, cap_height=cap_height,
                      material=material)
    elif type_name == "cone":
        half_angle = f.number("half_angle_deg", positive=True, max=89.0)
        start = f.number("start", nonnegative=True)
        end = f.number("end", positive=True)
        if end <= start:
            raise f.error("end", f"must be greater than start ({start}), got {end}")
        feat = Cone(fid, apex=f.vector("apex"), axis=f.vector("axis", unit_norm=True),
                    half_angle=math.radians(half_angle), start=start, end=end, material=material)
    else:
        axis = f.vector("axis", unit_norm=True)
        start_dir = f.vector("start", unit_norm=True)
        _perpendicular(f, "start", start_dir, axis, "axis")
        major = f.number("major_radius", positive=True)
        minor = f.number("minor_radius", positive=True)
        if minor >= major:
            raise f.error("minor_radius", f"must be smaller than major_radius ({major}), got {minor}")
        sweep = f.number("sweep_deg", positive=True, max=360.0)
        feat = Torus(fid, centre=f.vector("centre"), axis=axis, major_radius=major, minor_radius=minor,
                     start=start_dir, sweep=math.radians(sweep), material=material)
    f.check_unknown()
    return feat


__all__ = ["SCHEMA", "OBJECT_KINDS", "Object", "SceneModel", "feature_to_dict", "feature_from_fields",
           "MATERIALS"]
