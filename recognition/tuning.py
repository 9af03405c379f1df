"""Where the core's tuned values come from: every field of a ``*Params`` dataclass of :mod:`recognition` is
declared with :func:`tuned`, which records its unit and where its value was chosen (the suite and the figure,
or its honest history). ``python -m harness.tuning --write`` writes them all as one table, ``docs/tuning.md``,
with the few named numeric constants that are not settings (:data:`CONSTANTS`); a test fails when the file and
the code disagree.

The spelling of a setting, the same in every ``*Params`` (:data:`AUTO`):

* a switch is a plain ``bool``;
* a threshold, limit or step that can be turned off is ``T | None``, and ``None`` means off (no limit, the
  step is not taken); no number (0, 1, 1_000_000) stands for off;
* a value the core derives from the data unless it is given is ``T | "auto"`` (never ``None``);
* a count of rounds or steps is a plain ``int``: 0 runs none of them.

One field is none of these: ``DescribeParams.classifier_params`` is a nested parameter object whose class
depends on ``classifier``; None there stands for that classifier's own defaults.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import MISSING
from typing import Any

__all__ = ["AUTO", "tuned", "PARAMS_MODULES", "params_classes", "CONSTANTS"]

AUTO = "auto"
"""The value of a ``*Params`` field that the core derives from the data (``"auto"``; ``None`` means off)."""

#: The modules that declare the core's ``*Params`` dataclasses, in the order of the paper's stages.
PARAMS_MODULES = (
    "recognition.segmentation.types",
    "recognition.classification.params",
    "recognition.describe",
    "recognition.localisation.matching",
    "recognition.localisation.verification",
    "recognition.localisation.icp",
    "recognition.localisation.localise",
    "recognition.change.detection",
    "recognition.peers.registration",
    "recognition.peers.primitives",
    "recognition.peers.differencing",
)

#: The named numeric constants of the core that are not settings, as ``(module, name, unit, why)``. Physical or
#: mathematical constants, measurements and library defaults stay constants; anything a stage's result depends on
#: and that one might tune is a ``*Params`` field instead (a test fails on any other numeric module constant).
CONSTANTS = (
    ("recognition.fitting.algebra", "MIN_GRAZING", "|cos|",
     "part of the definition of the ray residual shared by the fits and the segmentation: beyond ~75 deg incidence "
     "the orthogonal distance / 0.25 stands in (not tuned, b65f74f)"),
    ("recognition.fitting._solver", "TRIM_SIGMA", "sigma",
     "the fits' API default level of chi2_trim for callers that do not say; the select classifier passes "
     "SelectParams.trim_sigma"),
    ("recognition.fitting._solver", "_INIT_POINTS", "points",
     "the fitting library's coarse subset for choosing between starts (not a stage's setting; not tuned, 1a61ec8)"),
    ("recognition.describe", "BYTES_PER_PIXEL", "bytes",
     "a measurement (describe()'s peak working memory per pixel at 1000² and 2000², with margin), for the error "
     "that max_pixels raises"),
    ("recognition.peers.registration", "_MODEL_CACHE_SIZE", "models", "a cache size: no result depends on it"),
    ("recognition.segmentation.quick_fits", "UNDETERMINED_QUADRIC", "eigenvalue / trace",
     "numerical: a null space of two or more quadrics (a one-pixel strip lies exactly on a plane through the "
     "sensor: eigenvalues ~1e-17 against ~1e-8 and up for the noisiest real groups of 10-16 points)"),
    ("recognition.localisation.pose", "COST_TIE_REL", "fraction",
     "numerical: costs that agree to this are the same fit up to rounding (the floating-point paths differ by "
     "~1e-12 of the cost), ordered by a tie rule"),
)


def tuned(default: Any = MISSING, *, unit: str, chosen: str, default_factory: Any = MISSING) -> Any:
    """A ``*Params`` field: its default, its unit and where its value was chosen.

    Parameters
    ----------
    default, default_factory : as for :func:`dataclasses.field` (exactly one of them).
    unit : the unit of the value (``"sigma"``, ``"px"``, ``"m"``, ``"rad"``, ``"fraction"``, ``"count"``, ...;
        ``"-"`` for switches and choices).
    chosen : where the value was chosen: the suite and the figure (``"calibration: correct detection 0.730 ->
        0.739"``), or its honest history (``"not tuned: set with the step in b65f74f"``). One sentence or two.
    """
    if (default is MISSING) == (default_factory is MISSING):
        raise TypeError("tuned() needs exactly one of default and default_factory")
    if not unit or not chosen:
        raise ValueError("tuned() needs a unit and where the value was chosen")
    metadata = {"unit": unit, "chosen": chosen}
    if default_factory is not MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def params_classes() -> list[type]:
    """Every ``*Params`` dataclass declared in :data:`PARAMS_MODULES`, in declaration order."""
    out = []
    for name in PARAMS_MODULES:
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if (isinstance(obj, type) and dataclasses.is_dataclass(obj) and obj.__name__.endswith("Params")
                    and obj.__module__ == name):
                out.append(obj)
    return out
