"""What many test files share: the repository's paths, a tiny sensor for fast runs, an angle helper.

``tests/`` is on ``sys.path`` under pytest's default import mode (``conftest.py`` lives here), so a test file in
any folder below imports this as ``import _support``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent                      # the repository
DATA = TESTS / "data"                    # the tests' own data files
REAL = ROOT.parent / "shared" / "data" / "real"   # the workplace's real scans (absent elsewhere: tests skip)

#: a 160 x 120 range camera: trials of the mock-up in a fraction of a second
TINY_SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise:
  range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
  footprint: {rays: 2, radius_px: 0.5, min_return_fraction: 0.5, mixed_threshold_sigma: 3}
  outliers: {rate: 2.0e-4}
"""


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions, or between two rotations ((3, 3) or the rotation of (4, 4) poses), in
    degrees."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    if a.shape == (4, 4):
        a, b = a[:3, :3], b[:3, :3]
    if a.shape == (3, 3):
        c = (np.trace(a @ b.T) - 1.0) / 2.0
    else:
        c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
