"""A seeded family of paper-like 1:10 factory mock-ups around :func:`scenes.generator.mockup_model`.

Every member has the parts of today's mock-up, with the same object ids: a table top (``table``), a back
wall (``wall``), two horizontal pipes joined by an elbow (``pipe_a``), a straight pipe with a reducer
(``pipe_b``), a slanted pipe (``pipe_c``), a cylindrical tank (``tank``), a spherical tank on a leg
(``sphere``) and a cabinet (``cabinet``). Each parameter is drawn uniformly from a range of the config; the
shipped ranges (``scenes/data/mockup_family.yaml``, equal to ``MockupFamilyConfig()``) centre on today's
mock-up and span pipes and tanks about 30 % thinner to 30 % thicker. Ranges (metres, degrees in keys ending
``_deg``; today's mock-up in brackets):

* ``table``: ``size`` 1.6 x 1.0 (fixed; centred on the origin, top at z = 0); every placed part stays
  ``margin`` 0.01 inside its edge and below ``max_height`` 0.7.
* ``wall`` (along the table's far, +y, edge and as long as the table): ``height`` 0.5-0.7 [0.6];
  ``thickness`` 0.03 and ``inset`` 0.015 (its gap to the table's edge) are fixed numbers.
* ``elbow_pipe`` (``pipe_a``, from its corner a run towards -x and one towards -y, joined by an elbow):
  ``radius`` 0.0175-0.0325 [0.025]; ``bend_ratio`` (elbow bend radius / pipe radius) 2.2-3.4 [2.8];
  ``height`` of the axis 0.17-0.23 [0.2]; corner ``x`` 0.12-0.18 [0.15], ``y`` 0.22-0.28 [0.25];
  ``run_x`` 0.7-0.9 [0.8], ``run_y`` 0.45-0.65 [0.55].
* ``reducer_pipe`` (``pipe_b``, along x with a conical reducer in its middle): ``radius`` 0.021-0.039
  [0.03]; ``radius_ratio`` (after / before the reducer) 0.55-0.8 [0.667]; ``cone_angle_deg`` (half-angle)
  6-14 [9.5]; ``length`` 1.3-1.5 [1.4]; centre ``x`` -0.03-0.03 [0], ``y`` 0.36-0.40 [0.38], ``height``
  0.38-0.46 [0.42].
* ``slanted_pipe`` (``pipe_c``): ``radius`` 0.014-0.026 [0.02]; low end ``x`` -0.5 to -0.4 [-0.45], ``y``
  -0.08 to -0.02 [-0.05], ``height`` 0.05-0.07 [0.06]; horizontal ``length`` 0.42-0.58 [0.5] towards
  ``azimuth_deg`` -45 to -29 [-36.9], rising at ``slant_deg`` 22-34 [28.4].
* ``tank`` (body and hemispherical top): ``radius`` 0.056-0.104 [0.08], body ``height`` 0.2-0.3 [0.25];
  base centre ``x`` 0.42-0.58 [0.5], ``y`` 0.02-0.18 [0.1].
* ``sphere_tank`` (``sphere``, a ball on a leg): ``radius`` 0.045-0.075 [0.06]; ``leg_height`` (the gap
  under the ball) 0.03-0.07 [0.05]; base centre ``x`` -0.45 to -0.25 [-0.35], ``y`` 0.16-0.28 [0.22].
* ``cabinet``: ``width`` 0.14-0.22 [0.18], ``depth`` 0.09-0.15 [0.12], ``height`` 0.17-0.27 [0.22]; base
  centre ``x`` 0.38-0.52 [0.45], ``y`` -0.33 to -0.23 [-0.28]; ``yaw_deg`` about the vertical 5-30 [17.2].
* ``clearance`` 0.01: the minimum gap between parts; ``max_tries`` 200: draws per part before it is skipped.

The extent stays today's (the 1.6 m x 1.0 m table, parts below 0.7 m), so the mock-up's sensor
(``sensors/presets/mockup_laser.yaml``) and its viewpoint sampler see members as they see today's mock-up.
Placement is by rejection (like the factory generator): in the order wall, ``pipe_b``, ``pipe_a``,
``tank``, ``cabinet``, ``sphere``, ``pipe_c``, each part is redrawn until it keeps ``clearance`` from every
part placed before (the table excepted, which floor-standing parts touch) and lies on the table below
``max_height``; a part not placed after ``max_tries`` draws is left out and named in
:attr:`MockupDraw.skipped`. With the shipped config no part is skipped for seeds 0-29, 1000-1107, 2000-2107
and 3000-3029 (the spherical tank, tucked under the elbow pipe as in today's mock-up, takes the most draws:
at most 58).

YAML (schema ``mockup_family/1``; metres, degrees in keys ending ``_deg``), every key optional::

    schema: mockup_family/1
    table: {size: [1.6, 1.0], margin: 0.01, max_height: 0.7}
    wall: {height: [0.5, 0.7], thickness: 0.03, inset: 0.015}
    elbow_pipe: {radius: [0.0175, 0.0325], bend_ratio: [2.2, 3.4], height: [0.17, 0.23], ...}
    clearance: 0.01

Same config and seed: the same model, byte for byte once saved (``SceneModel.to_yaml``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from scenes import builders
from scenes.clearance import object_samples
from scenes.config import Fields, load_yaml
from scenes.generator import DATA_DIR, Placer, Range
from scenes.model import Object, SceneModel

SCHEMA = "mockup_family/1"
#: The shipped config of the family (equal to ``MockupFamilyConfig()``).
MOCKUP_FAMILY = DATA_DIR / "mockup_family.yaml"
_STREAM = 0x3C0F  # the family's random stream, beside the seed
_SIGNED = frozenset({"x", "y", "azimuth_deg", "yaw_deg"})  # ranges that may be negative
_HEIGHTS = frozenset({"height", "leg_height"})
_FLOOR_STANDING = frozenset({"wall", "tank", "cabinet"})


@dataclass(frozen=True)
class TableConfig:
    """The table top: ``size`` (x, y) in metres; parts stay ``margin`` inside its edge and below
    ``max_height`` (metres)."""

    size: tuple[float, float] = (1.6, 1.0)
    margin: float = 0.01
    max_height: float = 0.7


@dataclass(frozen=True)
class WallConfig:
    """The back wall along the table's +y edge, as long as the table (metres)."""

    height: Range = Range(0.5, 0.7)
    thickness: float = 0.03
    inset: float = 0.015


@dataclass(frozen=True)
class ElbowPipeConfig:
    """Two horizontal pipes joined by an elbow: from the corner (x, y, height) a run towards -x and one
    towards -y (metres; ``bend_ratio`` = elbow bend radius / pipe radius)."""

    radius: Range = Range(0.0175, 0.0325)
    bend_ratio: Range = Range(2.2, 3.4)
    height: Range = Range(0.17, 0.23)
    x: Range = Range(0.12, 0.18)
    y: Range = Range(0.22, 0.28)
    run_x: Range = Range(0.7, 0.9)
    run_y: Range = Range(0.45, 0.65)


@dataclass(frozen=True)
class ReducerPipeConfig:
    """A straight pipe along x centred on (x, y, height) with a conical reducer in its middle (metres,
    degrees): the radius goes from ``radius`` to ``radius * radius_ratio`` over a cone of half-angle
    ``cone_angle_deg``."""

    radius: Range = Range(0.021, 0.039)
    radius_ratio: Range = Range(0.55, 0.8)
    cone_angle_deg: Range = Range(6.0, 14.0)
    length: Range = Range(1.3, 1.5)
    x: Range = Range(-0.03, 0.03)
    y: Range = Range(0.36, 0.40)
    height: Range = Range(0.38, 0.46)


@dataclass(frozen=True)
class SlantedPipeConfig:
    """A straight slanted pipe from its low end (x, y, height), ``length`` metres horizontally towards
    ``azimuth_deg``, rising at ``slant_deg`` (degrees)."""

    radius: Range = Range(0.014, 0.026)
    x: Range = Range(-0.5, -0.4)
    y: Range = Range(-0.08, -0.02)
    height: Range = Range(0.05, 0.07)
    length: Range = Range(0.42, 0.58)
    azimuth_deg: Range = Range(-45.0, -29.0)
    slant_deg: Range = Range(22.0, 34.0)


@dataclass(frozen=True)
class TankConfig:
    """A vertical tank with a hemispherical top standing at (x, y): body radius and height (metres)."""

    radius: Range = Range(0.056, 0.104)
    height: Range = Range(0.2, 0.3)
    x: Range = Range(0.42, 0.58)
    y: Range = Range(0.02, 0.18)


@dataclass(frozen=True)
class SphereTankConfig:
    """A spherical tank on a leg standing at (x, y); ``leg_height`` is the gap under the ball (metres)."""

    radius: Range = Range(0.045, 0.075)
    leg_height: Range = Range(0.03, 0.07)
    x: Range = Range(-0.45, -0.25)
    y: Range = Range(0.16, 0.28)


@dataclass(frozen=True)
class CabinetConfig:
    """A box cabinet standing at (x, y), turned by ``yaw_deg`` about the vertical (metres, degrees)."""

    width: Range = Range(0.14, 0.22)
    depth: Range = Range(0.09, 0.15)
    height: Range = Range(0.17, 0.27)
    x: Range = Range(0.38, 0.52)
    y: Range = Range(-0.33, -0.23)
    yaw_deg: Range = Range(5.0, 30.0)


_PARTS: dict[str, type] = {"wall": WallConfig, "elbow_pipe": ElbowPipeConfig, "reducer_pipe": ReducerPipeConfig,
                           "slanted_pipe": SlantedPipeConfig, "tank": TankConfig, "sphere_tank": SphereTankConfig,
                           "cabinet": CabinetConfig}


@dataclass(frozen=True)
class MockupFamilyConfig:
    """The ranges of the mock-up family (see the module docstring for every key, its unit and range)."""

    table: TableConfig = TableConfig()
    wall: WallConfig = WallConfig()
    elbow_pipe: ElbowPipeConfig = ElbowPipeConfig()
    reducer_pipe: ReducerPipeConfig = ReducerPipeConfig()
    slanted_pipe: SlantedPipeConfig = SlantedPipeConfig()
    tank: TankConfig = TankConfig()
    sphere_tank: SphereTankConfig = SphereTankConfig()
    cabinet: CabinetConfig = CabinetConfig()
    clearance: float = 0.01
    max_tries: int = 200

    @staticmethod
    def load(path: str | Path) -> MockupFamilyConfig:
        """Read and validate a ``mockup_family/1`` YAML file (errors: :class:`scenes.config.ConfigError`)."""
        return MockupFamilyConfig.from_dict(load_yaml(path), str(path))

    @staticmethod
    def from_dict(data: Any, source: str = "<mockup_family>") -> MockupFamilyConfig:
        """Validate plain data read from YAML; a bad value raises one :class:`ConfigError` naming ``source``,
        the field and the reason."""
        root = Fields(data, source)
        schema = root.string("schema", SCHEMA)
        if schema != SCHEMA:
            raise root.error("schema", f"unsupported schema {schema!r} (expected {SCHEMA!r})")
        d = MockupFamilyConfig()
        table = _table(root.sub("table", {}), d.table)
        parts = {name: _part(root.sub(name, {}), getattr(d, name), table) for name in _PARTS}
        wall = root.sub("wall", {})
        if parts["wall"].thickness + parts["wall"].inset >= table.size[1] / 2:
            raise wall.error("thickness", f"thickness + inset must be < half the table depth ({table.size[1] / 2})")
        clearance = root.number("clearance", d.clearance, positive=True, min=1e-4, max=0.1)
        cfg = MockupFamilyConfig(table=table, **parts, clearance=clearance,
                                 max_tries=root.integer("max_tries", d.max_tries, min=1, max=10_000))
        root.check_unknown()
        return cfg


def _table(f: Fields, d: TableConfig) -> TableConfig:
    size = f.vector("size", list(d.size), size=2)
    for i, s in enumerate(size):
        if not 0.2 <= s <= 10.0:
            raise f.error("size", f"each side must be in [0.2, 10] m, got size[{i}] = {s}")
    table = TableConfig((float(size[0]), float(size[1])), f.number("margin", d.margin, nonnegative=True,
                                                                   max=float(min(size)) / 4),
                        f.number("max_height", d.max_height, positive=True, max=10.0))
    f.check_unknown()
    return table


def _part(f: Fields, default: Any, table: TableConfig) -> Any:
    """A part's config of the same type as ``default``: every ``Range`` field read as ``[low, high]`` and
    checked against the table, every number as a fixed length."""
    values: dict[str, Any] = {}
    for fld in fields(default):
        value = getattr(default, fld.name)
        if isinstance(value, Range):
            values[fld.name] = _range(f, fld.name, value, table)
        else:  # a fixed length (the wall's thickness > 0, its inset >= 0)
            values[fld.name] = f.number(fld.name, value, positive=fld.name != "inset",
                                        nonnegative=True, max=float(min(table.size)) / 2)
    f.check_unknown()
    return type(default)(**values)


def _range(f: Fields, key: str, default: Range, table: TableConfig) -> Range:
    v = f.vector(key, [default.low, default.high], size=2)
    signed = key in _SIGNED
    if v[1] < v[0] or (not signed and v[0] <= 0):
        raise f.error(key, f"expected [low, high] with {'' if signed else '0 < '}low <= high, got {v.tolist()}")
    r = Range(float(v[0]), float(v[1]))
    reason = _range_problem(key, r, table)
    if reason:
        raise f.error(key, f"{reason}, got {v.tolist()}")
    return r


def _range_problem(key: str, r: Range, table: TableConfig) -> str:
    """Why the range of ``key`` cannot be used (empty when it can)."""
    half = {"x": table.size[0] / 2, "y": table.size[1] / 2}
    if key in half and max(abs(r.low), abs(r.high)) > half[key]:
        return f"must lie on the table (|{key}| <= {half[key]})"
    if key in ("azimuth_deg", "yaw_deg") and not -180 <= r.low <= r.high <= 180:
        return "must lie in [-180, 180] degrees"
    limits = {"bend_ratio": (1.0, 10.0), "radius_ratio": (0.0, 1.0), "cone_angle_deg": (0.0, 45.0),
              "slant_deg": (0.0, 80.0)}
    if key in limits:
        lo, hi = limits[key]
        return "" if lo < r.low and r.high < hi else f"must lie strictly between {lo:g} and {hi:g}"
    if key in _HEIGHTS and r.high > table.max_height:
        return f"must stay below the table's max_height ({table.max_height})"
    if key not in _SIGNED and r.high > max(table.size):
        return f"must fit on the table (<= {max(table.size)} m)"
    return ""


@dataclass(frozen=True)
class MockupDraw:
    """One member of the family: its model and the ids of the parts that could not be placed (left out)."""

    model: SceneModel
    skipped: tuple[str, ...] = ()


def generate_mockup(cfg: MockupFamilyConfig, seed: int, name: str | None = None) -> SceneModel:
    """Member ``seed`` of the mock-up family (see :func:`draw_mockup`).

    Parameters
    ----------
    cfg : the family's ranges.
    seed : a whole number >= 0; the same config and seed give the same model, byte for byte once saved.
    name : the model's name (default ``mockup_{seed}``).
    """
    return draw_mockup(cfg, seed, name).model


def draw_mockup(cfg: MockupFamilyConfig, seed: int, name: str | None = None) -> MockupDraw:
    """Member ``seed`` of the mock-up family with the list of parts left out (see the module docstring for
    the placement). Raises ``ValueError`` for a negative or non-integer seed."""
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a whole number >= 0, got {seed!r}")
    rng = np.random.default_rng([int(seed), _STREAM])
    sx, sy = cfg.table.size
    placer = Placer(cfg.clearance, cfg.max_tries, rng, fits=lambda obj: on_table(obj, cfg))
    placer.add_fixed(builders.floor("table", sx, sy), in_index=False)
    w = cfg.wall
    placer.add_fixed(builders.wall("wall", (0.0, sy / 2 - w.inset - w.thickness / 2, 0.0), 0.0, sx,
                                   w.height.draw(rng), w.thickness))
    makers: dict[str, Callable[[np.random.Generator], Object]] = {
        "pipe_b": _reducer_pipe(cfg.reducer_pipe), "pipe_a": _elbow_pipe(cfg.elbow_pipe), "tank": _tank(cfg.tank),
        "cabinet": _cabinet(cfg.cabinet), "sphere": _sphere_tank(cfg.sphere_tank),
        "pipe_c": _slanted_pipe(cfg.slanted_pipe)}
    for oid, make in makers.items():  # placement order: the largest and most constrained parts first
        placer.place(make, oid)
    order = ("table", "wall", "pipe_a", "pipe_b", "pipe_c", "tank", "sphere", "cabinet")  # as mockup_model()
    objects = sorted(placer.objects, key=lambda o: order.index(o.id))
    return MockupDraw(SceneModel(name or f"mockup_{seed}", tuple(objects)), tuple(placer.skipped))


def on_table(obj: Object, cfg: MockupFamilyConfig) -> bool:
    """True when ``obj`` lies on the table, ``cfg.table.margin`` inside its edge and below its ``max_height``
    (pipes also at least ``cfg.clearance`` above it), judged on surface samples ``2 cfg.clearance`` apart."""
    sx, sy = cfg.table.size
    m = cfg.table.margin
    floor = 0.0 if obj.kind in _FLOOR_STANDING else cfg.clearance
    pts = object_samples(obj, 2 * cfg.clearance)
    lo = np.array([-sx / 2 + m, -sy / 2 + m, floor - 1e-9])
    hi = np.array([sx / 2 - m, sy / 2 - m, cfg.table.max_height])
    return bool(np.all(pts >= lo) and np.all(pts <= hi))


def _elbow_pipe(c: ElbowPipeConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        radius = c.radius.draw(r)
        bend = radius * c.bend_ratio.draw(r)
        z, x, y = c.height.draw(r), c.x.draw(r), c.y.draw(r)
        run_x, run_y = c.run_x.draw(r), c.run_y.draw(r)
        return builders.pipe_run("pipe_a", [[x - run_x, y, z], [x, y, z], [x, y - run_y, z]], radius, bend)
    return make


def _reducer_pipe(c: ReducerPipeConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        radius, ratio = c.radius.draw(r), c.radius_ratio.draw(r)
        angle = math.radians(c.cone_angle_deg.draw(r))
        length, x, y, z = c.length.draw(r), c.x.draw(r), c.y.draw(r), c.height.draw(r)
        reduced = radius * ratio
        cone_length = (radius - reduced) / math.tan(angle)
        return builders.pipe_run("pipe_b", [[x - length / 2, y, z], [x + length / 2, y, z]], radius, 3 * radius,
                                 reducers={0: (reduced, cone_length)})
    return make


def _slanted_pipe(c: SlantedPipeConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        radius = c.radius.draw(r)
        x, y, z = c.x.draw(r), c.y.draw(r), c.height.draw(r)
        length = c.length.draw(r)
        azimuth, slant = math.radians(c.azimuth_deg.draw(r)), math.radians(c.slant_deg.draw(r))
        end = [x + length * math.cos(azimuth), y + length * math.sin(azimuth), z + length * math.tan(slant)]
        return builders.pipe_run("pipe_c", [[x, y, z], end], radius, 3 * radius)
    return make


def _tank(c: TankConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        radius, height, x, y = c.radius.draw(r), c.height.draw(r), c.x.draw(r), c.y.draw(r)
        return builders.tank("tank", (x, y, 0.0), radius, height)
    return make


def _sphere_tank(c: SphereTankConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        radius, leg, x, y = c.radius.draw(r), c.leg_height.draw(r), c.x.draw(r), c.y.draw(r)
        return builders.sphere_tank("sphere", (x, y, 0.0), radius, leg)
    return make


def _cabinet(c: CabinetConfig) -> Callable[[np.random.Generator], Object]:
    def make(r: np.random.Generator) -> Object:
        w, d, h = c.width.draw(r), c.depth.draw(r), c.height.draw(r)
        x, y, yaw = c.x.draw(r), c.y.draw(r), math.radians(c.yaw_deg.draw(r))
        return builders.cabinet("cabinet", (x, y, 0.0), yaw, (w, d, h))
    return make


__all__ = ["SCHEMA", "MOCKUP_FAMILY", "MockupFamilyConfig", "TableConfig", "WallConfig", "ElbowPipeConfig",
           "ReducerPipeConfig", "SlantedPipeConfig", "TankConfig", "SphereTankConfig", "CabinetConfig",
           "MockupDraw", "generate_mockup", "draw_mockup", "on_table"]
