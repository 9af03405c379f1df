"""Shared fixtures. The tests mirror the package tree (tests/scenes, tests/sensors, tests/recognition/...,
tests/evaluation, tests/reports, tests/harness); helpers common to several files are in ``_support.py``."""

from __future__ import annotations

import _support
import pytest


@pytest.fixture()
def tiny_sensor(tmp_path):
    """``tmp_path / "tiny_sensor.yaml"``: the 160 x 120 camera of :data:`_support.TINY_SENSOR`."""
    path = tmp_path / "tiny_sensor.yaml"
    path.write_text(_support.TINY_SENSOR)
    return path
