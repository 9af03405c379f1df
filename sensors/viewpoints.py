"""Seeded sensor viewpoints in the free space of a scene, looking at its parts.

A candidate is drawn as: a target feature (uniformly among the features of objects other than floors
and walls, when there are any), a point on it, a direction from it (azimuth uniform, elevation in
``spec.elevation_deg``) and a distance (``spec.distance_m``). It is rejected when the sensor position
leaves the scene's bounds, lies closer than ``spec.clearance_m`` to any geometry (or inside it), or when
the noise-free view shows fewer than ``spec.min_surfaces`` truth surfaces of at least ``spec.min_pixels``
pixels each (DESIGN 10.5: 4 surfaces of 200 pixels). The rejection counts per reason are reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scenes.geometry import look_at
from scenes.model import SceneModel
from sensors.models import SensorModel
from sensors.simulate import Simulator

REJECT_REASONS = ("outside_bounds", "no_clearance", "too_few_surfaces")


@dataclass(frozen=True)
class ViewpointSpec:
    """What makes an acceptable viewpoint.

    Attributes
    ----------
    min_surfaces, min_pixels : at least ``min_surfaces`` truth surfaces with ``min_pixels`` pixels each.
    distance_m : (min, max) distance from the target point, metres; None: ``(max(1.5 min_range,
        0.15 max_range), 0.6 max_range)`` of the sensor.
    elevation_deg : (min, max) elevation of the sensor above the target, degrees.
    clearance_m : minimum distance to any geometry; None: 2 % of the sensor's max range (at least 2 cm).
    max_attempts : candidates drawn per requested viewpoint before giving up.
    """

    min_surfaces: int = 4
    min_pixels: int = 200
    distance_m: tuple[float, float] | None = None
    elevation_deg: tuple[float, float] = (5.0, 60.0)
    clearance_m: float | None = None
    max_attempts: int = 100

    def __post_init__(self):
        if self.min_surfaces < 0 or self.min_pixels < 1:
            raise ValueError(f"min_surfaces must be >= 0 and min_pixels >= 1, got {self.min_surfaces}, "
                             f"{self.min_pixels}")
        if self.distance_m is not None and not 0 < self.distance_m[0] <= self.distance_m[1]:
            raise ValueError(f"distance_m must satisfy 0 < min <= max, got {self.distance_m}")
        if not -90 <= self.elevation_deg[0] <= self.elevation_deg[1] <= 89:
            raise ValueError(f"elevation_deg must satisfy -90 <= min <= max <= 89, got {self.elevation_deg}")
        if self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1, got {self.max_attempts}")

    def distances(self, sensor: SensorModel) -> tuple[float, float]:
        if self.distance_m is not None:
            return self.distance_m
        return max(1.5 * sensor.min_range, 0.15 * sensor.max_range), 0.6 * sensor.max_range

    def clearance(self, sensor: SensorModel) -> float:
        return self.clearance_m if self.clearance_m is not None else max(0.02, 0.02 * sensor.max_range)


@dataclass(frozen=True)
class Viewpoint:
    """An accepted viewpoint: ``T_world_sensor`` (4, 4), the target point and feature, surface pixel counts."""

    T_world_sensor: np.ndarray
    target: np.ndarray
    target_feature: str
    surface_pixels: dict[int, int]


@dataclass(frozen=True)
class ViewpointSample:
    """The accepted viewpoints and the rejection statistics of the draw."""

    viewpoints: tuple[Viewpoint, ...]
    attempts: int
    rejected: dict[str, int] = field(default_factory=dict)

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    @property
    def rejection_rate(self) -> float:
        """Rejected candidates / candidates drawn (0 when none were drawn)."""
        return self.n_rejected / self.attempts if self.attempts else 0.0


def scene_bounds(sim: Simulator) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned world bounds (lo (3,), hi (3,)) of the scene's geoms (from their bounding spheres)."""
    c, r = sim.caster.sphere_centre, sim.caster.sphere_radius
    return (c - r[:, None]).min(axis=0), (c + r[:, None]).max(axis=0)


def sample_viewpoints(sim: Simulator, scene: SceneModel, sensor: SensorModel, n: int, rng: np.random.Generator,
                      spec: ViewpointSpec = ViewpointSpec()) -> ViewpointSample:
    """Draw up to ``n`` acceptable viewpoints (fewer when ``n * spec.max_attempts`` candidates do not give them).

    Parameters
    ----------
    sim : the compiled scene.
    scene : its model (targets are drawn on its features).
    sensor : the sensor whose view is judged.
    n : viewpoints wanted.
    rng : all random draws come from it (same seed, same viewpoints).
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    targets = [f for o in scene.objects if o.kind not in ("floor", "wall") for f in o.features] \
        or list(scene.features)
    if not targets:
        raise ValueError("the scene has no features to look at")
    d_lo, d_hi = spec.distances(sensor)
    el_lo, el_hi = (math.radians(a) for a in spec.elevation_deg)
    clearance = spec.clearance(sensor)
    lo, hi = scene_bounds(sim)
    extent = hi - lo
    box_lo = lo - 0.1 * extent * np.array([1, 1, 0])
    box_hi = hi + np.array([0.1, 0.1, 0.5]) * extent
    rejected = dict.fromkeys(REJECT_REASONS, 0)
    accepted: list[Viewpoint] = []
    attempts = 0
    while len(accepted) < n and attempts < n * spec.max_attempts:
        attempts += 1
        feature = targets[int(rng.integers(len(targets)))]
        target = feature.sample(1, rng)[0][0]
        az = rng.uniform(0.0, 2 * math.pi)
        el = rng.uniform(el_lo, el_hi)
        dist = rng.uniform(d_lo, d_hi)
        position = target + dist * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        if np.any(position < box_lo) or np.any(position > box_hi):
            rejected["outside_bounds"] += 1
            continue
        if sim.clearance(position) < clearance:
            rejected["no_clearance"] += 1
            continue
        T = look_at(position, target)
        _, surface = sim.truth_image(sensor, T, check=False)
        counts = np.bincount(surface[surface >= 0].ravel(), minlength=len(sim.surfaces))
        big = np.flatnonzero(counts >= spec.min_pixels)
        if len(big) < spec.min_surfaces:
            rejected["too_few_surfaces"] += 1
            continue
        accepted.append(Viewpoint(T, target, feature.id, {int(i): int(counts[i]) for i in big}))
    return ViewpointSample(tuple(accepted), attempts, rejected)


__all__ = ["ViewpointSpec", "Viewpoint", "ViewpointSample", "sample_viewpoints", "scene_bounds", "REJECT_REASONS"]
