"""Simulated range scans: exact ray casting plus the configured noise model.

:class:`Simulator` holds a compiled scene (reuse it across scans: compiling and tiling are the slow
parts); :func:`simulate` is the one-shot form. Order of operations per pixel (all vectorised):

1. centre ray cast: exact range, geom, surface id (truth), true normal (analytic, also for meshes);
   surfaces beyond ``max_range`` are dropped from the truth (flag RANGE), closer than ``min_range``
   are kept in the truth but give no return (flag RANGE);
2. footprint: ``k - 1`` more sub-rays per pixel; the return is the mean of the sub-ray ranges that lie
   within the range limits; too few of them -> dropout (WEAK); a blend far from the centre ray's
   exact range is flagged MIXED;
3. Gaussian range noise with ``sigma(true range, true incidence, ray z)``;
4. quantisation; 5. outliers; 6. grazing and specular dropouts.

Randomness: four child generators are seeded from ``rng`` on every call (whatever the configuration),
one per random term (range noise, outliers, grazing, specular), so switching one term off leaves the
draws of the others unchanged, and the same seed gives bit-identical output. Each term draws one value
per pixel that sees a surface within the range limits.
"""

from __future__ import annotations

from collections.abc import Iterable

import mujoco
import numpy as np
import scipy.ndimage as ndi

from scenes.features import Feature
from scenes.geometry import check_transform
from scenes.mjcf import ExportedScene, export_mjcf
from scenes.model import SceneModel
from sensors.config import SensorConfig
from sensors.models import SensorModel
from sensors.range_image import (
    FLAG_GRAZING,
    FLAG_MIXED,
    FLAG_OUTLIER,
    FLAG_RANGE,
    FLAG_SPECULAR,
    FLAG_WEAK,
    Scan,
    ScanTruth,
)
from sensors.raycast import Hits, RayBundle, RayCaster, matmul_rows, surface_of_hits


class SensorPlacementError(ValueError):
    """The sensor pose is unusable (inside geometry, not a rigid transform)."""


class Simulator:
    """A compiled scene ready to be scanned.

    Parameters
    ----------
    exported : the scene's MJCF export.
    mj_model : its compiled ``MjModel`` (compiled here when None).
    scene : the scene's features (``SceneModel`` or iterable of features): needed for analytic normals and
        exact ranges on mesh geoms (cones, tori) and for material-dependent (specular) dropouts.
    tile_px : tile size for the caster's geom culling (0 = off).
    """

    def __init__(self, exported: ExportedScene, mj_model: mujoco.MjModel | None = None,
                 scene: SceneModel | Iterable[Feature] | None = None, tile_px: int = 32):
        self.exported = exported
        feats = getattr(scene, "features", scene)
        feats = tuple(feats) if feats is not None else None
        self.caster = RayCaster(exported, mj_model, feats, tile_px)
        by_id = {f.id: f for f in feats} if feats is not None else {}
        self.surface_material = tuple(by_id[s.feature_id].material if s.feature_id in by_id else "matte"
                                      for s in exported.surfaces)
        self._dirs: dict = {}

    @classmethod
    def from_scene(cls, scene: SceneModel, **kwargs) -> Simulator:
        """Export ``scene`` to MJCF and compile it."""
        return cls(export_mjcf(scene), scene=scene, **kwargs)

    @property
    def surfaces(self):
        return self.exported.surfaces

    # -- rays -----------------------------------------------------------------------------------------
    def directions(self, sensor: SensorModel, offset: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """Unit ray directions (H * W, 3), sensor frame, image order (cached)."""
        key = (sensor, float(offset[0]), float(offset[1]))
        d = self._dirs.get(key)
        if d is None:
            d = sensor.ray_directions(offset).reshape(-1, 3)
            d.setflags(write=False)
            self._dirs[key] = d
        return d

    def _bundle(self, sensor: SensorModel, offset: tuple[float, float] = (0.0, 0.0)) -> RayBundle:
        key = (sensor, float(offset[0]), float(offset[1]))
        try:
            return self.caster.bundle(key)
        except KeyError:
            return self.caster.bundle(key, self.directions(sensor, offset).reshape(*sensor.shape, 3))

    def _cast(self, sensor: SensorModel, origin: np.ndarray, R: np.ndarray, offset=(0.0, 0.0),
              normals: bool = True, exclude: np.ndarray | None = None) -> Hits:
        hits = self.caster.cast(origin, R, self._bundle(sensor, offset), sensor.max_range, normals=normals,
                                exclude=exclude)
        return self.caster.refine_meshes(origin, R, self.directions(sensor, offset), hits)

    def check_pose(self, T_world_sensor: np.ndarray) -> np.ndarray:
        """Validate a sensor pose: a rigid (4, 4) transform whose origin is not inside any geometry.

        Raises
        ------
        SensorPlacementError (a ValueError) with the reason.
        """
        try:
            T = check_transform(T_world_sensor, "T_world_sensor")
        except ValueError as exc:
            raise SensorPlacementError(str(exc)) from None
        _, inside = self.caster.probe(T[:3, 3])
        if inside is not None:
            p = ", ".join(f"{x:.4g}" for x in T[:3, 3])
            raise SensorPlacementError(f"sensor position [{p}] is inside the geometry of {inside!r}")
        return T

    def clearance(self, position: np.ndarray) -> float:
        """Distance (metres) from ``position`` to the nearest geometry along 162 directions (0 if inside)."""
        return self.caster.probe(np.asarray(position, dtype=np.float64))[0]

    def truth_image(self, sensor: SensorModel, T_world_sensor: np.ndarray, check: bool = True,
                    through_containing: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free centre-ray truth: ``(true_range (H, W), surface_id (H, W) int32)``, within ``max_range``.

        ``through_containing`` (with ``check=False``): the rays pass through geometry that contains the
        sensor, instead of hitting it from inside.
        """
        T = self.check_pose(T_world_sensor) if check else np.asarray(T_world_sensor, dtype=np.float64)
        exclude = self.caster.containing(T[:3, 3]) if through_containing else None
        hits = self._cast(sensor, T[:3, 3].copy(), T[:3, :3], normals=True,
                          exclude=exclude if exclude is not None and exclude.any() else None)
        surface = surface_of_hits(self.exported, hits.geom_id, hits.normal_world)
        beyond = ~(hits.dist <= sensor.max_range)
        r = np.where(beyond, np.nan, hits.dist)
        surface[beyond] = -1
        return r.reshape(sensor.shape), surface.reshape(sensor.shape)

    # -- the scan ---------------------------------------------------------------------------------------
    def simulate(self, config: SensorConfig, T_world_sensor: np.ndarray, rng: np.random.Generator
                 ) -> tuple[Scan, ScanTruth]:
        """Scan the scene from ``T_world_sensor`` (4, 4) with ``config``'s sensor and noise.

        Returns
        -------
        (Scan, ScanTruth) : see :mod:`sensors.range_image`. A view that hits nothing is a valid all-NaN scan.

        Raises
        ------
        SensorPlacementError : the pose is not rigid or the sensor is inside geometry.
        """
        sensor, noise = config.model, config.noise
        T = self.check_pose(T_world_sensor)
        origin, R = T[:3, 3].copy(), T[:3, :3]
        H, W = sensor.shape
        n = H * W
        seeds = rng.integers(0, 2**63 - 1, size=4, dtype=np.int64)
        lo, hi = sensor.min_range, sensor.max_range

        d_s = self.directions(sensor)
        hits = self._cast(sensor, origin, R, normals=True)
        surface = surface_of_hits(self.exported, hits.geom_id, hits.normal_world)
        true_range = hits.dist
        flags = np.zeros(n, dtype=np.uint8)
        with np.errstate(invalid="ignore"):
            beyond = true_range > hi  # NaN compares False
            close = true_range < lo
        flags[beyond | close] = FLAG_RANGE
        true_range[beyond] = np.nan
        surface[beyond] = -1
        normals = matmul_rows(hits.normal_world, R)  # world -> sensor: R^T n, row-wise
        normals[beyond] = np.nan
        del hits

        seen = np.flatnonzero(np.isfinite(true_range) & ~close)
        r = true_range[seen]
        cos_i = -np.einsum("ij,ij->i", normals, d_s)[seen]
        ray_z = d_s[:, 2][seen]
        sigma = noise.sigma(r, cos_i, ray_z)
        meas = r.copy()
        fl = np.zeros(len(seen), dtype=np.uint8)
        drop = np.zeros(len(seen), dtype=bool)

        offsets = noise.footprint_offsets()
        if len(offsets) > 1:
            total = r.copy()
            count = np.ones(len(seen))
            for off in offsets[1:]:
                sub = self._cast(sensor, origin, R, (off[0], off[1]), normals=False).dist[seen]
                ok = (sub >= lo) & (sub <= hi)
                total += np.where(ok, sub, 0.0)
                count += ok
            weak = count < noise.min_return_fraction * len(offsets) - 1e-9
            drop |= weak
            fl[weak] |= FLAG_WEAK
            meas = total / count
            mixed = np.abs(meas - r) > np.maximum(noise.mixed_threshold_sigma * sigma, 1e-4 * r)
            fl[mixed & ~weak] |= FLAG_MIXED
        if noise.has_range_noise:
            g = np.random.default_rng(seeds[0])
            if noise.matching_window_px > 1:  # correlated over the matching window, unit variance per pixel
                w = noise.matching_window_px
                field = ndi.uniform_filter(g.standard_normal((H, W)), size=w, mode="reflect") * w
                meas += sigma * field.ravel()[seen]
            else:
                meas += sigma * g.standard_normal(len(seen))
        meas = noise.quantise(meas, ray_z)
        if noise.has_outliers:
            g = np.random.default_rng(seeds[1])
            out = g.random(len(seen)) < noise.outlier_rate
            meas[out] = g.uniform(lo, hi, int(out.sum()))
            fl[out] |= FLAG_OUTLIER
        if noise.has_grazing:
            graze = np.random.default_rng(seeds[2]).random(len(seen)) < noise.grazing_probability(cos_i)
            drop |= graze
            fl[graze] |= FLAG_GRAZING
        if noise.has_specular:
            probs = np.array([noise.specular_probability(m) for m in self.surface_material] + [0.0])
            spec = np.random.default_rng(seeds[3]).random(len(seen)) < probs[surface[seen]]
            drop |= spec
            fl[spec] |= FLAG_SPECULAR
        meas[drop] = np.nan
        flags[seen] |= fl

        rng_img = np.full(n, np.nan)
        rng_img[seen] = meas
        sig_img = np.full(n, np.nan)
        sig_img[seen] = np.where(drop, np.nan, sigma)
        points = rng_img[:, None] * d_s
        scan = Scan(rng_img.reshape(H, W), points.reshape(H, W, 3), sensor, noise)
        truth = ScanTruth(T.copy(), sig_img.reshape(H, W), surface.reshape(H, W), normals.reshape(H, W, 3),
                          self.exported.surfaces, true_range.reshape(H, W), flags.reshape(H, W))
        return scan, truth


def simulate(exported: ExportedScene, mj_model: mujoco.MjModel | None, config: SensorConfig,
             T_world_sensor: np.ndarray, rng: np.random.Generator, *,
             scene: SceneModel | Iterable[Feature] | None = None) -> tuple[Scan, ScanTruth]:
    """One scan (see :meth:`Simulator.simulate`); build a :class:`Simulator` to scan a scene repeatedly."""
    return Simulator(exported, mj_model, scene).simulate(config, T_world_sensor, rng)


__all__ = ["Simulator", "simulate", "SensorPlacementError"]
