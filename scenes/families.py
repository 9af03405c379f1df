"""Scene families: generated a priori models named by (family, seed).

A suite group may draw its scenes from a family instead of naming one scene file (DESIGN 11.1):

* ``factory``: the procedural factory bay of :func:`scenes.generator.generate_factory`, configured by a
  ``generator/1`` YAML (default ``scenes/data/factory_generator.yaml``);
* ``mockup``: the parametric paper-like mock-up of :func:`scenes.mockup_family.generate_mockup`, configured
  by a ``mockup_family/1`` YAML (default ``scenes/data/mockup_family.yaml``).

A member is named ``<family>-s<seed>`` (e.g. ``factory-s1003``): the name a trial id starts with and the
unit that the summary's intervals resample. The same family, configuration and seed give the same model,
byte for byte once saved.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from scenes.generator import DATA_DIR, FACTORY_GENERATOR, GeneratorConfig, generate_factory
from scenes.mockup_family import MOCKUP_FAMILY, MockupFamilyConfig, generate_mockup
from scenes.model import SceneModel


@dataclass(frozen=True)
class Family:
    """How to make the members of one family: its default config file and ``make(config_path, seed, name)``."""

    name: str
    default_config: Path
    make: Callable[[Path, int, str], SceneModel]


def _factory(config: Path, seed: int, name: str) -> SceneModel:
    return generate_factory(GeneratorConfig.load(config), seed, name)


def _mockup(config: Path, seed: int, name: str) -> SceneModel:
    return generate_mockup(MockupFamilyConfig.load(config), seed, name)


FAMILIES: dict[str, Family] = {
    "factory": Family("factory", FACTORY_GENERATOR, _factory),
    "mockup": Family("mockup", MOCKUP_FAMILY, _mockup),
}


def member_name(family: str, seed: int) -> str:
    """The name of a family member, e.g. ``factory-s1003``."""
    return f"{family}-s{seed}"


def family_config_path(family: str, config: str | Path | None = None) -> Path:
    """The config file of ``family``: ``config`` (a shipped config name or a path), or the family's default.

    Raises
    ------
    ValueError
        For an unknown family or a config that is neither a shipped name nor a file.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r} (known: {', '.join(FAMILIES)})")
    if config is None:
        return FAMILIES[family].default_config
    for cand in (DATA_DIR / f"{config}.yaml", Path(config)):
        if cand.is_file():
            return cand.resolve()
    raise ValueError(f"no shipped config named {str(config)!r} and no such file")


def family_member(family: str, seed: int, config: str | Path | None = None) -> SceneModel:
    """The a priori model of member ``seed`` of ``family`` (see the module docstring), its numbers rounded to 10
    decimals (:meth:`SceneModel.rounded`: the same scene on every machine)."""
    path = family_config_path(family, config)
    return FAMILIES[family].make(path, seed, member_name(family, seed)).rounded()
