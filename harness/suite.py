"""Benchmark suites: YAML (schema ``suite/1``) expanded into trials.

A suite lists scene groups; each group is a scene (shipped name or file) with a perturbation spec and
seeds, a sensor (preset name or file), a number of viewpoints and noise seeds. A trial is
(scene, perturbation seed, viewpoint, sensor preset, noise seed) (DESIGN 10.4); every method of the
suite runs on the same trial and image::

    schema: suite/1
    name: smoke
    seed: 2026
    timeout_s: 120
    methods:                               # what runs on every trial (harness.methods); core is required
      core: {classifier: select}           # the core; params: its parameters, by stage (below)
      paper: {classifier: paper}           # the core with the paper's classifier
      core_merge4: {base: core, params: {segmentation: {merge_k: 4.0}}}   # an A/B variant, on the same scans
      diff_change: {k_sigma: 4.0}          # a peer replacing one stage, with its options
    groups:
      - scene: mockup                      # shipped scene name, or a path to a scene YAML
        perturbation: mockup_perturbation  # shipped spec name, path, or omitted for no changes
        perturbation_seeds: [0]
        sensor: mockup_laser               # preset name or sensor YAML
        viewpoints: 2                      # per perturbation seed
        noise_seeds: [0]
        max_range: 4.0                     # optional: clip the sensor's range (e.g. kinect_like < 4 m)
        sweep: {noise_scale: [0.5, 1.0, 2.0]}   # optional: each value is a group of its own (DESIGN 10.13)

Sweepable (:data:`SWEEPABLE`): ``noise_scale`` (every noise sigma times the value), ``footprint_rays`` (sub-rays
of the beam), ``max_range`` (metres, as the group key above) and ``view_distance`` (metres: the sensor's
distance from the point it looks at is drawn within +-10 % of the value, :data:`VIEW_DISTANCE_BAND`, instead of
the sensor's own ``(max(1.5 min_range, 0.15 max_range), 0.6 max_range)``; the same directions are drawn).

Methods (DESIGN 11.5; :mod:`harness.methods`). A method's name is a built-in method (``core``, ``paper``, a peer of
:data:`recognition.peers.PEERS`), a plug-in installed under the entry-point group ``landmark_harness.methods``, or
a name of one's own that says what it is: ``base: <one of those>`` (``core_merge4: {base: core, ...}``) or
``entry: "package.module:factory"`` (a factory returning a :class:`recognition.Peer`). Its mapping holds:

- ``classifier``: ``select`` or ``paper`` (default: ``paper`` for ``paper`` and ``base: paper``, else the ``core``
  method's);
- ``params``: the core's parameters, ``params.<stage>.<field>``, with the stages of
  :data:`recognition.interfaces.PARAM_STAGES` - ``segmentation`` (``SegmentationParams``), ``classify`` (the
  classifier's ``SelectParams`` or ``PaperParams``), ``describe`` (the rest of ``DescribeParams``), ``match``
  (``MatchParams``), ``localise`` (the rest of ``LocaliseParams``: ``verify``, ``icp``, ``icp_screen`` as nested
  mappings), ``change`` (``ChangeParams``); fields are read by dataclass introspection (:mod:`harness.params`), so
  every field of those classes is reachable, checked against its type and by the class itself;
- for a stage method (a peer or a plug-in), its options (keys among its ``defaults``).

Every method runs the core's stages with the ``core`` method's ``params``, its own deep-merged on top (``classify``
only between methods of one classifier): two methods of a suite differ by exactly what their mappings say, and
run on the very same scans, so ``core`` against ``core_merge4`` is an A/B of one value on the same images. The
trial computes what methods share once (one segmentation per ``segmentation`` parameters, one description per
``describe`` parameters, one pose per description and ``localise`` parameters; its times are reported by the
first method that needed it). The suite's raw mapping enters :attr:`Suite.config_hash`, with the factory each
plug-in registered by name stands for; the plug-ins' versions enter the run's code identity.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scenes.config import ConfigError, Fields, load_yaml, show
from scenes.generator import DATA_DIR as SCENE_DATA

if TYPE_CHECKING:
    from harness.methods import MethodSpec

SUITES_DIR = Path(__file__).parent / "suites"
METHODS = ("core", "paper")
ORACLES = ("segmentation", "classification", "pairing", "pose")
SWEEPABLE = ("noise_scale", "footprint_rays", "max_range", "view_distance")
VIEW_DISTANCE_BAND = (0.9, 1.1)  # a swept view_distance d: the viewpoint's distance is drawn in [0.9 d, 1.1 d]
MAX_TRIALS = 100_000  # a suite larger than this is a typo (e.g. a seed list pasted twice), not a benchmark


@dataclass(frozen=True)
class TrialSpec:
    """One trial: everything needed to run it, in plain data (it crosses process boundaries)."""

    trial_id: str
    index: int
    group: str
    scene: str
    scene_file: str
    perturbation_file: str | None
    perturbation_seed: int
    viewpoint: int
    sensor: str
    noise_seed: int
    suite_seed: int
    min_view_pixels: int = 200
    min_view_surfaces: int = 4
    overrides: dict[str, float] = field(default_factory=dict)
    family: str | None = None          # a generated scene: its family, config file and seed (``scene_file`` "")
    family_config: str | None = None
    scene_seed: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @property
    def scene_key(self) -> tuple:
        """What the a priori model is made from: a file, or (family, config, seed)."""
        return (self.scene_file, self.family, self.family_config, self.scene_seed)

    @property
    def prepared_key(self) -> tuple:
        """What the prepared scene is made from: the a priori model, the perturbation spec and its seed (trials
        with the same key share one prepared scene)."""
        return (self.scene_key, self.perturbation_file, self.perturbation_seed)


@dataclass(frozen=True)
class TrialPlan:
    """What runs on every trial: the methods (core, paper, peers) and the stage-isolating oracles."""

    methods: dict[str, dict[str, Any]]
    oracles: tuple[str, ...] = ()
    specs: dict[str, MethodSpec] | None = None  # the validated methods (None: read from ``methods``)

    def method_specs(self) -> dict[str, MethodSpec]:
        """What every method runs (:class:`harness.methods.MethodSpec`), ``core`` first."""
        specs = self.specs
        if specs is None:
            from harness.methods import method_specs

            specs = method_specs(Fields(self.methods, "<plan>", "methods"))
        return {"core": specs["core"], **{m: s for m, s in specs.items() if m != "core"}}


@dataclass(frozen=True)
class Suite:
    """A validated suite and where it came from."""

    name: str
    source: str
    seed: int
    timeout_s: float
    methods: dict[str, dict[str, Any]]
    trials: tuple[TrialSpec, ...]
    raw: dict[str, Any]
    oracles: tuple[str, ...] = ()
    specs: dict[str, MethodSpec] = field(default_factory=dict)

    @property
    def plan(self) -> TrialPlan:
        return TrialPlan(self.methods, self.oracles, self.specs or None)

    @property
    def plugins(self) -> tuple[tuple[str, str | None], ...]:
        """``(module, distribution or None)`` of each plug-in method (for the code identity)."""
        return tuple(sorted({(s.module, s.distribution) for s in self.specs.values() if s.kind == "plugin"},
                            key=lambda p: (p[0], p[1] or "")))

    @property
    def config_hash(self) -> str:
        """SHA-256 of the canonical JSON of the suite, of the factory each plug-in method registered by name
        stands for, and of every file the suite refers to."""
        h = hashlib.sha256(json.dumps(self.raw, sort_keys=True, default=str).encode())
        registered = sorted((m, s.entry) for m, s in self.specs.items() if s.kind == "plugin" and s.base != s.entry)
        if registered:  # (no such method: the hash of a suite without plug-ins is what it always was)
            h.update(json.dumps(registered).encode())
        files = sorted({t.scene_file for t in self.trials if t.scene_file}
                       | {t.family_config for t in self.trials if t.family_config}
                       | {t.perturbation_file for t in self.trials if t.perturbation_file})
        for f in files:
            h.update(Path(f).read_bytes())
        return h.hexdigest()[:16]


def closest_hint(trial_id: str, ids: list[str], otherwise: str = "") -> str:
    """`` (closest: a, b, c)``: the ids nearest a mistyped ``trial_id`` (``otherwise`` when none is near)."""
    import difflib

    close = difflib.get_close_matches(trial_id, ids, n=3, cutoff=0.6)
    return f" (closest: {', '.join(close)})" if close else otherwise


def shipped_suites() -> list[str]:
    return sorted(p.stem for p in SUITES_DIR.glob("*.yaml"))


def resolve_suite_path(name_or_file: str) -> Path:
    """A shipped suite by name (``default``, ``smoke``...) or a path to a suite YAML."""
    path = Path(name_or_file)
    if path.suffix in (".yaml", ".yml") or path.exists():
        if not path.exists():
            raise FileNotFoundError(f"suite file not found: {path}")
        return path
    shipped = SUITES_DIR / f"{name_or_file}.yaml"
    if not shipped.exists():
        raise FileNotFoundError(f"no shipped suite {name_or_file!r} (known: {', '.join(shipped_suites())})")
    return shipped


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False for a name the OS cannot even look up (too long, ...)."""
    try:
        return path.is_file()
    except OSError:
        return False


def _resolve_data(f: Fields, key: str, value: str, base: Path) -> str:
    """A shipped scene/spec name or a path (relative to the suite file)."""
    for cand in (SCENE_DATA / f"{value}.yaml", base / value, Path(value)):
        if _is_file(cand):
            return str(cand.resolve())
    raise f.error(key, f"no shipped file named {value!r} and no such file")


def load_suite(name_or_file: str) -> Suite:
    path = resolve_suite_path(name_or_file)
    return suite_from_dict(load_yaml(path), str(path), base=path.parent)


def suite_from_dict(data: Any, source: str = "<suite>", base: Path = Path(".")) -> Suite:
    from harness.methods import method_specs
    from sensors.config import load_sensor  # validated here so a bad preset fails before any trial runs

    root = Fields(data, source)
    schema = root.string("schema", "suite/1")
    if schema != "suite/1":
        raise root.error("schema", f"unsupported schema {schema!r} (expected 'suite/1')")
    name = root.string("name", Path(source).stem)
    seed = root.integer("seed", 0, min=0)
    timeout_s = root.number("timeout_s", 300.0, positive=True)
    methods_f = root.sub("methods", {"core": {}})
    # validated here, not at each trial: a typo would otherwise fail every trial of the run one by one
    specs = method_specs(methods_f)
    methods: dict[str, dict[str, Any]] = {m: dict(methods_f.data[m] or {}) for m in specs}
    oracles = root.raw("oracles", [])
    if not isinstance(oracles, list) or any(o not in ORACLES for o in oracles) or len(set(oracles)) != len(oracles):
        raise root.error("oracles", f"expected a list of distinct oracles from {', '.join(ORACLES)}, "
                                    f"got {show(oracles)}")
    trials: list[TrialSpec] = []
    groups = root.list_of_fields("groups")
    if not groups:
        raise root.error("groups", "a suite needs at least one group")
    for g in groups:
        scenes = _group_scenes(g, base)
        pert = g.string("perturbation") if g.raw("perturbation", None) is not None else None
        pert_file = _resolve_data(g, "perturbation", pert, base) if pert is not None else None
        pseeds = _int_list(g, "perturbation_seeds", [0])
        nseeds = _int_list(g, "noise_seeds", [0])
        n_views = g.integer("viewpoints", 1, min=1, max=10_000)
        sensor = g.string("sensor")
        local = _is_file(base / sensor)
        try:
            load_sensor(sensor if not local else str(base / sensor))
        except (ConfigError, ValueError, OSError) as exc:
            raise g.error("sensor", str(exc)) from None
        sensor_ref = str((base / sensor).resolve()) if local else sensor
        overrides: dict[str, float] = {}
        if g.has("max_range"):
            overrides["max_range"] = g.number("max_range", positive=True)
        sweep = g.sub("sweep", {})
        sweep_values: list[tuple[str, list[float]]] = []
        for key in sweep.data:
            if key not in SWEEPABLE:
                raise sweep.error(str(key), f"cannot sweep this (sweepable: {', '.join(SWEEPABLE)})")
            vals = sweep.raw(key)
            if not isinstance(vals, list) or not vals:
                raise sweep.error(str(key), "expected a non-empty list of values")
            sweep_values.append((str(key), [_positive(sweep, str(key), v) for v in vals]))
        label = g.string("label", f"{scenes[0].label}/{Path(sensor).stem}")
        min_pixels = g.integer("min_view_pixels", 200, min=1)
        min_surfaces = g.integer("min_view_surfaces", 4, min=0)
        g.check_unknown()
        n_combos = 1
        for _, vals in sweep_values:
            n_combos *= len(vals)
        n_group = n_combos * len(scenes) * len(pseeds) * n_views * len(nseeds)
        if len(trials) + n_group > MAX_TRIALS:  # checked before expanding: a huge product would exhaust memory
            raise g.error(None, f"this group expands to {n_group} trials (sweep values x scenes x perturbation "
                                f"seeds x viewpoints x noise seeds), more than the {MAX_TRIALS} a suite may hold "
                                "in all")
        combos = list(itertools.product(*[[(k, v) for v in vals] for k, vals in sweep_values])) or [()]
        for combo in combos:
            ov = {**overrides, **dict(combo)}
            group = label + "".join(f"[{k}={v:g}]" for k, v in combo)
            for sc, ps, vp, ns in itertools.product(scenes, pseeds, range(n_views), nseeds):
                tid = f"{sc.name}-p{ps}-v{vp}-{Path(sensor).stem}-n{ns}" + \
                      "".join(f"-{k}{v:g}" for k, v in combo)
                trials.append(TrialSpec(tid, len(trials), group, sc.name, sc.file, pert_file, ps,
                                        vp, sensor_ref, ns, seed, min_pixels, min_surfaces, ov,
                                        sc.family, sc.family_config, sc.seed))
    ids = [t.trial_id for t in trials]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[0]
        raise root.error("groups", f"two groups produce the same trial id {dup!r}: give them distinct labels")
    root.check_unknown()
    return Suite(name, source, seed, timeout_s, methods, tuple(trials), data, tuple(oracles), specs)


@dataclass(frozen=True)
class _GroupScene:
    """One a priori scene of a group: a file, or a member of a generated family."""

    name: str
    label: str
    file: str = ""
    family: str | None = None
    family_config: str | None = None
    seed: int | None = None


def _group_scenes(g: Fields, base: Path) -> list[_GroupScene]:
    """The scenes of a group: ``scene`` (one shipped name or file) or ``family`` with ``scene_seeds``."""
    from scenes.families import FAMILIES, family_config_path, member_name

    if g.has("scene") == g.has("family"):
        raise g.error("scene", "give either scene (a shipped name or a file) or family (generated scenes)")
    if g.has("scene"):
        name = g.string("scene")
        return [_GroupScene(Path(name).stem, Path(name).stem, _resolve_data(g, "scene", name, base))]
    family = g.string("family", choices=tuple(FAMILIES))
    config = str(family_config_path(family))  # named in the spec: the file enters the configuration hash
    if g.has("family_config"):
        value = g.string("family_config")
        local = base / value
        try:
            config = str(family_config_path(family, str(local) if _is_file(local) else value))
        except ValueError as exc:
            raise g.error("family_config", str(exc)) from None
    seeds = _seed_list(g, "scene_seeds")
    return [_GroupScene(member_name(family, s), family, "", family, config, s) for s in seeds]


def _seed_list(f: Fields, key: str) -> list[int]:
    """A list of distinct seeds, or ``{start: S, count: N}`` for S .. S + N - 1."""
    raw = f.raw(key, None)
    if raw is None:
        raise f.error(key, "a family needs its scene seeds: a list, or {start: S, count: N}")
    if isinstance(raw, dict):
        sub = f.sub(key)
        start, count = sub.integer("start", min=0), sub.integer("count", min=1, max=MAX_TRIALS)
        sub.check_unknown()
        return list(range(start, start + count))
    return _int_list(f, key, [])


def _positive(f: Fields, key: str, v: Any) -> float:
    from scenes.config import check_number

    return check_number(v, f.source, f.child_path(key), positive=True)


def _int_list(f: Fields, key: str, default: list[int]) -> list[int]:
    vals = f.raw(key, default)
    if not isinstance(vals, list) or not vals or any(isinstance(v, bool) or not isinstance(v, int) or v < 0
                                                     for v in vals):
        raise f.error(key, f"expected a non-empty list of non-negative integers, got {show(vals)}")
    if len(set(vals)) != len(vals):
        raise f.error(key, "values must be distinct")
    return list(vals)
