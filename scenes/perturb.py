"""Perturbation engine: from the a priori model, the actual scene and its change ground truth.

The spec is YAML (schema ``perturbation/1``, magnitudes in metres and degrees, changes relative)::

    schema: perturbation/1
    moved:   {probability: 0.15, translation: [0.05, 0.5], rotation_deg: [2, 20]}
    missing: {probability: 0.10}
    altered: {probability: 0.10, radius_change: [0.2, 0.5], size_change: [0.2, 0.5], by_kind: {wall: 0.05}}
    section_moved: {probability: 0.05, translation: [0.05, 0.3]}   # one section of a pipe run
    new:     {count: [1, 3], kinds: {pipe_run: 0.4, cabinet: 0.2, tank: 0.2, sphere_tank: 0.2},
              pipe_radius: [0.05, 0.15], length: [1.0, 4.0], box_size: [0.4, 1.5],
              tank_radius: [0.3, 0.8], tank_height: [1.0, 2.5]}
    clearance: 0.05          # moved, altered and new parts keep this gap to every other part
    moved_threshold: 0.01    # a feature is truth-moved when its surface moved by at least this much
    protected_kinds: [floor] # kinds never changed at all

Kinds of objects (:func:`change_kind`): ``pipe_run``, ``tank`` (cylindrical, with a hemispherical top),
``sphere_tank`` (a ``tank`` object whose features include a whole sphere: a ball on a leg), ``cabinet``,
``structure``, ``wall`` and ``floor``. Each a priori object draws one of moved, missing, altered (with the
probabilities of its kind, in that order of a single uniform draw) or stays unchanged; a pipe run left
unchanged then has one straight section moved with ``section_moved.probability``.

Rates per kind: every ``moved``, ``missing`` and ``altered`` section has a ``probability`` for all kinds and
an optional ``by_kind: {kind: probability}`` that overrides it for the kinds it names; per kind the three
must sum to at most 1. Walls and the floor are a bay's structure: they are never moved, removed or added
(``moved.by_kind`` and ``missing.by_kind`` refuse them); walls may be altered, the floor never changes.
``protected_kinds`` (default ``[floor, wall]``, the older specs' value) are never changed at all. The
shipped specs (``scenes/data/mockup_perturbation.yaml``, ``scenes/data/factory_bay_perturbation.yaml``)
protect only the floor and draw per object:

===========  ======  =======  =======  ==========================================================
kind         moved   missing  altered  what an alteration changes (each by a factor 1 +- change)
===========  ======  =======  =======  ==========================================================
pipe_run     0.15    0.10     0.10     the radius of every section, elbow and reducer (radius_change)
tank         0.15    0.10     0.10     radius (radius_change) and/or body height (size_change)
sphere_tank  0.15    0.10     0.10     ball radius (radius_change); its leg follows, its base stays
cabinet      0.15    0.10     0.10     one or more of width, depth, height (size_change); base stays
wall         never   never    0.05     length and/or height (size_change); base and centre stay
floor        never   never    never
===========  ======  =======  =======  ==========================================================

An unchanged pipe run then has one section moved with probability 0.05 (0.0325 of all pipe runs). An
alteration changes a non-empty subset of its kind's dimensions (each subset equally likely), each grown or
shrunk (equally likely) by a factor drawn from ``radius_change`` (radii) or ``size_change`` (lengths); a
draw that does not fit (interpenetration, off the floor) is redrawn up to ``max_tries`` times. Elbow bend
radii and reducer angles are not altered. ``new`` adds ``count`` objects of the ``kinds`` drawn with those
relative weights (a kind left out of ``kinds`` is never drawn; shipped: pipe run 0.4, cabinet 0.2, tank 0.2,
spherical tank 0.2): a straight horizontal pipe (``pipe_radius``, ``length``, at the height of the scene's
pipes), a cabinet (``box_size`` per side), a tank (``tank_radius``, body ``tank_height``) or a spherical
tank (``tank_radius``, a leg of 0.5-1.5 radii).

Labels (DESIGN 10.7) for features and objects: ``unchanged``, ``moved`` (with its transform),
``missing``, ``altered`` (same place, new shape parameters) and ``new``. The features of an altered object
that did not change (a cabinet's bottom when its height changed) stay ``unchanged``. An object of which only
one section moved is ``altered`` as a whole, its moved section ``moved``.

Randomness: the draws come from ``default_rng([seed, 0xC4A9, scene_key(model)])``, where
:func:`scene_key` is the first 64 bits of the SHA-256 of the YAML of the model's objects (its name left
out; not Python's ``hash``, which is salted per process). So the change pattern depends on the scene as well
as the seed: two bays with the same object list but other geometry get different patterns from one seed,
while the same scene (also read back from its YAML file) and seed give the same draw in every process.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from scenes import builders
from scenes.clearance import ClearanceIndex
from scenes.config import Fields, dump_yaml, load_yaml
from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.generator import DATA_DIR
from scenes.geometry import make_transform, rotation_about, unit
from scenes.mjcf import box_of_planes
from scenes.model import Object, SceneModel
from scenes.vocabulary import CHANGE_LABELS

LABELS = CHANGE_LABELS  # the truth labels of features and objects (scenes.vocabulary)
FLOOR_STANDING = ("tank", "cabinet")
#: Kinds of objects as the perturbation tells them apart (:func:`change_kind`).
CHANGE_KINDS = ("floor", "wall", "pipe_run", "tank", "sphere_tank", "cabinet", "structure")
#: A bay's structure: never moved, removed or added (walls may be altered, the floor never changes).
STRUCTURE_KINDS = ("floor", "wall")
MOVABLE_KINDS = ("pipe_run", "tank", "sphere_tank", "cabinet", "structure")
ALTERABLE_KINDS = ("wall", *MOVABLE_KINDS)
NEW_KINDS = ("pipe_run", "cabinet", "tank", "sphere_tank")
#: What an alteration of each kind may change (a non-empty subset is drawn).
ALTERED_DIMENSIONS: dict[str, tuple[str, ...]] = {
    "pipe_run": ("radius",), "structure": ("radius",), "tank": ("radius", "height"), "sphere_tank": ("radius",),
    "cabinet": ("width", "depth", "height"), "wall": ("length", "height")}
#: The shipped specs.
MOCKUP_PERTURBATION = DATA_DIR / "mockup_perturbation.yaml"
FACTORY_BAY_PERTURBATION = DATA_DIR / "factory_bay_perturbation.yaml"
_STREAM = 0xC4A9
_SAME_TOL = 1e-12  # parameters closer than this (metres, radians) are unchanged
_MAX_LENGTH_M = 1000.0  # a sanity bound of every length in a spec

KindRates = tuple[tuple[str, float], ...]


@dataclass(frozen=True)
class Interval:
    """A closed interval [low, high] to draw from uniformly."""

    low: float
    high: float

    def draw(self, rng: np.random.Generator) -> float:
        return float(rng.uniform(self.low, self.high))


@dataclass(frozen=True)
class PerturbationSpec:
    """How a priori objects are changed (see the module docstring for the YAML form and the rates).

    ``*_by_kind`` are ``((kind, probability), ...)`` overrides of the section's probability; ``new_kinds``
    are ``((kind, weight), ...)``. Lengths in metres, ``rotation_deg`` in degrees, changes relative.
    """

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
    moved_by_kind: KindRates = ()
    missing_by_kind: KindRates = ()
    altered_by_kind: KindRates = ()
    size_change: Interval = Interval(0.2, 0.5)
    new_kinds: KindRates = (("pipe_run", 0.4), ("cabinet", 0.2), ("tank", 0.2), ("sphere_tank", 0.2))
    new_tank_radius: Interval = Interval(0.3, 0.8)
    new_tank_height: Interval = Interval(1.0, 2.5)

    def rates(self, kind: str) -> tuple[float, float, float]:
        """Probabilities (moved, missing, altered) of one object of ``kind`` (a :data:`CHANGE_KINDS` entry),
        after ``protected_kinds`` and the structure rule (walls only altered, the floor never changed)."""
        if kind in self.protected_kinds or kind == "floor":
            return 0.0, 0.0, 0.0
        altered = dict(self.altered_by_kind).get(kind, self.altered_probability)
        if kind in STRUCTURE_KINDS:
            return 0.0, 0.0, altered
        return (dict(self.moved_by_kind).get(kind, self.moved_probability),
                dict(self.missing_by_kind).get(kind, self.missing_probability), altered)

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
        moved, missing, altered = root.sub("moved", {}), root.sub("missing", {}), root.sub("altered", {})
        section, new = root.sub("section_moved", {}), root.sub("new", {})
        count = new.vector("count", list(d.new_count), size=2)
        if count[0] < 0 or count[1] < count[0] or count[1] > 20 or any(c != int(c) for c in count):
            raise new.error("count", "expected whole numbers [low, high] with 0 <= low <= high <= 20, "
                                     f"got {count.tolist()}")
        kinds = root.raw("protected_kinds", list(d.protected_kinds))
        if not isinstance(kinds, list) or any(not isinstance(k, str) or k not in CHANGE_KINDS for k in kinds):
            raise root.error("protected_kinds", f"expected a list of object kinds from {', '.join(CHANGE_KINDS)}")
        spec = PerturbationSpec(
            moved_probability=moved.number("probability", d.moved_probability, min=0, max=1),
            translation=_interval(moved, "translation", d.translation),
            rotation_deg=_interval(moved, "rotation_deg", d.rotation_deg, upper=180),
            missing_probability=missing.number("probability", d.missing_probability, min=0, max=1),
            altered_probability=altered.number("probability", d.altered_probability, min=0, max=1),
            radius_change=_interval(altered, "radius_change", d.radius_change, upper=0.9),
            section_moved_probability=section.number("probability", d.section_moved_probability, min=0, max=1),
            section_translation=_interval(section, "translation", d.section_translation),
            new_count=(int(count[0]), int(count[1])),
            new_pipe_radius=_interval(new, "pipe_radius", d.new_pipe_radius),
            new_length=_interval(new, "length", d.new_length),
            new_box_size=_interval(new, "box_size", d.new_box_size),
            clearance=root.number("clearance", d.clearance, positive=True, min=1e-4, max=10.0),
            moved_threshold=root.number("moved_threshold", d.moved_threshold, positive=True),
            protected_kinds=tuple(kinds),
            max_tries=root.integer("max_tries", d.max_tries, min=1, max=10_000),
            moved_by_kind=_by_kind(moved, MOVABLE_KINDS, "moved"),
            missing_by_kind=_by_kind(missing, MOVABLE_KINDS, "removed"),
            altered_by_kind=_by_kind(altered, ALTERABLE_KINDS, "altered"),
            size_change=_interval(altered, "size_change", d.size_change, upper=0.9),
            new_kinds=_new_kinds(new, d.new_kinds),
            new_tank_radius=_interval(new, "tank_radius", d.new_tank_radius),
            new_tank_height=_interval(new, "tank_height", d.new_tank_height),
        )
        for kind in CHANGE_KINDS:
            total = sum(spec.rates(kind))
            if total > 1:
                raise root.error("moved", "moved + missing + altered probabilities must be <= 1, "
                                          f"got {total:.3g} for {kind}")
        if min(spec.new_pipe_radius.low, spec.new_length.low, spec.new_box_size.low, spec.new_tank_radius.low,
               spec.new_tank_height.low) <= 0:
            raise new.error(None, "sizes of new parts must be > 0")
        for f in (root, moved, missing, altered, section, new):
            f.check_unknown()
        return spec


def _interval(f: Fields, key: str, default: Interval, upper: float = _MAX_LENGTH_M) -> Interval:
    v = f.vector(key, [default.low, default.high], size=2)
    if v[0] < 0 or v[1] < v[0] or v[1] > upper:
        raise f.error(key, f"expected [low, high] with 0 <= low <= high <= {upper:g}, got {v.tolist()}")
    return Interval(float(v[0]), float(v[1]))


def _by_kind(section: Fields, allowed: tuple[str, ...], verb: str) -> KindRates:
    """The optional ``by_kind: {kind: probability}`` of a section (kinds from ``allowed``, in that order)."""
    f = section.sub("by_kind", {})
    for key in f.data:
        if key == "floor":
            raise f.error(str(key), "the floor never changes")
        if key in STRUCTURE_KINDS and key not in allowed:
            raise f.error(str(key), f"walls are never {verb} (a bay's structure); they can be altered")
    f.check_unknown(allowed)
    return tuple((k, f.number(k, min=0, max=1)) for k in allowed if f.has(k))


def _new_kinds(new: Fields, default: KindRates) -> KindRates:
    """The optional ``kinds: {kind: weight}`` of new objects (kinds left out are not drawn)."""
    if not new.has("kinds"):
        return default
    f = new.sub("kinds")
    f.check_unknown(NEW_KINDS)
    weights = tuple((k, f.number(k, nonnegative=True, max=1e6)) for k in NEW_KINDS if f.has(k))
    if sum(w for _, w in weights) <= 0:
        raise new.error("kinds", f"needs a kind with a weight > 0 (kinds: {', '.join(NEW_KINDS)})")
    return weights


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


def scene_key(model: SceneModel) -> int:
    """A stable 64-bit key of the model's geometry, mixed into the perturbation's random stream.

    The first 8 bytes (little-endian) of the SHA-256 of the YAML of ``model``'s objects; the model's name is
    left out. The same in every process and for the model read back from its YAML file.
    """
    text = dump_yaml(model.to_dict()["objects"])
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "little")


def change_kind(obj: Object) -> str:
    """The kind that sets ``obj``'s rates (:data:`CHANGE_KINDS`): its object kind, except ``sphere_tank`` for a
    tank that holds a whole sphere (a ball on a leg)."""
    if obj.kind == "tank" and any(isinstance(f, Sphere) and f.cap_axis is None for f in obj.features):
        return "sphere_tank"
    return obj.kind


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


def perturb(model: SceneModel, spec: PerturbationSpec, seed: int) -> tuple[SceneModel, ChangeTruth]:
    """Draw the actual scene from the a priori ``model`` and return it with its change truth.

    Deterministic in (``model``, ``seed``): see the module docstring. Moved, altered and new parts keep
    ``spec.clearance`` from every other part and stay over the floor (floor-standing tanks and cabinets
    slide and turn on the floor; pipe runs move freely; walls meet each other at the corners).
    """
    rng = np.random.default_rng([seed, _STREAM, scene_key(model)])
    p = _Perturbation(model, spec, rng)
    for obj in model.objects:
        p.change(obj)
    for obj in model.objects:
        p.obj_truth.setdefault(obj.id, Change("unchanged"))
        for f in obj.features:
            p.feat_truth.setdefault(f.id, Change("unchanged", object_id=obj.id))
    new_objects = p.add_new()
    objects = [p.actual[o.id] for o in model.objects if o.id in p.actual] + new_objects
    truth = ChangeTruth(p.feat_truth, p.obj_truth, tuple(f.id for o in new_objects for f in o.features),
                        tuple(o.id for o in new_objects), seed, tuple(p.notes))
    return SceneModel(model.name, tuple(objects)), truth


class _Perturbation:
    """The state of one perturbation: the clearance index, the actual objects and the truth so far."""

    def __init__(self, model: SceneModel, spec: PerturbationSpec, rng: np.random.Generator):
        self.model, self.spec, self.rng = model, spec, rng
        self.index = ClearanceIndex(spec.clearance / 2, spec.clearance)
        self.floor_ids = {o.id for o in model.objects if o.kind == "floor"}
        self.wall_ids = {o.id for o in model.objects if o.kind == "wall"}
        for o in model.objects:
            if o.kind != "floor":
                self.index.add(o)
        (xmin, ymin), (xmax, ymax) = _bounds(model)
        self.bounds = (float(xmin), float(ymin), float(xmax), float(ymax))
        self.actual: dict[str, Object] = {o.id: o for o in model.objects}
        self.feat_truth: dict[str, Change] = {}
        self.obj_truth: dict[str, Change] = {}
        self.notes: list[str] = []

    def inside_bay(self, obj: Object) -> bool:
        xmin, ymin, xmax, ymax = self.bounds
        pts = np.concatenate([f.sample(200, np.random.default_rng(3))[0] for f in obj.features])
        tol = 1e-9  # walls end flush with the floor's edge
        return bool(np.all(pts[:, 0] >= xmin - tol) and np.all(pts[:, 0] <= xmax + tol)
                    and np.all(pts[:, 1] >= ymin - tol) and np.all(pts[:, 1] <= ymax + tol)
                    and np.all(pts[:, 2] >= -tol))

    def try_place(self, candidate: Object, ignore: set[str] | None = None) -> bool:
        """True when ``candidate`` lies over the floor and keeps the clearance from the other parts (the floor
        ignored for floor-standing parts and walls, the other walls for walls)."""
        if not self.inside_bay(candidate):
            return False
        if ignore is None:
            ignore = {candidate.id}
            if candidate.kind in FLOOR_STANDING or candidate.kind == "wall":
                ignore |= self.floor_ids
            if candidate.kind == "wall":
                ignore |= self.wall_ids
        return not self.index.collides(candidate, ignore=ignore)

    def put(self, obj: Object) -> None:
        self.actual[obj.id] = obj
        self.index.add(obj)

    def change(self, obj: Object) -> None:
        """Draw and apply the change of one a priori object (two uniform draws for every object)."""
        u, section_draw = self.rng.uniform(), self.rng.uniform()
        kind = change_kind(obj)
        moved, missing, altered = self.spec.rates(kind)
        if u < moved:
            self.move(obj)
        elif u < moved + missing:
            self.remove(obj)
        elif u < moved + missing + altered:
            self.alter(obj, kind)
        elif kind == "pipe_run" and kind not in self.spec.protected_kinds \
                and section_draw < self.spec.section_moved_probability:
            self.move_section(obj)

    def move(self, obj: Object) -> None:
        for _ in range(self.spec.max_tries):
            T = _draw_move(obj, self.spec, self.rng)
            cand = obj.transformed(T)
            if self.try_place(cand):
                break
        else:
            self.notes.append(f"{obj.id}: no collision-free move found, left unchanged")
            return
        self.put(cand)
        disp = {f.id: surface_displacement(f, g) for f, g in zip(obj.features, cand.features, strict=True)}
        for fid, dm in disp.items():
            lab = "moved" if dm >= self.spec.moved_threshold else "unchanged"
            self.feat_truth[fid] = Change(lab, T if lab == "moved" else None, dm, obj.id)
        self.obj_truth[obj.id] = Change("moved", T, max(disp.values()))

    def remove(self, obj: Object) -> None:
        del self.actual[obj.id]
        self.index.remove(obj.id)
        for f in obj.features:
            self.feat_truth[f.id] = Change("missing", object_id=obj.id)
        self.obj_truth[obj.id] = Change("missing")

    def alter(self, obj: Object, kind: str) -> None:
        for _ in range(self.spec.max_tries):
            cand = _altered(obj, kind, self.spec, self.rng)
            if cand is not None and self.try_place(cand):
                break
        else:
            self.notes.append(f"{obj.id}: no valid alteration found, left unchanged")
            return
        self.put(cand)
        for f, g in zip(obj.features, cand.features, strict=True):
            self.feat_truth[f.id] = Change("altered" if f != g else "unchanged", object_id=obj.id)
        self.obj_truth[obj.id] = Change("altered")

    def move_section(self, obj: Object) -> None:
        sections = [i for i, f in enumerate(obj.features) if isinstance(f, Cylinder)]
        if len(sections) < 2:
            return
        i = sections[int(self.rng.integers(len(sections)))]
        f = obj.features[i]
        for _ in range(self.spec.max_tries):
            direction = unit(np.cross(f.axis, _random_unit(self.rng)))
            T = make_transform(np.eye(3), direction * self.spec.section_translation.draw(self.rng))
            g = f.transformed(T)
            if self.try_place(Object(obj.id + "#section", obj.kind, (g,)), ignore={obj.id}):
                break
        else:
            return
        self.put(Object(obj.id, obj.kind, obj.features[:i] + (g,) + obj.features[i + 1:]))
        dm = surface_displacement(f, g)
        for h in obj.features:
            self.feat_truth[h.id] = Change("unchanged", object_id=obj.id)
        self.feat_truth[f.id] = Change("moved" if dm >= self.spec.moved_threshold else "unchanged", T, dm, obj.id)
        self.obj_truth[obj.id] = Change("altered")

    def add_new(self) -> list[Object]:
        """Draw ``spec.new_count`` new objects and place those that fit (the others are noted)."""
        new_objects: list[Object] = []
        n_new = int(self.rng.integers(self.spec.new_count[0], self.spec.new_count[1] + 1))
        for i in range(n_new):
            for _ in range(self.spec.max_tries):
                cand = _draw_new(f"new{i}", self.spec, self.rng, self.bounds, self.model)
                if cand is not None and self.try_place(cand):
                    new_objects.append(cand)
                    self.index.add(cand)
                    break
            else:
                self.notes.append(f"new{i}: no collision-free place found, not added")
        return new_objects


# -- alterations ------------------------------------------------------------------------------------------


def _altered(obj: Object, kind: str, spec: PerturbationSpec, rng: np.random.Generator) -> Object | None:
    """``obj`` with a non-empty subset of its kind's dimensions each scaled by ``1 +- change``; None when the
    object's shape is not one this kind can be altered in (or the draw is impossible)."""
    dims = ALTERED_DIMENSIONS[kind]
    mask = int(rng.integers(1, 2 ** len(dims)))
    factors: dict[str, float] = {}
    for bit, dim in enumerate(dims):
        if mask >> bit & 1:
            change = spec.radius_change if dim == "radius" else spec.size_change
            factors[dim] = 1.0 + float(rng.choice([-1.0, 1.0])) * change.draw(rng)
    if kind in ("cabinet", "wall"):
        return _resized_box(obj, factors)
    if kind in ("tank", "sphere_tank"):
        return _resized_tank(obj, factors)
    return _scaled(obj, factors["radius"])


def _resized_box(obj: Object, factors: dict[str, float]) -> Object | None:
    """A box object (cabinet, wall) with its ``width`` or ``length`` (the first horizontal box axis, as the
    builders make them), ``depth`` (the second) and ``height`` scaled; its base stays on the floor, centred
    where it was. Faces that do not change are kept as they are."""
    box = box_of_planes(obj.features)
    if box is None:
        return None
    _, R, half, _ = box
    vertical = int(np.argmax(np.abs(R[2])))
    first, second = (k for k in range(3) if k != vertical)
    axis_of = {"width": first, "length": first, "depth": second, "height": vertical}
    scale = np.ones(3)
    for dim, k in factors.items():
        scale[axis_of[dim]] = k
    rise = R[:, vertical] * np.sign(R[2, vertical]) * half[vertical] * (scale[vertical] - 1)
    faces = []
    for p in obj.features:
        k, ku, kv = (int(np.argmax(np.abs(R.T @ v))) for v in (p.normal, p.u_axis, p.v_axis))
        g = replace(p, centre=p.centre + rise + p.normal * half[k] * (scale[k] - 1),
                    half_size=(p.half_size[0] * scale[ku], p.half_size[1] * scale[kv]))
        faces.append(p if _same(p, g) else g)
    return Object(obj.id, obj.kind, tuple(faces))


def _resized_tank(obj: Object, factors: dict[str, float]) -> Object | None:
    """A tank rebuilt with its ``radius`` and body ``height`` scaled (a spherical tank: its ball's radius, the
    leg following); its base stays. Tanks of another shape only have their radii scaled (:func:`_scaled`)."""
    cyl = [f for f in obj.features if isinstance(f, Cylinder)]
    sph = [f for f in obj.features if isinstance(f, Sphere)]
    upright = len(cyl) == 1 and abs(abs(float(cyl[0].axis[2])) - 1.0) < 1e-9
    if len(obj.features) != 2 or len(sph) != 1 or not upright:
        return _scaled(obj, factors["radius"]) if set(factors) == {"radius"} else None
    body, ball = cyl[0], sph[0]
    base = body.centre - np.array([0.0, 0.0, body.length / 2])
    kr, kh = factors.get("radius", 1.0), factors.get("height", 1.0)
    if ball.cap_axis is None:
        leg_height = float(ball.centre[2] - base[2]) - ball.radius
        rebuilt = builders.sphere_tank(obj.id, base, ball.radius * kr, leg_height)
    else:
        rebuilt = builders.tank(obj.id, base, body.radius * kr, body.length * kh)
    by_type = {type(g): g for g in rebuilt.features}
    feats = []
    for f in obj.features:
        g = replace(by_type[type(f)], id=f.id, material=f.material)
        feats.append(f if _same(f, g) else g)
    return Object(obj.id, obj.kind, tuple(feats))


def _same(f: Feature, g: Feature) -> bool:
    """True when two features of one type have the same parameters within ``_SAME_TOL``."""
    if type(f) is not type(g):
        return False
    for fld in fields(f):
        a, b = getattr(f, fld.name), getattr(g, fld.name)
        if a is None or b is None or isinstance(a, str):
            if a != b:
                return False
        elif not np.allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float), rtol=0, atol=_SAME_TOL):
            return False
    return True


def _scaled(obj: Object, k: float) -> Object | None:
    """``obj`` with every radius scaled by ``k`` (pipe runs' sections, elbows and reducers; structures, tanks of
    another shape); None if impossible."""
    feats: list[Feature] = []
    for f in obj.features:
        if isinstance(f, Cylinder):
            feats.append(replace(f, radius=f.radius * k))
        elif isinstance(f, Sphere):
            cap_h = None if f.cap_height is None else f.cap_height * k
            feats.append(replace(f, radius=f.radius * k, cap_height=cap_h))
        elif isinstance(f, Torus):
            if f.minor_radius * k >= f.major_radius * 0.95:
                return None
            feats.append(replace(f, minor_radius=f.minor_radius * k))
        elif isinstance(f, Cone):
            p0 = f.apex + f.axis * f.start
            tan_a = math.tan(f.half_angle) * k
            start = float(f.radius_at(f.start)) * k / tan_a
            feats.append(replace(f, half_angle=math.atan(tan_a), apex=p0 - f.axis * start, start=start,
                                 end=start + (f.end - f.start)))
        else:
            feats.append(f)
    return Object(obj.id, obj.kind, tuple(feats))



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


# -- new objects -----------------------------------------------------------------------------------------

Bounds = tuple[float, float, float, float]


def _draw_new(object_id: str, spec: PerturbationSpec, rng: np.random.Generator, bounds: Bounds,
              model: SceneModel) -> Object | None:
    """A new object of a kind drawn with the weights of ``spec.new_kinds``, somewhere over the floor
    ``bounds`` (xmin, ymin, xmax, ymax), metres."""
    kinds = [k for k, _ in spec.new_kinds]
    weights = np.array([w for _, w in spec.new_kinds])
    kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
    if kind == "pipe_run":
        return _new_pipe(object_id, spec, rng, bounds, model)
    if kind == "cabinet":
        return _new_cabinet(object_id, spec, rng, bounds)
    return _new_tank(object_id, spec, rng, bounds, spherical=kind == "sphere_tank")


def _new_pipe(object_id: str, spec: PerturbationSpec, rng: np.random.Generator, bounds: Bounds,
              model: SceneModel) -> Object:
    """A straight horizontal pipe at a height up to that of the scene's highest cylinder."""
    xmin, ymin, xmax, ymax = bounds
    heights = [float(f.centre[2]) for f in model.features if isinstance(f, Cylinder)]
    zmax = max(heights) if heights else 1.0
    r = spec.new_pipe_radius.draw(rng)
    length = spec.new_length.draw(rng)
    z = rng.uniform(2 * r + spec.clearance, max(zmax, 3 * r + spec.clearance))
    p = np.array([rng.uniform(xmin, xmax), rng.uniform(ymin, ymax), z])
    phi = rng.uniform(0, np.pi)
    q = p + length * np.array([math.cos(phi), math.sin(phi), 0.0])
    return builders.pipe_run(object_id, [p, q], r, 2 * r, material="metal")


def _new_cabinet(object_id: str, spec: PerturbationSpec, rng: np.random.Generator, bounds: Bounds) -> Object:
    xmin, ymin, xmax, ymax = bounds
    w, d, h = (spec.new_box_size.draw(rng) for _ in range(3))
    _check_fits(bounds, 2 * w, f"a new box of {w:.2f} m", "new_box_size")
    x, y = rng.uniform(xmin + w, xmax - w), rng.uniform(ymin + w, ymax - w)
    return builders.cabinet(object_id, (x, y, 0.0), rng.uniform(0, np.pi), (w, d, h))


def _new_tank(object_id: str, spec: PerturbationSpec, rng: np.random.Generator, bounds: Bounds,
              spherical: bool) -> Object:
    """A cylindrical tank (body height ``spec.new_tank_height``) or a spherical tank on a leg of 0.5-1.5
    radii, of radius ``spec.new_tank_radius``."""
    xmin, ymin, xmax, ymax = bounds
    r = spec.new_tank_radius.draw(rng)
    height = spec.new_tank_height.draw(rng) if not spherical else r * rng.uniform(0.5, 1.5)
    _check_fits(bounds, 4 * r, f"a new tank of radius {r:.2f} m", "new tank_radius")
    x, y = rng.uniform(xmin + r, xmax - r), rng.uniform(ymin + r, ymax - r)
    if spherical:
        return builders.sphere_tank(object_id, (x, y, 0.0), r, height)
    return builders.tank(object_id, (x, y, 0.0), r, height)


def _check_fits(bounds: Bounds, size: float, what: str, key: str) -> None:
    """Refuse a spec whose new parts are too large for the scene's floor, with a message that says so."""
    xmin, ymin, xmax, ymax = bounds
    if xmax - xmin < size or ymax - ymin < size:
        raise ValueError(f"{what} does not fit the scene's floor ({xmax - xmin:.2f} x {ymax - ymin:.2f} m): "
                         f"the perturbation spec's {key} is for a larger scene (the mock-up has its own spec, "
                         "scenes/data/mockup_perturbation.yaml)")
