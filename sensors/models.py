"""Geometric sensor models: a pinhole range camera and a scanning laser range finder.

Both are frozen dataclasses holding only intrinsic parameters (resolution, field of view, range
limits); the sensor pose is *not* part of the model (it is ground truth, DESIGN 10.1). Angles are
radians inside (YAML uses degrees with a ``_deg`` suffix, see :mod:`sensors.config`).

Frames: the sensor frame is OpenCV's (x right, y down, z forward). Images are indexed ``[row, col]``
= ``[v, u]``; ``ray_directions()`` gives one unit vector per pixel, shape (H, W, 3).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np


def _check_resolution(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def _check_ranges(min_range: float, max_range: float) -> tuple[float, float]:
    lo, hi = float(min_range), float(max_range)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"range limits must be finite, got [{lo}, {hi}]")
    if lo < 0:
        raise ValueError(f"min_range must be >= 0, got {lo}")
    if hi <= lo:
        raise ValueError(f"max_range must be > min_range ({lo}), got {hi}")
    return lo, hi


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole range camera with intrinsics ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``.

    Pixel ``(u, v)`` (column, row; pixel centres at integer coordinates, OpenCV) looks along the
    ray ``((u - cx) / fx, (v - cy) / fy, 1)``. Build one from a field of view with :meth:`from_fov`.

    Attributes
    ----------
    width, height : image size in pixels (>= 1).
    fx, fy : focal lengths in pixels (> 0).
    cx, cy : principal point in pixels.
    min_range, max_range : metres along the ray; returns outside are dropped.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    min_range: float
    max_range: float

    kind: ClassVar[str] = "pinhole"

    def __post_init__(self):
        object.__setattr__(self, "width", _check_resolution("width", self.width))
        object.__setattr__(self, "height", _check_resolution("height", self.height))
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        lo, hi = _check_ranges(self.min_range, self.max_range)
        object.__setattr__(self, "min_range", lo)
        object.__setattr__(self, "max_range", hi)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float, vfov_deg: float | None = None, *,
                 min_range: float, max_range: float) -> PinholeCamera:
        """Centred camera with horizontal field of view ``fov_deg`` (and vertical ``vfov_deg``;
        default: square pixels). Both must be in (0, 180) degrees."""
        width = _check_resolution("width", width)
        height = _check_resolution("height", height)
        for name, value in (("fov_deg", fov_deg), ("vfov_deg", vfov_deg)):
            if value is not None and not 0.0 < float(value) < 180.0:
                raise ValueError(f"{name} must be in (0, 180) degrees, got {value}")
        tans = [math.tan(math.radians(v) / 2.0) for v in (fov_deg, vfov_deg) if v is not None]
        if min(tans) <= 0.0:  # a field of view so small that its tangent underflows (e.g. 1e-320 degrees)
            raise ValueError(f"field of view too small to give a finite focal length: {fov_deg}, {vfov_deg}")
        fx = (width / 2.0) / tans[0]
        fy = fx if vfov_deg is None else (height / 2.0) / tans[1]
        return cls(width, height, fx, fy, (width - 1) / 2.0, (height - 1) / 2.0, min_range, max_range)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)``."""
        return (self.height, self.width)

    @property
    def K(self) -> np.ndarray:
        """Intrinsic matrix, shape (3, 3)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees (edge to edge of the image)."""
        return (math.degrees(2 * math.atan(self.width / 2.0 / self.fx)),
                math.degrees(2 * math.atan(self.height / 2.0 / self.fy)))

    @property
    def pixel_pitch_rad(self) -> float:
        """Angular size of a pixel at the principal point (radians)."""
        return 1.0 / min(self.fx, self.fy)

    def ray_directions(self, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """Unit ray directions in the sensor frame, shape (H, W, 3), read-only (cached per sensor and offset).

        Parameters
        ----------
        offset : (du, dv) sub-pixel offset in pixels added to every pixel centre (beam footprint sub-rays).
        """
        return _cached_rays(self, float(offset[0]), float(offset[1]))

    def _rays(self, offset: tuple[float, float]) -> np.ndarray:
        u = np.arange(self.width, dtype=np.float64) + offset[0]
        v = np.arange(self.height, dtype=np.float64) + offset[1]
        d = np.empty((self.height, self.width, 3))
        d[..., 0] = ((u - self.cx) / self.fx)[None, :]
        d[..., 1] = ((v - self.cy) / self.fy)[:, None]
        d[..., 2] = 1.0
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return d

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (N, 2) ``(u, v)`` of sensor-frame points (N, 3); NaN for points with z <= 0."""
        p = np.asarray(points, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * p[:, 0] / p[:, 2] + self.cx, self.fy * p[:, 1] / p[:, 2] + self.cy], axis=1)
        uv[p[:, 2] <= 0] = np.nan
        return uv


@dataclass(frozen=True)
class ScanningLaser:
    """A scanning laser range finder sampling an azimuth x elevation grid from one origin.

    Column ``j`` has azimuth ``az_min + (j + 0.5) (az_max - az_min) / n_azimuth`` (positive to the
    right, about the sensor's -y axis); row ``i`` has elevation ``el_max - (i + 0.5) (el_max - el_min) /
    n_elevation`` (positive up, so row 0 is the top of the image). The direction of ``(az, el)`` in the
    sensor frame is ``(cos el sin az, -sin el, cos el cos az)``.

    Attributes
    ----------
    n_azimuth, n_elevation : grid size (image width and height, >= 1).
    azimuth_min, azimuth_max : radians, ``-pi <= min < max <= pi``.
    elevation_min, elevation_max : radians, ``-pi/2 <= min < max <= pi/2``.
    min_range, max_range : metres along the ray.
    """

    n_azimuth: int
    n_elevation: int
    azimuth_min: float
    azimuth_max: float
    elevation_min: float
    elevation_max: float
    min_range: float
    max_range: float

    kind: ClassVar[str] = "laser"

    def __post_init__(self):
        object.__setattr__(self, "n_azimuth", _check_resolution("n_azimuth", self.n_azimuth))
        object.__setattr__(self, "n_elevation", _check_resolution("n_elevation", self.n_elevation))
        for name in ("azimuth_min", "azimuth_max", "elevation_min", "elevation_max"):
            object.__setattr__(self, name, float(getattr(self, name)))
        eps = 1e-12
        if not -math.pi - eps <= self.azimuth_min < self.azimuth_max <= math.pi + eps:
            raise ValueError("azimuth limits must satisfy -180 <= min < max <= 180 degrees, got "
                             f"[{math.degrees(self.azimuth_min):g}, {math.degrees(self.azimuth_max):g}]")
        if not -math.pi / 2 - eps <= self.elevation_min < self.elevation_max <= math.pi / 2 + eps:
            raise ValueError("elevation limits must satisfy -90 <= min < max <= 90 degrees, got "
                             f"[{math.degrees(self.elevation_min):g}, {math.degrees(self.elevation_max):g}]")
        lo, hi = _check_ranges(self.min_range, self.max_range)
        object.__setattr__(self, "min_range", lo)
        object.__setattr__(self, "max_range", hi)

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` = ``(n_elevation, n_azimuth)``."""
        return (self.n_elevation, self.n_azimuth)

    @property
    def width(self) -> int:
        return self.n_azimuth

    @property
    def height(self) -> int:
        return self.n_elevation

    @property
    def azimuth_step(self) -> float:
        return (self.azimuth_max - self.azimuth_min) / self.n_azimuth

    @property
    def elevation_step(self) -> float:
        return (self.elevation_max - self.elevation_min) / self.n_elevation

    @property
    def pixel_pitch_rad(self) -> float:
        """Angular grid step (radians, the smaller of the two)."""
        return min(self.azimuth_step, self.elevation_step)

    def angles(self, offset: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """Azimuths (W,) and elevations (H,) in radians, with a sub-cell ``offset`` (du, dv) in cells."""
        az = self.azimuth_min + (np.arange(self.n_azimuth) + 0.5 + offset[0]) * self.azimuth_step
        el = self.elevation_max - (np.arange(self.n_elevation) + 0.5 + offset[1]) * self.elevation_step
        return az, el

    def ray_directions(self, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """Unit ray directions in the sensor frame, shape (H, W, 3) (see the class docstring), read-only
        (cached per sensor and offset)."""
        return _cached_rays(self, float(offset[0]), float(offset[1]))

    def _rays(self, offset: tuple[float, float]) -> np.ndarray:
        az, el = self.angles(offset)
        ce = np.cos(el)[:, None]
        d = np.empty((self.n_elevation, self.n_azimuth, 3))
        d[..., 0] = ce * np.sin(az)[None, :]
        d[..., 1] = -np.sin(el)[:, None]
        d[..., 2] = ce * np.cos(az)[None, :]
        return d


SensorModel = PinholeCamera | ScanningLaser


@functools.lru_cache(maxsize=8)
def _cached_rays(sensor: SensorModel, du: float, dv: float) -> np.ndarray:
    """One home for the ray images: several stages of a frame need them (sigma, change, verification), and
    at 640 x 480 each costs about 9 ms to build. Read-only, so no caller can change another's copy."""
    d = sensor._rays((du, dv))
    d.setflags(write=False)
    return d

__all__ = ["PinholeCamera", "ScanningLaser", "SensorModel"]
