"""The methods of a suite: what each name under ``methods:`` runs (DESIGN 11.5).

A method is the core's pipeline with its parameters, or the core's pipeline with one stage replaced (a *stage
method*: a :class:`recognition.peers.Peer`, built in or from a plug-in package)::

    methods:
      core: {classifier: select, params: {segmentation: {merge_k: 2.0}}}   # the reference
      paper: {}                                          # the core with the paper's classifier
      core_k4: {base: core, params: {segmentation: {merge_k: 4.0}}}       # an A/B variant of the core
      diff_change: {k_sigma: 3.0}                        # a built-in peer (its options)
      relabel_change: {min_displacement_m: 0.05}        # a plug-in registered by an installed package
      mine: {entry: "my_package.methods:factory"}        # a plug-in named by its factory

A method's name is a built-in method (``core``, ``paper``, the peers of :data:`recognition.peers.PEERS`), a
plug-in registered under the entry-point group :data:`ENTRY_POINT_GROUP`, or a name of one's own that says what
it is: ``base: <one of those>`` or ``entry: "module:factory"``. Its mapping holds ``classifier`` (``select`` or
``paper``), ``params`` (the core's parameters, :mod:`harness.params`) and, for a stage method, its own options
(keys among its ``defaults``).

**Every method runs the core's stages with the** ``core`` **method's parameters**, its own ``params``
deep-merged on top (``classify`` is inherited only by methods with the core's classifier): two methods differ
by exactly what their mappings say, and the runner computes what they share once per trial (a variant that
changes only ``change`` reuses the core's description and pose, whose times are then reported by the core).

A plug-in is a factory ``() -> recognition.Peer`` whose ``run`` implements the stage interface of
:mod:`recognition.interfaces` named by ``replaces``. The factory is called when the suite is read (to check the
method's options against its ``defaults``) and again in each trial's process (which must be able to import it:
installed, or on ``PYTHONPATH``, on every Dask worker too). An entry naming a module or factory that does not
exist is a configuration error of the suite; anything the plug-in raises (importing its module, in its factory,
in its stage), a factory that returns no ``Peer`` and a stage result of the wrong type fail the trials with a
reason naming the method (:class:`PluginError`), never the run.
"""

from __future__ import annotations

import functools
import importlib
import re
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

from harness.params import check_fields, core_params, merge_params
from recognition.describe import CLASSIFIERS
from recognition.interfaces import PARAM_STAGES, REPLACED_PARAMS, CoreParams, check_stage_result
from scenes.config import ConfigError, Fields, show

__all__ = ["ENTRY_POINT_GROUP", "CORE_METHODS", "RESERVED", "MethodSpec", "PluginError", "PluginNotFound",
           "registered_plugins", "method_specs", "load_plugin", "stage_method", "call_stage"]

#: the entry-point group of plug-in methods (``[project.entry-points."landmark_harness.methods"]``)
ENTRY_POINT_GROUP = "landmark_harness.methods"
#: the built-in methods that are the core's pipeline, and their classifier
CORE_METHODS = {"core": "select", "paper": "paper"}
#: keys of a method's mapping that are not a stage method's options
RESERVED = ("base", "entry", "classifier", "params")
_ENTRY = re.compile(r"^[A-Za-z_]\w*(\.[A-Za-z_]\w*)*:[A-Za-z_]\w*(\.[A-Za-z_]\w*)*$")


class PluginError(RuntimeError):
    """A plug-in method that cannot run: its module or factory raised, the factory returned no ``Peer``, or a
    stage raised or returned the wrong type. Raised in the trial, so the trial fails with this reason."""


class PluginNotFound(PluginError):
    """The module or the factory that a plug-in's entry names does not exist (a typo of the suite, or a plug-in
    not installed here): a :class:`scenes.config.ConfigError` when the suite is read."""


@dataclass(frozen=True)
class MethodSpec:
    """What one method of a suite runs (plain data: it crosses process boundaries).

    Attributes
    ----------
    name : the suite's method name (the key of its figures in trial records and summaries).
    kind : ``core`` (the core's pipeline), ``peer`` (a built-in stage method) or ``plugin``.
    base : the built-in or registered method it is (``core``, ``paper``, a peer's or a plug-in's name; the entry
        for ``entry:``).
    params : the core's parameters for the stages it runs with the core.
    options : a stage method's own options (the suite's mapping; the stage applies its defaults).
    entry : ``module:factory`` of a plug-in.
    distribution : the distribution that registered the plug-in (None for ``entry:``; found from the module).
    stage : the stage a stage method replaces (``description``, ``pose`` or ``change``; None for the core's
        pipeline, or for a plug-in whose factory failed when the suite was read).
    error : why the plug-in could not be loaded when the suite was read (its trials fail with it).
    """

    name: str
    kind: str
    base: str
    params: CoreParams
    options: dict[str, Any] = field(default_factory=dict)
    entry: str | None = None
    distribution: str | None = None
    stage: str | None = None
    error: str | None = None

    @property
    def module(self) -> str | None:
        """The plug-in's module (None for the core and built-in peers)."""
        return self.entry.split(":")[0] if self.entry else None


def registered_plugins() -> dict[str, metadata.EntryPoint]:
    """The plug-in methods installed in this environment: entry points of :data:`ENTRY_POINT_GROUP`, by name.

    A plug-in cannot take a built-in method's name (``core``, ``paper``, a peer's): such an entry point is left
    out. Of two distributions registering one name, the first found is kept.
    """
    from recognition.peers import MISSING, PEERS

    out: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name not in CORE_METHODS and ep.name not in PEERS and ep.name not in MISSING:
            out.setdefault(ep.name, ep)
    return out


def method_specs(methods_f: Fields) -> dict[str, MethodSpec]:
    """Every method of a suite's ``methods`` mapping, validated (``core`` first).

    Raises
    ------
    ConfigError
        One line naming the field: an unknown method, base or option, a malformed entry, wrong parameters.
    """
    from recognition.peers import MISSING, PEERS

    plugins = registered_plugins()
    known = (*CORE_METHODS, *PEERS, *plugins)
    if "core" not in methods_f.data:
        raise methods_f.error(None, "the suite must run the 'core' method")
    names = ["core", *(m for m in methods_f.data if m != "core")]
    core_raw = _mapping(methods_f, "core")
    specs: dict[str, MethodSpec] = {}
    for m in names:
        if not isinstance(m, str) or not m:
            raise methods_f.error(str(m), "a method name must be a non-empty string")
        raw = core_raw if m == "core" else _mapping(methods_f, m)
        f = Fields(raw, methods_f.source, methods_f.child_path(m))
        entry = distribution = None
        if f.has("entry"):
            if f.has("base"):
                raise f.error("entry", "give either base (a built-in or registered method) or entry, not both")
            entry = f.string("entry")
            if not _ENTRY.match(entry):
                raise f.error("entry", f"expected 'package.module:factory', got {show(entry)}")
            base, kind = entry, "plugin"
        else:
            base = f.string("base") if f.has("base") else m
            if base not in known:
                if f.has("base"):
                    raise f.error("base", f"unknown method {show(base)}: base names a built-in or registered method "
                                          f"(known: {', '.join(known)})")
                why = f" ({MISSING[m]})" if m in MISSING else ""
                raise methods_f.error(m, f"unknown method{why} (known: {', '.join(known)}; a method of your own "
                                         "says what it is: base: <a known method> or entry: 'module:factory')")
            if m == "core" and base != "core":
                raise f.error("base", "the 'core' method is the core itself (base: core)")
            kind = "core" if base in CORE_METHODS else "peer" if base in PEERS else "plugin"
            if kind == "plugin":
                entry, distribution = plugins[base].value, _dist_name(plugins[base])
        core_classifier = specs["core"].params.describe.classifier if m != "core" else None
        default = CORE_METHODS[base] if base in CORE_METHODS else core_classifier
        classifier = f.string("classifier", choices=CLASSIFIERS) if f.has("classifier") else default
        own = f.raw("params", None)
        params = _params(f, own, core_raw.get("params") if m != "core" else None, classifier,
                         core_classifier)
        options = {k: v for k, v in raw.items() if k not in RESERVED}
        stage = error = None
        if kind == "core":
            if options:
                bad = next(iter(options))
                hint = f" (the core's parameters go under params: {{{bad}: ...}})" if bad in PARAM_STAGES else ""
                raise f.error(None, f"unknown key(s) {', '.join(map(str, options))}{hint} (known: base, classifier, "
                                    "params)")
        else:
            if kind == "peer":
                peer, stage = PEERS[base], PEERS[base].replaces
            else:
                try:
                    peer = load_plugin(entry, m)
                    stage = peer.replaces
                except PluginNotFound as exc:
                    raise f.error("entry" if f.has("entry") else None, str(exc)) from None
                except PluginError as exc:  # the plug-in's own failure: its trials fail with it
                    peer, error = None, str(exc)
            if peer is not None:
                clash = sorted(set(peer.defaults) & set(RESERVED))
                if clash:
                    raise f.error(None, f"the method's options {', '.join(clash)} clash with the keys every method "
                                        f"has ({', '.join(RESERVED)}): rename them in the plug-in")
                check_fields(Fields(options, f.source, f.path), (*RESERVED, *peer.defaults),
                             f"{base!r} (a {stage} method)", kind="option")
            if stage is not None and own:
                replaced = sorted(set(own) & set(REPLACED_PARAMS[stage]))
                if replaced:
                    raise ConfigError(f.source, f"{f.child_path('params')}.{replaced[0]}",
                                      f"this method replaces the {stage} stage: the core's {replaced[0]} parameters "
                                      "would be unused")
        specs[m] = MethodSpec(m, kind, base, params, options, entry, distribution, stage, error)
    return {m: specs[m] for m in methods_f.data}


def _mapping(methods_f: Fields, m: Any) -> dict[str, Any]:
    raw = methods_f.raw(m)
    if raw is not None and not isinstance(raw, dict):
        raise methods_f.error(str(m), "expected a mapping of parameters")
    return dict(raw or {})


def _params(f: Fields, own: Any, inherited: Any, classifier: str, core_classifier: str | None) -> CoreParams:
    """The method's CoreParams: its own ``params`` (checked alone first, for their own paths), on top of the
    core method's (without ``classify`` when the classifiers differ)."""
    path = f.child_path("params")
    if own is not None and not isinstance(own, dict):
        raise f.error("params", f"expected a mapping of stages, got {show(own)}")
    mine = core_params(own, classifier, f.source, path)
    if not inherited:
        return mine
    base = dict(inherited)
    if classifier != core_classifier:
        base.pop("classify", None)
    return core_params(merge_params(base, own or {}), classifier, f.source, path)


def _dist_name(ep: metadata.EntryPoint) -> str | None:
    dist = getattr(ep, "dist", None)
    return dist.metadata["Name"] if dist is not None else None


def _missing_module(exc: ModuleNotFoundError, entry: str) -> bool:
    """Whether the module of ``entry`` itself (or a parent package) is what is missing: a typo of the suite,
    not a plug-in that fails to import its own dependencies."""
    module = entry.split(":")[0]
    return exc.name is not None and (module == exc.name or module.startswith(exc.name + "."))


@functools.cache
def load_plugin(entry: str, name: str):
    """The :class:`recognition.peers.Peer` of the plug-in ``entry`` (``module:factory``), once per process.

    Raises
    ------
    PluginError
        When the module cannot be imported, has no such factory, or the factory raises or returns no Peer.
    """
    from recognition.peers import STAGES, Peer

    module_name, _, attr = entry.partition(":")
    where = f"method {name!r} (plug-in {entry})"
    try:
        obj: Any = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - whatever the plug-in's import raises is its failure
        error = PluginNotFound if isinstance(exc, ModuleNotFoundError) and _missing_module(exc, entry) else PluginError
        raise error(f"{where}: cannot import {module_name}: {type(exc).__name__}: {exc}") from exc
    try:
        for part in attr.split("."):
            obj = getattr(obj, part)
    except AttributeError:
        raise PluginNotFound(f"{where}: module {module_name} has no {attr}") from None
    if not callable(obj):
        raise PluginNotFound(f"{where}: {attr} is not callable (expected a factory returning a recognition.Peer)")
    try:
        peer = obj()
    except Exception as exc:  # noqa: BLE001
        raise PluginError(f"{where}: its factory raised {type(exc).__name__}: {exc}") from exc
    if not isinstance(peer, Peer):
        raise PluginError(f"{where}: its factory returned {type(peer).__name__}, expected a recognition.Peer")
    if peer.replaces not in STAGES or not callable(peer.run):
        raise PluginError(f"{where}: its Peer must replace one of {', '.join(STAGES)} with a callable run")
    return peer


def stage_method(spec: MethodSpec):
    """The Peer that runs ``spec``'s stage (None for the core's pipeline), loaded in this process.

    Raises
    ------
    PluginError
        For a plug-in that cannot be loaded, or whose stage is not the one it had when the suite was read.
    """
    if spec.kind == "core":
        return None
    if spec.kind == "peer":
        from recognition.peers import MISSING, PEERS

        if spec.base not in PEERS:  # registered where the suite was read, not in this (worker's) environment
            raise RuntimeError(f"method {spec.name!r}: the peer {spec.base!r} is not available here"
                               + (f" ({MISSING[spec.base]})" if spec.base in MISSING else ""))
        return PEERS[spec.base]
    if spec.error is not None:
        raise PluginError(spec.error)
    peer = load_plugin(spec.entry, spec.name)
    if spec.stage is not None and peer.replaces != spec.stage:
        raise PluginError(f"method {spec.name!r} (plug-in {spec.entry}): replaces {peer.replaces} here, "
                          f"{spec.stage} when the suite was read")
    return peer


def call_stage(spec: MethodSpec, peer, *args, **kwargs):
    """``peer.run(*args, **kwargs)``; for a plug-in, whatever it raises, or a result of the wrong type, becomes a
    :class:`PluginError` naming the method (built-in peers' exceptions pass unchanged)."""
    if spec.kind != "plugin":
        return peer.run(*args, **kwargs)
    where = f"method {spec.name!r} (plug-in {spec.entry}), {peer.replaces} stage"
    try:
        result = peer.run(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - a plug-in's failure, recorded with the trial
        raise PluginError(f"{where}: raised {type(exc).__name__}: {exc}") from exc
    why = check_stage_result(peer.replaces, result)
    if why is not None:
        raise PluginError(f"{where}: {why}")
    return result
