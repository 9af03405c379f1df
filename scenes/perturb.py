"""Perturbation engine: from the a priori model, the actual scene and its change ground truth.

The spec is YAML (schema ``perturbation/1``, magnitudes in metres and degrees)::

    schema: perturbation/1
    moved:   {probability: 0.15, translation: [0.05, 0.5], rotation_deg: [2, 20]}
    missing: {probability: 0.10}
    altered: {probability: 0.10, radius_change: [0.2, 0.5]}
    section_moved: {probability: 0.05, translation: [0.05, 0.3]}   # one section of a pipe run
    new:     {count: [1, 3], pipe_radius: [0.05, 0.15], length: [1.0, 4.0], box_size: [0.4, 1.5]}
    clearance: 0.05          # moved and new parts keep this gap to every other part
    moved_threshold: 0.01    # a feature is truth-moved when its surface moved by at least this much
    protected_kinds: [floor, wall]

Labels (DESIGN 10.7) for features and objects: ``unchanged``, ``moved`` (with its transform),
``missing``, ``altered`` (same place, new shape parameters) and ``new``. An object of which only one
section moved is ``altered`` as a whole, its moved section ``moved``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scenes import builders
from scenes.clearance import ClearanceIndex
from scenes.config import Fields, load_yaml
from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.geometry import make_transform, rotation_about, unit
from scenes.mjcf import box_of_planes
from scenes.model import OBJECT_KINDS, Object, SceneModel

LABELS = ("unchanged", "moved", "missing", "altered", "new")
FLOOR_STANDING = ("tank", "cabinet")


@dataclass(frozen=True)
class Interval:
    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class PerturbationSpec:
    """How a priori objects are changed (see the module docstring for the YAML form)."""

    moved_probability: float = 0.15
    translation: Interval = Interval(0.05, 0.5)
    rotation_deg: Interval = Interval(2.0, 20.0)
    missing_probability: float = 0.10
    altered_probability: float = 0.10
    radius_change: Interval = Interval(0.2, 0.5)
    section_moved_probability: float = 0.05
    section_translation: Interval = Interval(0.05, 0.3)
    new_count: tuple[int, int] = (1, 3)
    new_pipe_radius: Interval = Interval(0.05, 0.15)
    new_length: Interval = Interval(1.0, 4.0)
    new_box_size: Interval = Interval(0.4, 1.5)
    clearance: float = 0.05
    moved_threshold: float = 0.01
    protected_kinds: tuple[str, ...] = ("floor", "wall")
    max_tries: int = 40

    @staticmethod
    def load(path: str | Path) -> PerturbationSpec:
        return PerturbationSpec.from_dict(load_yaml(path), str(path))

    @staticmethod
    def from_dict(data: Any, source: str = "<perturbation>") -> PerturbationSpec:
        root = Fields(data, source)
        schema = root.string("schema", "perturbation/1")
        if schema != "perturbation/1":
            raise root.error("schema", f"unsupported schema {schema!r} (expected 'perturbation/1')")
        d = PerturbationSpec()

        def interval(f: Fields, key: str, default: Interval, upper: float | None = None) -> Interval:
            v = f.vector(key, [default.low, default.high], size=2)
            if v[0] < 0 or v[1] < v[0] or (upper is not None and v[1] > upper):
                bound = f" <= {upper}" if upper is not None else ""
                raise f.error(key, f"expected [low, high] with 0 <= low <= high{bound}, got {v.tolist()}")
            return Interval(float(v[0]), float(v[1]))

        moved, missing, altered = root.sub("moved", {}), root.sub("missing", {}), root.sub("altered", {})
        section, new = root.sub("section_moved", {}), root.sub("new", {})
        count = new.vector("count", list(d.new_count), size=2)
        if count[0] < 0 or count[1] < count[0] or count[1] > 20 or any(c != int(c) for c in count):
            raise new.error("count", "expected whole numbers [low, high] with 0 <= low <= high <= 20, "
                                     f"got {count.tolist()}")
        kinds = root.raw("protected_kinds", list(d.protected_kinds))
        if not isinstance(kinds, list) or any(k not in OBJECT_KINDS for k in kinds):
            raise root.error("protected_kinds", f"expected a list of object kinds from {', '.join(OBJECT_KINDS)}")
        spec = PerturbationSpec(
            moved_probability=moved.number("probability", d.moved_probability, min=0, max=1),
            translation=interval(moved, "translation", d.translation),
            rotation_deg=interval(moved, "rotation_deg", d.rotation_deg, upper=180),
            missing_probability=missing.number("probability", d.missing_probability, min=0, max=1),
            altered_probability=altered.number("probability", d.altered_probability, min=0, max=1),
            radius_change=interval(altered, "radius_change", d.radius_change, upper=0.9),
            section_moved_probability=section.number("probability", d.section_moved_probability, min=0, max=1),
            section_translation=interval(section, "translation", d.section_translation),
            new_count=(int(count[0]), int(count[1])),
            new_pipe_radius=interval(new, "pipe_radius", d.new_pipe_radius),
            new_length=interval(new, "length", d.new_length),
            new_box_size=interval(new, "box_size", d.new_box_size),
            clearance=root.number("clearance", d.clearance, positive=True),
            moved_threshold=root.number("moved_threshold", d.moved_threshold, positive=True),
            protected_kinds=tuple(kinds),
            max_tries=root.integer("max_tries", d.max_tries, min=1, max=10_000),
        )
        total = spec.moved_probability + spec.missing_probability + spec.altered_probability
        if total > 1:
            raise root.error("moved", f"moved + missing + altered probabilities must be <= 1, got {total:.3g}")
        if spec.new_pipe_radius.low <= 0 or spec.new_length.low <= 0 or spec.new_box_size.low <= 0:
            raise new.error(None, "sizes of new parts must be > 0")
        for f in (root, moved, missing, altered, section, new):
            f.check_unknown()
        return spec


@dataclass(frozen=True)
class Change:
    """The truth of one feature or object: its label, the rigid transform of a move (a priori -> actual,
    world frame, (4, 4)) and the largest displacement of its surface in metres."""

    label: str
    transform: np.ndarray | None = None
    displacement_m: float = 0.0
    object_id: str = ""

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"label": self.label}
        if self.object_id:
            d["object"] = self.object_id
        if self.transform is not None:
            d["transform"] = [[float(x) for x in row] for row in self.transform]
            d["displacement_m"] = float(self.displacement_m)
        return d

    @staticmethod
    def from_dict(d: dict[str, Any]) -> Change:
        T = np.array(d["transform"], dtype=np.float64) if "transform" in d else None
        return Change(d["label"], T, float(d.get("displacement_m", 0.0)), d.get("object", ""))


@dataclass(frozen=True)
class ChangeTruth:
    """Ground truth of a perturbation: a label per a priori feature and object, plus the new ones."""

    features: dict[str, Change]
    objects: dict[str, Change]
    new_features: tuple[str, ...] = ()
    new_objects: tuple[str, ...] = ()
    seed: int = 0
    notes: tuple[str, ...] = field(default=())

    def feature_label(self, feature_id: str) -> str:
        """Label of any feature of the a priori or the actual scene (``new`` for added ones)."""
        if feature_id in self.features:
            return self.features[feature_id].label
        if feature_id in self.new_features:
            return "new"
        raise KeyError(feature_id)

    def to_json(self) -> str:
        return json.dumps({"schema": "change_truth/1", "seed": self.seed,
                           "features": {k: v.to_dict() for k, v in self.features.items()},
                           "objects": {k: v.to_dict() for k, v in self.objects.items()},
                           "new_features": list(self.new_features), "new_objects": list(self.new_objects),
                           "notes": list(self.notes)}, indent=1)

    @staticmethod
    def from_json(text: str) -> ChangeTruth:
        d = json.loads(text)
        return ChangeTruth({k: Change.from_dict(v) for k, v in d["features"].items()},
                           {k: Change.from_dict(v) for k, v in d["objects"].items()},
                           tuple(d["new_features"]), tuple(d["new_objects"]), int(d.get("seed", 0)),
                           tuple(d.get("notes", ())))


def surface_displacement(before: Feature, after: Feature, n: int = 1500) -> float:
    """Largest distance between the surfaces of a feature before and after a change (metres), estimated
    on ``n`` samples each way (symmetric, so a slide along a pipe's axis counts and a spin about it does not)."""
    rng = np.random.default_rng(7)
    a = after.sample(n, rng)[0]
    b = before.sample(n, rng)[0]
    return float(max(before.surface_distance(a).max(), after.surface_distance(b).max()))


def _centroid(obj: Object) -> np.ndarray:
    return np.mean([f.sample(64, np.random.default_rng(1))[0].mean(axis=0) for f in obj.features], axis=0)


def _bounds(model: SceneModel) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal extent (x, y) of the floor objects, or of everything when there is no floor."""
    floors = [f for o in model.objects if o.kind == "floor" for f in o.features if isinstance(f, Plane)]
    pts = np.concatenate([f.corners() for f in floors]) if floors else \
        np.concatenate([f.sample(64, np.random.default_rng(1))[0] for f in model.features])
    return pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    return unit(rng.normal(size=3))


def _scaled(obj: Object, k: float) -> Object | None:
    """``obj`` with its radii scaled by ``k`` (pipe runs, tanks) or its height (cabinets); None if impossible."""
    feats: list[Feature] = []
    if obj.kind == "cabinet":
        box = box_of_planes(obj.features)
        if box is None:
            return None
        centre, R, half, _ = box
        base = centre - R[:, 2] * half[2]
        return builders.cabinet(obj.id, base, math.atan2(R[1, 0], R[0, 0]),
                                (2 * half[0], 2 * half[1], 2 * half[2] * k), material=obj.features[0].material)
    for f in obj.features:
        if isinstance(f, Cylinder):
            feats.append(_replace(f, radius=f.radius * k))
        elif isinstance(f, Sphere):
            cap_h = None if f.cap_height is None else f.cap_height * k
            feats.append(_replace(f, radius=f.radius * k, cap_height=cap_h))
        elif isinstance(f, Torus):
            if f.minor_radius * k >= f.major_radius * 0.95:
                return None
            feats.append(_replace(f, minor_radius=f.minor_radius * k))
        elif isinstance(f, Cone):
            p0 = f.apex + f.axis * f.start
            tan_a = math.tan(f.half_angle) * k
            start = float(f.radius_at(f.start)) * k / tan_a
            feats.append(_replace(f, half_angle=math.atan(tan_a), apex=p0 - f.axis * start, start=start,
                                  end=start + (f.end - f.start)))
        else:
            feats.append(f)
    return Object(obj.id, obj.kind, tuple(feats))


def _replace(f: Feature, **kw: Any) -> Feature:
    from dataclasses import replace

    return replace(f, **kw)


def perturb(model: SceneModel, spec: PerturbationSpec, seed: int) -> tuple[SceneModel, ChangeTruth]:
    """Draw the actual scene from the a priori ``model`` and return it with its change truth.

    Deterministic in ``seed``. Moved, altered and new parts keep ``spec.clearance`` from every other part
    (floor-standing tanks and cabinets slide and turn on the floor; pipe runs move freely).
    """
    rng = np.random.default_rng([seed, 0xC4A9])
    spacing = spec.clearance / 2
    index = ClearanceIndex(spacing, spec.clearance)
    floor_ids = {o.id for o in model.objects if o.kind == "floor"}
    for o in model.objects:
        if o.kind != "floor":
            index.add(o)
    (xmin, ymin), (xmax, ymax) = _bounds(model)
    actual: dict[str, Object] = {o.id: o for o in model.objects}
    feat_truth: dict[str, Change] = {}
    obj_truth: dict[str, Change] = {}
    notes: list[str] = []

    def inside_bay(obj: Object) -> bool:
        pts = np.concatenate([f.sample(200, np.random.default_rng(3))[0] for f in obj.features])
        return bool(np.all(pts[:, 0] >= xmin) and np.all(pts[:, 0] <= xmax) and np.all(pts[:, 1] >= ymin)
                    and np.all(pts[:, 1] <= ymax) and np.all(pts[:, 2] >= -1e-9))

    def try_place(candidate: Object) -> bool:
        if not inside_bay(candidate):
            return False
        ignore = floor_ids | {candidate.id}
        if candidate.kind not in FLOOR_STANDING:
            ignore = {candidate.id}
        return not index.collides(candidate, ignore=ignore)

    for obj in model.objects:
        u = rng.uniform()
        section_draw = rng.uniform()
        if obj.kind in spec.protected_kinds:
            continue
        if u < spec.moved_probability:
            moved = None
            for _ in range(spec.max_tries):
                T = _draw_move(obj, spec, rng)
                cand = obj.transformed(T)
                if try_place(cand):
                    moved = (cand, T)
                    break
            if moved is None:
                notes.append(f"{obj.id}: no collision-free move found, left unchanged")
                continue
            cand, T = moved
            actual[obj.id] = cand
            index.add(cand)
            disp = {f.id: surface_displacement(f, g) for f, g in zip(obj.features, cand.features, strict=True)}
            for fid, dm in disp.items():
                lab = "moved" if dm >= spec.moved_threshold else "unchanged"
                feat_truth[fid] = Change(lab, T if lab == "moved" else None, dm, obj.id)
            obj_truth[obj.id] = Change("moved", T, max(disp.values()))
        elif u < spec.moved_probability + spec.missing_probability:
            del actual[obj.id]
            index.remove(obj.id)
            for f in obj.features:
                feat_truth[f.id] = Change("missing", object_id=obj.id)
            obj_truth[obj.id] = Change("missing")
        elif u < spec.moved_probability + spec.missing_probability + spec.altered_probability:
            done = False
            for _ in range(spec.max_tries):
                k = 1.0 + rng.choice([-1.0, 1.0]) * spec.radius_change.draw(rng)
                cand = _scaled(obj, k)
                if cand is not None and try_place(cand):
                    done = True
                    break
            if not done:
                notes.append(f"{obj.id}: no valid alteration found, left unchanged")
                continue
            actual[obj.id] = cand
            index.add(cand)
            for f, g in zip(obj.features, cand.features, strict=True):
                feat_truth[f.id] = Change("altered" if f != g else "unchanged", object_id=obj.id)
            obj_truth[obj.id] = Change("altered")
        elif obj.kind == "pipe_run" and section_draw < spec.section_moved_probability:
            sections = [i for i, f in enumerate(obj.features) if isinstance(f, Cylinder)]
            if len(sections) < 2:
                continue
            i = sections[int(rng.integers(len(sections)))]
            f = obj.features[i]
            placed = False
            for _ in range(spec.max_tries):
                direction = unit(np.cross(f.axis, _random_unit(rng)))
                T = make_transform(np.eye(3), direction * spec.section_translation.draw(rng))
                g = f.transformed(T)
                cand = Object(obj.id, obj.kind, obj.features[:i] + (g,) + obj.features[i + 1:])
                section_obj = Object(obj.id + "#section", obj.kind, (g,))
                if inside_bay(section_obj) and not index.collides(section_obj, ignore={obj.id}):
                    placed = True
                    break
            if not placed:
                continue
            actual[obj.id] = cand
            index.add(cand)
            dm = surface_displacement(f, g)
            for h in obj.features:
                feat_truth[h.id] = Change("unchanged", object_id=obj.id)
            feat_truth[f.id] = Change("moved" if dm >= spec.moved_threshold else "unchanged", T, dm, obj.id)
            obj_truth[obj.id] = Change("altered")
    for obj in model.objects:
        obj_truth.setdefault(obj.id, Change("unchanged"))
        for f in obj.features:
            feat_truth.setdefault(f.id, Change("unchanged", object_id=obj.id))

    new_objects: list[Object] = []
    n_new = int(rng.integers(spec.new_count[0], spec.new_count[1] + 1))
    for i in range(n_new):
        for _ in range(spec.max_tries):
            cand = _draw_new(f"new{i}", spec, rng, (xmin, ymin, xmax, ymax), model)
            if cand is not None and try_place(cand):
                new_objects.append(cand)
                index.add(cand)
                break
        else:
            notes.append(f"new{i}: no collision-free place found, not added")
    objects = [actual[o.id] for o in model.objects if o.id in actual] + new_objects
    truth = ChangeTruth(feat_truth, obj_truth, tuple(f.id for o in new_objects for f in o.features),
                        tuple(o.id for o in new_objects), seed, tuple(notes))
    return SceneModel(model.name, tuple(objects)), truth


def _draw_move(obj: Object, spec: PerturbationSpec, rng: np.random.Generator) -> np.ndarray:
    """A rigid move (4, 4) of ``obj`` about its centroid: turns about the vertical for floor-standing parts."""
    c = _centroid(obj)
    angle = math.radians(spec.rotation_deg.draw(rng)) * rng.choice([-1.0, 1.0])
    dist = spec.translation.draw(rng)
    if obj.kind in FLOOR_STANDING:
        axis = np.array([0.0, 0.0, 1.0])
        phi = rng.uniform(0, 2 * np.pi)
        t = dist * np.array([math.cos(phi), math.sin(phi), 0.0])
    else:
        axis = _random_unit(rng)
        t = dist * _random_unit(rng)
    R = rotation_about(axis, angle)
    return make_transform(R, c - R @ c + t)


def _draw_new(object_id: str, spec: PerturbationSpec, rng: np.random.Generator,
              bounds: tuple[float, float, float, float], model: SceneModel) -> Object | None:
    """A new straight pipe (horizontal, at the height of existing pipes) or a new cabinet."""
    xmin, ymin, xmax, ymax = bounds
    heights = [float(f.centre[2]) for f in model.features if isinstance(f, Cylinder)]
    zmax = max(heights) if heights else 1.0
    if rng.uniform() < 0.6:
        r = spec.new_pipe_radius.draw(rng)
        length = spec.new_length.draw(rng)
        z = rng.uniform(2 * r + spec.clearance, max(zmax, 3 * r + spec.clearance))
        p = np.array([rng.uniform(xmin, xmax), rng.uniform(ymin, ymax), z])
        phi = rng.uniform(0, np.pi)
        q = p + length * np.array([math.cos(phi), math.sin(phi), 0.0])
        return builders.pipe_run(object_id, [p, q], r, 2 * r, material="metal")
    w, d, h = (spec.new_box_size.draw(rng) for _ in range(3))
    if xmax - xmin < 2 * w or ymax - ymin < 2 * w:
        raise ValueError(f"a new box of {w:.2f} m does not fit the scene's floor ({xmax - xmin:.2f} x "
                         f"{ymax - ymin:.2f} m): the perturbation spec's new_box_size is for a larger scene "
                         "(the mock-up has its own spec, scenes/data/mockup_perturbation.yaml)")
    x, y = rng.uniform(xmin + w, xmax - w), rng.uniform(ymin + w, ymax - w)
    return builders.cabinet(object_id, (x, y, 0.0), rng.uniform(0, np.pi), (w, d, h))
