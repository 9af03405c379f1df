"""``python -m harness.tuning [--write]``: ``docs/tuning.md``, every tuned value of the core in one table.

The table is generated from the fields' metadata (:func:`recognition.tuning.tuned`: unit and where the value was
chosen) of every ``*Params`` dataclass of :mod:`recognition` (:func:`recognition.tuning.params_classes`), with the
named numeric constants that are not settings (:data:`recognition.tuning.CONSTANTS`). ``tests/test_tuning.py``
fails when the committed file and the code disagree: edit the field, then run this with ``--write``.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import math
import sys
from dataclasses import MISSING
from pathlib import Path
from typing import Any

from recognition.tuning import CONSTANTS, params_classes

__all__ = ["DOC_PATH", "table", "main"]

DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "tuning.md"

HEADER = """\
# Tuned values

Every value the core uses is a field of a frozen `*Params` dataclass in `recognition/`, listed here with its
unit and where it was chosen. Generated from the fields' metadata (`recognition.tuning.tuned`) by
`python -m harness.tuning --write`; `tests/test_tuning.py` fails when this file and the code disagree.
Edit the field in the code, never this file. A suite sets the core's as `methods.<name>.params.<stage>.<field>`
and a peer's (`RegistrationParams`, `PrimitiveParams`, `DiffChangeParams`) as that method's own options.

How to read "where chosen":

- `calibration`: today's tuning suite (`harness/suites/calibration.yaml`); the rule is to tune there and report
  on `default` (its figures: [results.md](results.md)).
- *calibration (phase 1)*: the first phase's `calibration` suite (seed 4242, one bay and one mock-up), which the
  suites' redesign (commit 4c22693) replaced; the figure was measured there and has not been re-checked on
  today's `calibration`.
- *the first phase's default (now classic)*: the first phase's `default` suite, shipped today as `classic`; its
  perturbation draws have changed since, so the figure cannot be reproduced as such
  ([notebook.md](notebook.md) keeps the record).
- *not tuned*: set when the step was written (the commit named) and never varied on a suite: a candidate for
  tuning on `calibration`.
- A commit (`git show <commit>`) says what was measured when the value was set.

Spelling: a switch is a `bool`; `None` means off (no limit, the step is not taken); `"auto"` means the core
derives the value from the data; a count of rounds or steps is an `int` (0: none). The one exception,
`DescribeParams.classifier_params`, is a nested parameter object: None stands for the chosen classifier's
defaults.
"""


def _default(f: dataclasses.Field) -> Any:
    return f.default_factory() if f.default_factory is not MISSING else f.default


def _value(v: Any, unit: str) -> str:
    """The value as the table shows it (radians also in degrees; a nested ``*Params`` by what it changes)."""
    if dataclasses.is_dataclass(v):
        base = type(v)()
        diff = [f"{f.name}={_value(getattr(v, f.name), '')}" for f in dataclasses.fields(v)
                if getattr(v, f.name) != getattr(base, f.name)]
        return f"{type(v).__name__}({', '.join(diff)})"
    if isinstance(v, bool) or v is None:
        return repr(v)
    if isinstance(v, float):
        text = f"{v:.6g}"
        if text.lstrip("-").isdigit():
            text += ".0"  # a float reads as one
        return f"{text} ({math.degrees(v):.4g} deg)" if unit == "rad" else text
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, tuple):
        return ", ".join(str(x) for x in v)
    return str(v)


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def table() -> str:
    """The text of ``docs/tuning.md``: one table of every field of every ``*Params`` of the core, then the named
    constants that are not settings."""
    lines = [HEADER, "| Params | field | value | unit | where chosen |", "|---|---|---|---|---|"]
    for cls in params_classes():
        for f in dataclasses.fields(cls):
            md = f.metadata
            unit = md.get("unit", "?")
            lines.append(f"| `{cls.__name__}` | `{f.name}` | {_cell(_value(_default(f), unit))} | {_cell(unit)} | "
                         f"{_cell(md.get('chosen', '?'))} |")
    lines += ["", "## Named constants that are not settings", "",
              "| module | name | value | unit | why a constant |", "|---|---|---|---|---|"]
    for module, name, unit, why in CONSTANTS:
        value = getattr(importlib.import_module(module), name)
        lines.append(f"| `{module}` | `{name}` | {_cell(_value(value, unit))} | {_cell(unit)} | {_cell(why)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Print docs/tuning.md's table, or (``--write``) write it."""
    ap = argparse.ArgumentParser(prog="python -m harness.tuning",
                                 description="every tuned value of the core (docs/tuning.md), from the code")
    ap.add_argument("--write", action="store_true", help=f"write the table to {DOC_PATH} instead of printing it")
    args = ap.parse_args(argv)
    text = table()
    if args.write:
        DOC_PATH.write_text(text)
        print(f"wrote {DOC_PATH}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
