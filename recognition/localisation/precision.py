"""How precisely the data fix a pose: the agreement around it (DESIGN 11.6).

ICP minimises distances to the model surfaces it pairs the points with; when a changed part or a wrong pairing
pulls it, it can stop a few centimetres from the pose the data agree with best, and its covariance (which
assumes the pairs are right) then claims millimetres. The verification's agreement
(:func:`recognition.localisation.agreement`) is the arbiter of the localisation, so its profile around the
final pose says what ICP cannot:

- :func:`probe_poses`: the pose moved by a step along each world axis and turned by a step about each world
  axis through the sensor (12 poses);
- :func:`flattest_probe`: the separation (:func:`recognition.localisation.agreement_separation`) of a pose
  from the probe the data separate it from least, with the probes at the evaluation's success tolerance:
  when that probe is not separated, the data do not fix the pose within the tolerance, and the pose cannot be
  claimed to be within it.

All pure functions of a ``score(T) -> (agreement, fractions)`` callable.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .pose import exp_so3

__all__ = ["probe_poses", "separation_z", "flattest_probe"]

Score = Callable[[np.ndarray], tuple[float, dict[int, float]]]


def probe_poses(T: np.ndarray, step_rad: float, step_m: float) -> list[np.ndarray]:
    """The 12 poses around ``T`` (4, 4) ``T_world_sensor``: ``T`` turned by ``±step_rad`` about each world axis
    through the sensor's position, then ``T`` moved by ``±step_m`` along each world axis (in that order)."""
    out = []
    for k in range(3):
        for sgn in (-1.0, 1.0):
            w = np.zeros(3)
            w[k] = sgn * step_rad
            P = T.copy()
            P[:3, :3] = exp_so3(w) @ T[:3, :3]
            out.append(P)
    for k in range(3):
        for sgn in (-1.0, 1.0):
            P = T.copy()
            P[k, 3] += sgn * step_m
            out.append(P)
    return out


def separation_z(d: float, se: float) -> float:
    """``d / se``, a difference over its standard error; with ``se = 0`` (every patch differs by the same amount)
    ``±inf`` by the sign of ``d``, 0 for no difference."""
    if se > 0:
        return d / se
    return math.inf if d > 0 else (-math.inf if d < 0 else 0.0)


def flattest_probe(T: np.ndarray, fractions: dict[int, float], score: Score, step_rad: float, step_m: float,
                   separation: Callable[[dict[int, float], dict[int, float]], tuple[float, float]]
                   ) -> tuple[float, int]:
    """The least separation ``d / se`` of ``T`` (with per-patch ``fractions``) from its 12 probes at
    ``step_rad`` and ``step_m``, and the index of that probe (:func:`probe_poses`' order).

    ``separation(fractions_T, fractions_probe) -> (d, se)``; a probe the data prefer gives a negative value.
    """
    worst, which = math.inf, -1
    for k, P in enumerate(probe_poses(T, step_rad, step_m)):
        _, f = score(P)
        z = separation_z(*separation(fractions, f))
        if z < worst:
            worst, which = z, k
    return worst, which
