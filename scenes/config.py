"""Validated reading of YAML configuration files.

Every YAML file the project reads (scenes, generator and perturbation specs, sensors, suites)
goes through :func:`load_yaml` (safe loader only) and the typed field readers below, so that
a bad file gives one clear message naming the file, the field path and the reason::

    scene.yaml: objects[2].features[0].radius: must be > 0, got -1.0
"""

from __future__ import annotations

import math
import reprlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

MAX_REASON = 1500  # the longest legitimate reason lists a parameter dataclass's ~40 field names
_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxdict, _REPR.maxtuple, _REPR.maxset = 3, 6, 6, 6, 6
_REPR.maxstring, _REPR.maxother = 80, 80


def show(value: Any) -> str:
    """A short, bounded ``repr`` of a config value for error messages.

    Plain ``repr`` is unbounded: a YAML alias bomb (a few lines expanding to 10^9 shared list elements), a huge
    string or an integer of thousands of digits would hang the error message or raise inside it.
    """
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 64:
        return f"an integer of {value.bit_length()} bits"
    return _REPR.repr(value)


class ConfigError(ValueError):
    """A configuration file or mapping that cannot be used, with where and why."""

    def __init__(self, source: str, path: str, reason: str):
        if len(reason) > MAX_REASON:  # e.g. a 10 kB string quoted back: keep messages one readable line
            reason = reason[:MAX_REASON] + "... (truncated)"
        self.source, self.path, self.reason = source, path, reason
        where = ": ".join(p for p in (source, path) if p)
        super().__init__(f"{where}: {reason}" if where else reason)


def load_yaml(path: str | Path) -> Any:
    """Read a YAML file with the safe loader; errors become :class:`ConfigError`."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), "", f"cannot read file ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(str(path), "", "not a UTF-8 text file") from None
    return parse_yaml(text, str(path))


def parse_yaml(text: str, source: str = "<string>") -> Any:
    """Parse YAML text with the safe loader; errors become :class:`ConfigError`."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(source, where, f"malformed YAML: {problem}") from None
    except RecursionError:
        raise ConfigError(source, "", "malformed YAML: nesting too deep") from None
    except ValueError as exc:  # a scalar the constructor cannot convert, e.g. an integer of > 4300 digits
        raise ConfigError(source, "", f"malformed YAML: {str(exc).split(':')[0]}") from None


def dump_yaml(data: Any) -> str:
    """Serialise plain data to YAML deterministically (insertion order, exact float repr)."""
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=100)


class Fields:
    """Typed access to one mapping of a config, remembering its path for error messages.

    Parameters
    ----------
    data : mapping read from YAML.
    source : file name (or other origin) used in messages.
    path : dotted/indexed path of this mapping inside the file (``""`` for the root).
    """

    def __init__(self, data: Any, source: str, path: str = ""):
        if not isinstance(data, Mapping):
            raise ConfigError(source, path, f"expected a mapping, got {_type_name(data)}")
        self.data, self.source, self.path = data, source, path
        self._used: set[str] = set()

    def error(self, key: str | None, reason: str) -> ConfigError:
        return ConfigError(self.source, self.child_path(key) if key else self.path, reason)

    def child_path(self, key: str | int) -> str:
        if isinstance(key, int):
            return f"{self.path}[{key}]"
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = ..., *, required: bool | None = None) -> Any:
        self._used.add(key)
        if key in self.data:
            return self.data[key]
        if default is ... or required:
            raise self.error(key, "missing required key")
        return default

    def sub(self, key: str, default: Any = ...) -> Fields:
        value = self.raw(key, default)
        return Fields({} if value is None else value, self.source, self.child_path(key))

    def items(self, key: str, default: Any = ...) -> list[Fields | Any]:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.error(key, f"expected a list, got {_type_name(value)}")
        return [(Fields(v, self.source, f"{self.child_path(key)}[{i}]") if isinstance(v, Mapping) else v)
                for i, v in enumerate(value)]

    def list_of_fields(self, key: str, default: Any = ...) -> list[Fields]:
        value = self.raw(key, default)
        if not isinstance(value, list):
            raise self.error(key, f"expected a list, got {_type_name(value)}")
        return [Fields(v, self.source, f"{self.child_path(key)}[{i}]") for i, v in enumerate(value)]

    def string(self, key: str, default: Any = ..., choices: Iterable[str] | None = None) -> str:
        value = self.raw(key, default)
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected a non-empty string, got {show(value)}")
        if choices is not None and value not in (allowed := tuple(choices)):
            raise self.error(key, f"must be one of {', '.join(allowed)}, got {show(value)}")
        return value

    def boolean(self, key: str, default: Any = ...) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {show(value)}")
        return value

    def integer(self, key: str, default: Any = ..., *, min: int | None = None, max: int | None = None) -> int:
        value = self.raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {show(value)}")
        if min is not None and value < min:
            raise self.error(key, f"must be >= {min}, got {show(value)}")
        if max is not None and value > max:
            raise self.error(key, f"must be <= {max}, got {show(value)}")
        return value

    def number(self, key: str, default: Any = ..., *, min: float | None = None, max: float | None = None,
               positive: bool = False, nonnegative: bool = False) -> float:
        value = self.raw(key, default)
        return check_number(value, self.source, self.child_path(key), min=min, max=max,
                            positive=positive, nonnegative=nonnegative)

    def vector(self, key: str, default: Any = ..., *, size: int = 3, unit_norm: bool = False,
               nonzero: bool = False) -> np.ndarray:
        value = self.raw(key, default)
        path = self.child_path(key)
        if not isinstance(value, list | tuple) or len(value) != size:
            raise ConfigError(self.source, path, f"expected a list of {size} numbers, got {show(value)}")
        arr = np.array([check_number(v, self.source, f"{path}[{i}]") for i, v in enumerate(value)])
        norm = float(np.linalg.norm(arr))
        if (unit_norm or nonzero) and norm < 1e-12:
            raise ConfigError(self.source, path, "must be a non-zero vector")
        if unit_norm and abs(norm - 1.0) > 1e-9:
            raise ConfigError(self.source, path, f"must be a unit vector, has norm {norm:.6g}")
        return arr

    def check_unknown(self, allowed: Iterable[str] | None = None) -> None:
        """Raise on keys that were never read (or are not in ``allowed``)."""
        allowed_set = set(allowed) if allowed is not None else self._used
        unknown = [str(k) for k in self.data if k not in allowed_set]
        if unknown:
            known = ", ".join(sorted(allowed_set)) or "none"
            raise self.error(None, f"unknown key(s) {', '.join(unknown)} (known: {known})")


def check_number(value: Any, source: str, path: str, *, min: float | None = None, max: float | None = None,
                 positive: bool = False, nonnegative: bool = False) -> float:
    """Validate one real number from a config."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(source, path, f"expected a number, got {show(value)}")
    try:
        value = float(value)
    except OverflowError:  # an int beyond float range
        raise ConfigError(source, path, f"must be finite, got {show(value)}") from None
    if not math.isfinite(value):
        raise ConfigError(source, path, f"must be finite, got {value}")
    if positive and value <= 0:
        raise ConfigError(source, path, f"must be > 0, got {value}")
    if nonnegative and value < 0:
        raise ConfigError(source, path, f"must be >= 0, got {value}")
    if min is not None and value < min:
        raise ConfigError(source, path, f"must be >= {min}, got {value}")
    if max is not None and value > max:
        raise ConfigError(source, path, f"must be <= {max}, got {value}")
    return value


def _type_name(value: Any) -> str:
    return "nothing" if value is None else type(value).__name__
