"""The core's parameters from a suite: ``methods.<name>.params`` read into a
:class:`recognition.interfaces.CoreParams` (DESIGN 11.5).

Every stage name of :data:`recognition.interfaces.PARAM_STAGES` is a mapping of the fields of its dataclass
(nested dataclasses as nested mappings); fields are found by dataclass introspection, so a field added to a
``*Params`` class is reachable from a suite as soon as it exists. Values are checked against the field's type
annotation (``int``, ``float`` (an integer is accepted), ``bool``, ``str``, ``Literal`` choices such as
``"auto"``, unions such as ``X | None``, tuples), then the dataclass's own ``__post_init__`` checks run; every
failure is one :class:`scenes.config.ConfigError` naming the file, the field path
(``methods.core.params.segmentation.merge_k``) and the reason, and an unknown field is listed with the accepted
ones::

    suite.yaml: methods.core.params.segmentation: unknown key(s) merge_kk of SegmentationParams (did you mean
    merge_k? known: absorb_k, ...)
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import re
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any

from recognition.describe import DescribeParams
from recognition.interfaces import METHOD_FIELDS, PARAM_STAGES, CoreParams, stage_default
from scenes.config import ConfigError, Fields, check_number, show

__all__ = ["core_params", "merge_params", "params_tree"]


def core_params(data: Any, classifier: str = "select", source: str = "<suite>", path: str = "params") -> CoreParams:
    """The core's parameters for a method with ``classifier`` and the ``params`` mapping ``data``
    (None or {}: the defaults).

    Raises
    ------
    ConfigError
        For an unknown stage or field, a value of the wrong type, or one the dataclass refuses.
    """
    core = CoreParams(describe=DescribeParams(classifier=classifier))
    f = Fields({} if data is None else data, source, path)
    check_fields(f, PARAM_STAGES, None, kind="stage")
    return _build(core, (), f, core)


def _build(instance: Any, at: tuple[str, ...], f: Fields, core: CoreParams) -> Any:
    """``instance`` (the dataclass at path ``at`` of ``core``) with the stages at and below ``at`` that ``f`` (the
    ``params`` mapping) sets applied."""
    values: dict[str, Any] = {}
    children = set()
    for stage, path in PARAM_STAGES.items():  # the stages one level below this one
        if len(path) == len(at) + 1 and path[:len(at)] == at:
            children.add(path[-1])
            if _sets(f, stage, path):
                values[path[-1]] = _build(stage_default(stage, core), path, f, core)
    own = _stage_at(at)
    if own is None or not f.has(own):
        return _replace(instance, values, f)
    sub = f.sub(own)
    children |= {p[-1] for p in METHOD_FIELDS.values() if p[:-1] == at}
    values.update(read_dataclass(sub, instance, exclude=children))
    return _replace(instance, values, sub)


def _sets(f: Fields, stage: str, path: tuple[str, ...]) -> bool:
    """Whether ``f`` sets ``stage`` or a stage below it."""
    return f.has(stage) or any(len(p) > len(path) and p[:len(path)] == path and f.has(s)
                               for s, p in PARAM_STAGES.items())


def _stage_at(at: tuple[str, ...]) -> str | None:
    for stage, path in PARAM_STAGES.items():
        if path == at:
            return stage
    return None


def read_dataclass(f: Fields, instance: Any, exclude: set[str] = frozenset()) -> dict[str, Any]:
    """The values of mapping ``f`` for fields of the dataclass ``instance`` (excluding ``exclude``), checked
    against their annotations; nested dataclasses are built from nested mappings (from the value in
    ``instance``)."""
    cls = type(instance)
    hints = _hints(cls)
    names = [fl.name for fl in dataclasses.fields(cls) if fl.init and fl.name not in exclude]
    check_fields(f, names, cls.__name__)
    values: dict[str, Any] = {}
    for name in names:
        if not f.has(name):
            continue
        current = getattr(instance, name)
        nested = _dataclass_of(hints.get(name), current)
        if nested is not None:
            raw = f.raw(name)
            if raw is None and _allows_none(hints.get(name)):
                values[name] = None
                continue
            sub = f.sub(name)
            start = current if dataclasses.is_dataclass(current) else nested()
            values[name] = _replace(start, read_dataclass(sub, start), sub)
        else:
            values[name] = read_value(f, name, hints.get(name, Any))
    return values


def check_fields(f: Fields, known: Iterable[str], what: str | None, kind: str = "key") -> None:
    """Raise on keys of ``f`` not in ``known``: one line with the closest known name and all of them."""
    known = list(known)
    unknown = [k for k in f.data if k not in known]
    if not unknown:
        return
    close = difflib.get_close_matches(str(unknown[0]), known, n=1)
    hint = f"did you mean {close[0]}? " if close else ""
    shown = ", ".join(show(k) if not isinstance(k, str) or len(k) > 80 else k for k in unknown[:5])
    more = f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""
    of = f" of {what}" if what else ""
    raise f.error(None, f"unknown {kind}(s) {shown}{more}{of} ({hint}known: {', '.join(sorted(known))})")


def _replace(instance: Any, values: dict[str, Any], f: Fields) -> Any:
    """``dataclasses.replace(instance, **values)``; the dataclass's own ValueError as a ConfigError naming the
    field its message starts with (else the mapping)."""
    if not values:
        return instance
    try:
        return dataclasses.replace(instance, **values)
    except (ValueError, TypeError) as exc:
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        m = re.match(r"\w+", msg)
        key = m.group(0) if m and m.group(0) in values else (next(iter(values)) if len(values) == 1 else None)
        raise f.error(key, msg) from None


def read_value(f: Fields, key: str, annotation: Any) -> Any:
    """One scalar field: the YAML value checked against the field's annotation."""
    value = f.raw(key)
    args = typing.get_args(annotation)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        if len(options) == 1:
            return read_value(f, key, options[0])
        for option in options:  # the first that accepts it
            try:
                return read_value(f, key, option)
            except ConfigError:
                continue
        names = " or ".join(getattr(o, "__name__", str(o)) for o in options)
        raise f.error(key, f"expected {names}, got {show(value)}")
    if annotation is bool:
        return f.boolean(key)
    if annotation is int:
        return f.integer(key)
    if annotation is float:
        return check_number(value, f.source, f.child_path(key))
    if annotation is str:
        return f.string(key)
    if origin is typing.Literal:
        if value not in args:
            raise f.error(key, f"must be one of {', '.join(map(str, args))}, got {show(value)}")
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise f.error(key, f"expected a list, got {show(value)}")
        items = Fields({str(i): v for i, v in enumerate(value)}, f.source, f.child_path(key))
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(read_value(items, str(i), args[0]) for i in range(len(value)))
        if args and len(args) != len(value):
            raise f.error(key, f"expected a list of {len(args)} values, got {show(value)}")
        return tuple(read_value(items, str(i), a) if args else v for i, (a, v) in
                     enumerate(zip(args or [Any] * len(value), value, strict=True)))
    return value  # an annotation not known here: the dataclass's own checks decide


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except Exception:  # noqa: BLE001 - an annotation that cannot be resolved: its values go unchecked
        return {}


def _dataclass_of(annotation: Any, current: Any) -> type | None:
    """The dataclass a field holds: its current value's, or the one dataclass of its annotation."""
    if dataclasses.is_dataclass(current) and not isinstance(current, type):
        return type(current)
    candidates = [a for a in (typing.get_args(annotation) or (annotation,)) if isinstance(a, type)
                  and dataclasses.is_dataclass(a)]
    return candidates[0] if len(candidates) == 1 else None


def _allows_none(annotation: Any) -> bool:
    return type(None) in typing.get_args(annotation)


def merge_params(base: Any, override: Any) -> Any:
    """``override`` deep-merged onto ``base`` (mappings key by key, anything else replaced): how a method's own
    ``params`` go on top of the ``core`` method's."""
    if isinstance(base, Mapping) and isinstance(override, Mapping):
        out = dict(base)
        for k, v in override.items():
            out[k] = merge_params(base[k], v) if k in base else v
        return out
    return override


def params_tree(core: CoreParams | None = None) -> dict[str, Any]:
    """Every field a suite can set, by stage: ``{stage: {field: default, nested: {...}}}`` (for documentation
    and ``--help`` texts; the defaults of ``classify`` are the ``select`` classifier's)."""
    core = CoreParams() if core is None else core
    out: dict[str, Any] = {}
    for stage, path in PARAM_STAGES.items():
        exclude = {p[-1] for p in PARAM_STAGES.values() if len(p) == len(path) + 1 and p[:len(path)] == path}
        exclude |= {p[-1] for p in METHOD_FIELDS.values() if p[:-1] == path}
        out[stage] = _as_tree(stage_default(stage, core), exclude)
    return out


def _as_tree(instance: Any, exclude: set[str] = frozenset()) -> dict[str, Any]:
    return {fl.name: (_as_tree(v) if dataclasses.is_dataclass(v := getattr(instance, fl.name)) else v)
            for fl in dataclasses.fields(instance) if fl.init and fl.name not in exclude}
