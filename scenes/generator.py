"""Seeded procedural factory bay, and the paper-like 1:10 factory mock-up.

The generator config is YAML (schema ``generator/1``, see ``scenes/data/factory_generator.yaml``)::

    schema: generator/1
    bay: {size: [20.0, 16.0], wall_height: 6.0, wall_thickness: 0.2}
    cabinets: {count: 4, width: [0.6, 1.6], depth: [0.4, 0.8], height: [1.2, 2.2]}
    tanks: {count: 2, spherical: 1, radius: [0.6, 1.2], height: [1.5, 3.0]}
    pipes: {runs: 5, vertical: 1, slanted: 1, radius: [0.05, 0.2], segments: [2, 4],
            height: [1.5, 4.5], bend_ratio: [1.5, 3.0], reducer_probability: 0.3}
    clearance: 0.1

Same config and seed: the same model, byte for byte once saved. The parametric family of mock-ups drawn
around :func:`mockup_model` is :mod:`scenes.mockup_family`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from scenes import builders
from scenes.clearance import ClearanceIndex
from scenes.config import Fields, load_yaml
from scenes.model import Object, SceneModel

DATA_DIR = Path(__file__).parent / "data"
#: The shipped factory generator config (schema ``generator/1``), equal to ``GeneratorConfig()``'s defaults
#: apart from ``reducer_probability`` (0.4 in the file).
FACTORY_GENERATOR = DATA_DIR / "factory_generator.yaml"


@dataclass(frozen=True)
class Range:
    """A closed interval [low, high] to draw from."""

    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class GeneratorConfig:
    """Parameters of the factory bay generator (metres, see the module docstring)."""

    size: tuple[float, float] = (20.0, 16.0)
    wall_height: float = 6.0
    wall_thickness: float = 0.2
    cabinets: int = 4
    cabinet_width: Range = Range(0.6, 1.6)
    cabinet_depth: Range = Range(0.4, 0.8)
    cabinet_height: Range = Range(1.2, 2.2)
    tanks: int = 2
    spherical_tanks: int = 1
    tank_radius: Range = Range(0.6, 1.2)
    tank_height: Range = Range(1.5, 3.0)
    pipe_runs: int = 5
    vertical_runs: int = 1
    slanted_runs: int = 1
    pipe_radius: Range = Range(0.05, 0.2)
    pipe_segments: tuple[int, int] = (2, 4)
    pipe_height: Range = Range(1.5, 4.5)
    bend_ratio: Range = Range(1.5, 3.0)
    reducer_probability: float = 0.3
    clearance: float = 0.1
    max_tries: int = 60

    @staticmethod
    def load(path: str | Path) -> GeneratorConfig:
        return GeneratorConfig.from_dict(load_yaml(path), str(path))

    @staticmethod
    def from_dict(data, source: str = "<generator>") -> GeneratorConfig:
        root = Fields(data, source)
        schema = root.string("schema", "generator/1")
        if schema != "generator/1":
            raise root.error("schema", f"unsupported schema {schema!r} (expected 'generator/1')")
        d = GeneratorConfig()
        bay, cab = root.sub("bay", {}), root.sub("cabinets", {})
        tanks, pipes = root.sub("tanks", {}), root.sub("pipes", {})
        size = bay.vector("size", list(d.size), size=2)
        for i, s in enumerate(size):
            if s < 2.0:
                raise bay.error("size", f"each side must be >= 2 m, got size[{i}] = {s}")

        def rng_of(f: Fields, key: str, default: Range, positive: bool = True) -> Range:
            v = f.vector(key, [default.low, default.high], size=2)
            if (positive and v[0] <= 0) or v[1] < v[0]:
                raise f.error(key, f"expected [low, high] with 0 < low <= high, got {v.tolist()}")
            return Range(float(v[0]), float(v[1]))

        seg = pipes.vector("segments", list(d.pipe_segments), size=2)
        if seg[0] < 1 or seg[1] < seg[0] or seg[0] != int(seg[0]) or seg[1] != int(seg[1]):
            raise pipes.error("segments",
                              f"expected whole numbers [low, high] with 1 <= low <= high, got {seg.tolist()}")
        cfg = GeneratorConfig(
            size=(float(size[0]), float(size[1])),
            wall_height=bay.number("wall_height", d.wall_height, positive=True),
            wall_thickness=bay.number("wall_thickness", d.wall_thickness, positive=True),
            cabinets=cab.integer("count", d.cabinets, min=0, max=50),
            cabinet_width=rng_of(cab, "width", d.cabinet_width),
            cabinet_depth=rng_of(cab, "depth", d.cabinet_depth),
            cabinet_height=rng_of(cab, "height", d.cabinet_height),
            tanks=tanks.integer("count", d.tanks, min=0, max=20),
            spherical_tanks=tanks.integer("spherical", d.spherical_tanks, min=0, max=20),
            tank_radius=rng_of(tanks, "radius", d.tank_radius),
            tank_height=rng_of(tanks, "height", d.tank_height),
            pipe_runs=pipes.integer("runs", d.pipe_runs, min=0, max=50),
            vertical_runs=pipes.integer("vertical", d.vertical_runs, min=0, max=50),
            slanted_runs=pipes.integer("slanted", d.slanted_runs, min=0, max=50),
            pipe_radius=rng_of(pipes, "radius", d.pipe_radius),
            pipe_segments=(int(seg[0]), int(seg[1])),
            pipe_height=rng_of(pipes, "height", d.pipe_height),
            bend_ratio=rng_of(pipes, "bend_ratio", d.bend_ratio),
            reducer_probability=pipes.number("reducer_probability", d.reducer_probability, min=0, max=1),
            clearance=root.number("clearance", d.clearance, positive=True, min=1e-4),  # samples: clearance / 2 apart
            max_tries=root.integer("max_tries", d.max_tries, min=1, max=10_000),
        )
        if cfg.spherical_tanks > cfg.tanks:
            raise tanks.error("spherical", f"cannot exceed count ({cfg.tanks}), got {cfg.spherical_tanks}")
        if cfg.vertical_runs + cfg.slanted_runs > cfg.pipe_runs:
            raise pipes.error("runs", "must be at least vertical + slanted")
        if cfg.bend_ratio.low <= 1.0:
            raise pipes.error("bend_ratio", "must be > 1 (elbow bend radius over pipe radius)")
        if cfg.pipe_height.high > cfg.wall_height:
            raise pipes.error("height", f"must stay below the wall height {cfg.wall_height}")
        for f in (root, bay, cab, tanks, pipes):
            f.check_unknown()
        return cfg


class Placer:
    """Places objects one by one with rejection of interpenetrating candidates.

    Parameters
    ----------
    clearance : minimum gap between placed objects (metres); samples are spaced by half of it.
    max_tries : candidates drawn per object before it is skipped (its name is added to ``skipped``).
    rng : source of every draw.
    fits : optional extra acceptance test of a candidate (e.g. "lies on the table").
    """

    def __init__(self, clearance: float, max_tries: int, rng: np.random.Generator,
                 fits: Callable[[Object], bool] | None = None):
        self.max_tries, self.rng, self.fits = max_tries, rng, fits
        self.index = ClearanceIndex(spacing=clearance / 2, clearance=clearance)
        self.objects: list[Object] = []
        self.skipped: list[str] = []

    def add_fixed(self, obj: Object, in_index: bool = True) -> None:
        self.objects.append(obj)
        if in_index:
            self.index.add(obj)

    def place(self, make: Callable[[np.random.Generator], Object], name: str = "") -> bool:
        for _ in range(self.max_tries):
            try:
                obj = make(self.rng)
            except ValueError:
                continue  # geometrically impossible draw (e.g. a segment too short for its elbows)
            if (self.fits is None or self.fits(obj)) and not self.index.collides(obj):
                self.add_fixed(obj)
                return True
        self.skipped.append(name)
        return False


def generate_factory(cfg: GeneratorConfig, seed: int, name: str | None = None) -> SceneModel:
    """A factory bay: floor, four walls, cabinets, tanks and pipe runs, drawn from ``seed``."""
    rng = np.random.default_rng([seed, 0x5CE7E])
    sx, sy = cfg.size
    t, H = cfg.wall_thickness, cfg.wall_height
    placer = Placer(cfg.clearance, cfg.max_tries, rng)
    placer.add_fixed(builders.floor("floor", sx + 2 * t, sy + 2 * t), in_index=False)
    for oid, c, yaw, length in (("wall_s", (0, -sy / 2 - t / 2, 0), 0.0, sx + 2 * t),
                                ("wall_n", (0, sy / 2 + t / 2, 0), 0.0, sx + 2 * t),
                                ("wall_w", (-sx / 2 - t / 2, 0, 0), math.pi / 2, sy),
                                ("wall_e", (sx / 2 + t / 2, 0, 0), math.pi / 2, sy)):
        placer.add_fixed(builders.wall(oid, c, yaw, length, H, t))
    margin = 2 * cfg.clearance

    def cabinet(i):
        def make(r):
            w, d, h = cfg.cabinet_width.draw(r), cfg.cabinet_depth.draw(r), cfg.cabinet_height.draw(r)
            side = int(r.integers(4))  # back against one of the walls
            along = r.uniform(-0.5, 0.5)
            off = margin + d / 2
            x, y, yaw = {0: (along * (sx - w - 2 * margin), -sy / 2 + off, 0.0),
                         1: (along * (sx - w - 2 * margin), sy / 2 - off, math.pi),
                         2: (-sx / 2 + off, along * (sy - w - 2 * margin), -math.pi / 2),
                         3: (sx / 2 - off, along * (sy - w - 2 * margin), math.pi / 2)}[side]
            return builders.cabinet(f"cabinet{i}", (x, y, 0.0), yaw, (w, d, h))
        return make

    def tank(i, spherical):
        def make(r):
            rad = cfg.tank_radius.draw(r)
            m = rad + margin + 1.0
            x, y = r.uniform(-sx / 2 + m, sx / 2 - m), r.uniform(-sy / 2 + m, sy / 2 - m)
            if spherical:
                return builders.sphere_tank(f"tank{i}", (x, y, 0.0), rad, leg_height=r.uniform(0.3, 1.0))
            height = max(cfg.tank_height.draw(r), rad)
            return builders.tank(f"tank{i}", (x, y, 0.0), rad, height)
        return make

    def pipe(i, style):
        def make(r):
            rad = cfg.pipe_radius.draw(r)
            bend = rad * cfg.bend_ratio.draw(r)
            m = margin + bend + rad
            lo, hi = np.array([-sx / 2 + m, -sy / 2 + m]), np.array([sx / 2 - m, sy / 2 - m])
            n_seg = int(r.integers(cfg.pipe_segments[0], cfg.pipe_segments[1] + 1))
            z = cfg.pipe_height.draw(r)
            p = r.uniform(lo, hi)
            path = []
            if style == "vertical":  # rises from near the floor, then runs horizontally
                path.append([p[0], p[1], rad + margin])
            elif style == "slanted":  # a straight slanted pipe between two heights, like the paper's
                q = r.uniform(lo, hi)
                z2 = float(np.clip(z + r.choice([-1, 1]) * r.uniform(0.4, 0.8) * np.linalg.norm(q - p),
                                   cfg.pipe_height.low, cfg.pipe_height.high))
                return builders.pipe_run(f"pipe{i}", [[p[0], p[1], z], [q[0], q[1], z2]], rad, bend)
            path.append([p[0], p[1], z])
            axis = int(r.integers(2))
            for _ in range(n_seg - (1 if style == "vertical" else 0)):
                q = path[-1].copy()
                target = r.uniform(lo[axis], hi[axis])
                if abs(target - q[axis]) < 4 * bend:
                    target = q[axis] + np.sign(target - q[axis] or 1.0) * 4 * bend
                q[axis] = float(np.clip(target, lo[axis], hi[axis]))
                path.append(q)
                axis = 1 - axis
            reducers = {}
            for s in range(len(path) - 1):
                if r.uniform() < cfg.reducer_probability and not reducers:
                    reducers[s] = (rad * r.uniform(0.55, 0.8), rad * 3.0)
            return builders.pipe_run(f"pipe{i}", path, rad, bend, reducers)
        return make

    for i in range(cfg.cabinets):
        placer.place(cabinet(i), f"cabinet{i}")
    for i in range(cfg.tanks):
        placer.place(tank(i, i < cfg.spherical_tanks), f"tank{i}")
    styles = ["vertical"] * cfg.vertical_runs + ["slanted"] * cfg.slanted_runs
    styles += ["horizontal"] * (cfg.pipe_runs - len(styles))
    for i, style in enumerate(styles):
        placer.place(pipe(i, style), f"pipe{i}")
    return SceneModel(name or f"factory_bay_{seed}", tuple(placer.objects))


def mockup_model() -> SceneModel:
    """The paper-like factory mock-up at about 1:10 scale (metres): a table top, a back wall, two horizontal
    pipes joined by an elbow, a pipe with a reducer, a slanted pipe, a tank, a spherical tank and a cabinet."""
    objects = [
        builders.floor("table", 1.6, 1.0),
        builders.wall("wall", (0.0, 0.47, 0.0), 0.0, 1.6, 0.6, 0.03),
        builders.pipe_run("pipe_a", [[-0.65, 0.25, 0.2], [0.15, 0.25, 0.2], [0.15, -0.3, 0.2]], 0.025, 0.07),
        builders.pipe_run("pipe_b", [[-0.7, 0.38, 0.42], [0.7, 0.38, 0.42]], 0.03, 0.09, reducers={0: (0.02, 0.06)}),
        builders.pipe_run("pipe_c", [[-0.45, -0.05, 0.06], [-0.05, -0.35, 0.33]], 0.02, 0.06),
        builders.tank("tank", (0.5, 0.1, 0.0), 0.08, 0.25),
        builders.sphere_tank("sphere", (-0.35, 0.22, 0.0), 0.06, 0.05),
        builders.cabinet("cabinet", (0.45, -0.28, 0.0), 0.3, (0.18, 0.12, 0.22)),
    ]
    return SceneModel("mockup", tuple(objects))


def shipped_scene(name: str) -> Path:
    """Path of a shipped scene file by name (``mockup``, ``factory_bay``)."""
    path = DATA_DIR / f"{name}.yaml"
    if not path.exists():
        known = sorted(p.stem for p in DATA_DIR.glob("*.yaml")
                       if not p.stem.endswith(("_perturbation", "_generator", "_family")))
        raise FileNotFoundError(f"no shipped scene {name!r} (known: {', '.join(known)})")
    return path
