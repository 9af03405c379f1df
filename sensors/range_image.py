"""Range images: the :class:`Scan` the recognition core sees and the :class:`ScanTruth` beside it.

DESIGN 10.1: the core receives a ``Scan`` only (range, points, sensor intrinsics, noise parameters and an
optional noisy pose prior). The sensor pose, true per-pixel sigma, true normals and surface ids are
truth, carried by ``ScanTruth`` to evaluation. :class:`RangeImage` pairs them for saving and loading.

``ScanTruth.flags`` is a per-pixel uint8 bitmask of what the simulator did (:data:`FLAG_NAMES`):

========  =====  ==========================================================================
bit       value  meaning
========  =====  ==========================================================================
MIXED     1      footprint blend moved the return away from the centre ray's surface
OUTLIER   2      the return was replaced by a random range
RANGE     4      dropout: the surface lies outside [min_range, max_range]
GRAZING   8      dropout: grazing incidence
SPECULAR  16     dropout: specular material
WEAK      32     dropout: too few footprint sub-rays returned
========  =====  ==========================================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.mjcf import Surface
from sensors.models import SensorModel
from sensors.noise import NoiseModel

FLAG_MIXED = np.uint8(1)
FLAG_OUTLIER = np.uint8(2)
FLAG_RANGE = np.uint8(4)
FLAG_GRAZING = np.uint8(8)
FLAG_SPECULAR = np.uint8(16)
FLAG_WEAK = np.uint8(32)
FLAG_NAMES = {"mixed": 1, "outlier": 2, "range": 4, "grazing": 8, "specular": 16, "weak": 32}
FLAG_DROPOUT = np.uint8(FLAG_RANGE | FLAG_GRAZING | FLAG_SPECULAR | FLAG_WEAK)


@dataclass(frozen=True, eq=False)
class Scan:
    """What the recognition core may see.

    Attributes
    ----------
    range : ndarray of shape (H, W), float64, metres along the ray; NaN = no return.
    points : ndarray of shape (H, W, 3), float64, sensor frame (OpenCV: x right, y down, z forward); NaN
        where no return.
    sensor : the sensor model (intrinsics, ray directions).
    noise : the preset's noise parameters (the core computes its own per-pixel sigma from them).
    pose_prior : optional noisy ``T_world_sensor`` (4, 4), only when a suite asks for one.
    """

    range: np.ndarray
    points: np.ndarray
    sensor: SensorModel
    noise: NoiseModel
    pose_prior: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.range.shape

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool, True where there is a return."""
        return np.isfinite(self.range)

    @property
    def depth(self) -> np.ndarray:
        """(H, W) float64, z in the sensor frame (metres); NaN where no return."""
        return self.points[..., 2]


@dataclass(frozen=True, eq=False)
class ScanTruth:
    """Ground truth travelling beside a :class:`Scan`, to evaluation only.

    Attributes
    ----------
    T_world_sensor : (4, 4) true sensor pose, ``p_world = T_world_sensor @ p_sensor``.
    sigma : (H, W) true per-pixel range sigma along the ray (metres), NaN where no return.
    surface_id : (H, W) int32 index into ``surfaces`` of the surface under the centre ray, -1 = none.
    normals : (H, W, 3) true outward unit normals in the sensor frame, NaN where no surface.
    surfaces : the truth surface table (``surfaces[i].index == i``).
    true_range : (H, W) exact range of the centre ray before noise (metres), NaN = no surface within
        ``max_range``.
    flags : (H, W) uint8 bitmask (module docstring).
    """

    T_world_sensor: np.ndarray
    sigma: np.ndarray
    surface_id: np.ndarray
    normals: np.ndarray
    surfaces: tuple[Surface, ...]
    true_range: np.ndarray
    flags: np.ndarray

    @property
    def measured(self) -> np.ndarray:
        """(H, W) bool: the pixels where the sensor returned a point (no dropout flag). A surface closer than the
        sensor's minimum range, or dark at grazing incidence, is in the truth image but shows nothing there."""
        return (self.flags & FLAG_DROPOUT) == 0

    def surface_pixel_counts(self, valid: np.ndarray | None = None) -> dict[int, int]:
        """Pixels per surface index (only where ``valid``, if given), largest first."""
        ids = self.surface_id if valid is None else np.where(valid, self.surface_id, -1)
        counts = np.bincount(ids[ids >= 0].ravel(), minlength=len(self.surfaces))
        order = np.argsort(-counts, kind="stable")
        return {int(i): int(counts[i]) for i in order if counts[i] > 0}


@dataclass(frozen=True, eq=False)
class RangeImage:
    """A scan and (optionally) its truth, as saved together in a ``.npz``."""

    scan: Scan
    truth: ScanTruth | None = None


__all__ = ["Scan", "ScanTruth", "RangeImage", "FLAG_MIXED", "FLAG_OUTLIER", "FLAG_RANGE", "FLAG_GRAZING",
           "FLAG_SPECULAR", "FLAG_WEAK", "FLAG_NAMES", "FLAG_DROPOUT"]
