"""Exact ray casting against an exported scene with ``mujoco.mj_multiRay`` (no OpenGL).

:class:`RayCaster` holds a compiled ``MjModel`` and casts bundles of rays from one origin. Native
geoms (boxes, cylinders, spheres) give analytic hits and normals. Mesh geoms (cones, torus sections,
spherical caps) are refined onto the analytic feature surface by Newton steps along the ray and get
the analytic normal of the feature, so truth ranges and normals do not carry the facetting.

Speed. ``mj_multiRay`` tests every ray against every geom that its angular bounding box admits, so
its cost grows with the number of geoms. The caster splits the image into square tiles and, per tile,
admits only the geoms whose bounding spheres (a few per geom, covering its box) intersect the
tile's cone of rays; the admitted set is passed to MuJoCo through the geom groups (the model's
``geom_group`` is rewritten per tile and restored afterwards). The result is identical to one
untiled call (a test checks it); ``tile_px=0`` disables tiling.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import mujoco
import numpy as np

from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.mjcf import GEOM_BOX, GEOM_CYLINDER, ExportedScene

_INCLUDE_GROUP0 = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)
_MAX_SPLIT = 12  # bounding spheres per geom axis


@dataclass(frozen=True)
class RayBundle:
    """A fixed set of rays from one origin, ordered tile by tile.

    Attributes
    ----------
    shape : image shape (H, W).
    dirs : ndarray of shape (N, 3), unit directions in the sensor frame, tile-major order, N = H * W.
    order : ndarray of shape (N,), flat image index of each ray in ``dirs``.
    inverse : ndarray of shape (N,), position in ``dirs`` of each image pixel (``order[inverse] == arange(N)``).
    starts : ndarray of shape (T + 1,), tile boundaries in ``dirs``.
    axes : ndarray of shape (T, 3), unit axis of each tile's ray cone (sensor frame).
    half_angle : ndarray of shape (T,), radians, half-angle of each tile's cone (covers all its rays).
    """

    shape: tuple[int, int]
    dirs: np.ndarray
    order: np.ndarray
    inverse: np.ndarray
    starts: np.ndarray
    axes: np.ndarray
    half_angle: np.ndarray

    @staticmethod
    def build(directions: np.ndarray, tile_px: int) -> RayBundle:
        """Bundle the (H, W, 3) unit directions into tiles of ``tile_px`` x ``tile_px`` pixels (0: one tile)."""
        H, W, _ = directions.shape
        if tile_px <= 0:
            tile_px = max(H, W)
        nty, ntx = -(-H // tile_px), -(-W // tile_px)
        idx = np.full((nty * tile_px, ntx * tile_px), -1, dtype=np.int64)
        idx[:H, :W] = np.arange(H * W).reshape(H, W)
        blocks = idx.reshape(nty, tile_px, ntx, tile_px).transpose(0, 2, 1, 3).reshape(nty * ntx, -1)
        counts = np.count_nonzero(blocks >= 0, axis=1)
        order = blocks[blocks >= 0]
        dirs = np.ascontiguousarray(directions.reshape(-1, 3)[order])
        nonempty = counts > 0
        starts = np.concatenate([[0], np.cumsum(counts[nonempty])])
        sums = np.add.reduceat(dirs, starts[:-1], axis=0)
        norms = np.linalg.norm(sums, axis=1, keepdims=True)
        degenerate = norms[:, 0] < 1e-9 * np.diff(starts)  # rays spread all round: admit everything
        axes = np.where(degenerate[:, None], [0.0, 0.0, 1.0], sums / np.maximum(norms, 1e-300))
        cos = np.einsum("ij,ij->i", dirs, np.repeat(axes, np.diff(starts), axis=0))
        min_cos = np.minimum.reduceat(np.clip(cos, -1.0, 1.0), starts[:-1])
        half = np.where(degenerate, np.pi, np.arccos(min_cos) + 1e-9)
        inverse = np.empty_like(order)
        inverse[order] = np.arange(len(order))
        return RayBundle((H, W), dirs, order, inverse, starts, axes, half)

    @property
    def n_rays(self) -> int:
        return len(self.order)


@dataclass(frozen=True)
class Hits:
    """Ray hits in image order (flattened, N = H * W).

    Attributes
    ----------
    dist : ndarray of shape (N,), metres along the unit ray, NaN = no hit.
    geom_id : ndarray of shape (N,), int32 MuJoCo geom id, -1 = no hit.
    normal_world : ndarray of shape (N, 3) (unit, outward, world frame; NaN where no hit), or None.
    """

    dist: np.ndarray
    geom_id: np.ndarray
    normal_world: np.ndarray | None


class RayCaster:
    """Casts rays against an exported scene (see the module docstring).

    Parameters
    ----------
    exported : the MJCF export of the scene.
    mj_model : its compiled model (compiled from ``exported`` when None). Its ``geom_group`` is
        rewritten while casting and restored afterwards.
    features : the scene's features (a ``SceneModel`` or an iterable of features), used to refine
        mesh hits and give analytic normals; without them mesh geoms keep their facet hits and normals.
    tile_px : tile size for geom culling (0 = no tiling).
    """

    def __init__(self, exported: ExportedScene, mj_model: mujoco.MjModel | None = None,
                 features: Iterable[Feature] | None = None, tile_px: int = 32):
        self.exported = exported
        self.model = exported.load_model() if mj_model is None else mj_model
        if self.model.ngeom != len(exported.geom_names):
            raise ValueError(f"mj_model has {self.model.ngeom} geoms but the export has {len(exported.geom_names)}")
        self.data = mujoco.MjData(self.model)
        mujoco.mj_kinematics(self.model, self.data)
        self.tile_px = int(tile_px)
        feats = getattr(features, "features", features)
        self.features: dict[str, Feature] = {f.id: f for f in feats} if feats is not None else {}
        self.is_mesh = np.asarray(self.model.geom_type == mujoco.mjtGeom.mjGEOM_MESH)
        self.mesh_feature: dict[int, Feature] = {
            g: self.features[name] for g, name in enumerate(exported.geom_names)
            if self.is_mesh[g] and name in self.features}
        self.sphere_centre, self.sphere_radius, self.sphere_starts = self._bounding_spheres()
        self._bundles: dict = {}

    # -- bounding volumes -------------------------------------------------------------------------
    def _bounding_spheres(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Spheres covering each geom's bounding box: centres (S, 3) world, radii (S,), geom boundaries (G + 1,)."""
        centres, radii, starts = [], [], [0]
        aabb = np.asarray(self.model.geom_aabb).reshape(-1, 6)
        xpos = np.asarray(self.data.geom_xpos).reshape(-1, 3)
        xmat = np.asarray(self.data.geom_xmat).reshape(-1, 3, 3)
        for g in range(self.model.ngeom):
            c, h = aabb[g, :3], np.maximum(aabb[g, 3:], 1e-9)
            cell = max(2 * h.min(), 2 * h.max() / _MAX_SPLIT)
            n = np.minimum(np.ceil(2 * h / cell - 1e-9).astype(int), _MAX_SPLIT)
            step = 2 * h / n
            grids = [-h[k] + step[k] * (np.arange(n[k]) + 0.5) for k in range(3)]
            local = np.stack(np.meshgrid(*grids, indexing="ij"), axis=-1).reshape(-1, 3) + c
            centres.append(local @ xmat[g].T + xpos[g])
            radii.append(np.full(len(local), 0.5 * float(np.linalg.norm(step)) * (1 + 1e-9) + 1e-9))
            starts.append(starts[-1] + len(local))
        return np.concatenate(centres), np.concatenate(radii), np.array(starts)

    def bundle(self, directions_key, directions: np.ndarray | None = None) -> RayBundle:
        """The cached :class:`RayBundle` for ``directions_key`` (built from ``directions`` (H, W, 3) the first time)."""
        b = self._bundles.get(directions_key)
        if b is None:
            if directions is None:
                raise KeyError(directions_key)
            b = RayBundle.build(np.asarray(directions, dtype=np.float64), self.tile_px)
            self._bundles[directions_key] = b
        return b

    def tile_geoms(self, origin: np.ndarray, R_world_sensor: np.ndarray, bundle: RayBundle,
                   cutoff: float) -> np.ndarray:
        """Which geoms each tile must test, (T, G) bool (conservative: bounding spheres vs tile cones)."""
        c = matmul_rows(self.sphere_centre - origin, R_world_sensor)  # sensor frame
        D = np.linalg.norm(c, axis=1)
        rho = self.sphere_radius
        inside = D <= rho
        u = c / np.where(D > 0, D, 1.0)[:, None]
        beta = np.arcsin(np.minimum(rho / np.where(D > 0, D, 1.0), 1.0))
        reach = D - rho <= cutoff
        cos_ang = np.minimum(np.maximum(matmul_rows(bundle.axes, u.T), -1.0), 1.0)  # (T, S); np.clip is slower
        ok = (np.arccos(cos_ang) <= bundle.half_angle[:, None] + beta[None, :]) | inside[None, :]
        ok &= reach[None, :]
        return np.logical_or.reduceat(ok, self.sphere_starts[:-1], axis=1)

    # -- casting -------------------------------------------------------------------------------------
    def cast(self, origin: np.ndarray, R_world_sensor: np.ndarray, bundle: RayBundle, cutoff: float,
             normals: bool = True, exclude: np.ndarray | None = None) -> Hits:
        """Cast every ray of ``bundle`` from ``origin`` (world, (3,)) with the sensor rotation (3, 3).

        Returns hits in image order (flattened). ``cutoff`` (metres): geoms whose bounding volume lies
        entirely beyond it are ignored (hits beyond it may still be reported). ``exclude``: (G,) bool, geoms
        the rays pass through.
        """
        origin = np.ascontiguousarray(origin, dtype=np.float64)
        n = bundle.n_rays
        dirs_world = matmul_rows(bundle.dirs, R_world_sensor.T)
        dist = np.empty(n)
        gid = np.empty(n, dtype=np.int32)
        nrm = np.empty((n, 3)) if normals else None
        m, d = self.model, self.data
        groups = m.geom_group
        saved = groups.copy()
        try:
            if len(bundle.starts) == 2 and self.tile_px <= 0:
                if exclude is not None:
                    groups[:] = exclude
                mujoco.mj_multiRay(m, d, origin, dirs_world.ravel(), None if exclude is None else _INCLUDE_GROUP0,
                                   True, -1, gid, dist, None if nrm is None else nrm.ravel(), n, float(cutoff))
            else:
                admit = self.tile_geoms(origin, R_world_sensor, bundle, cutoff)
                if exclude is not None:
                    admit &= ~exclude[None, :]
                for t in range(len(bundle.starts) - 1):
                    a, b = int(bundle.starts[t]), int(bundle.starts[t + 1])
                    sel = admit[t]
                    if not sel.any():
                        dist[a:b] = -1.0
                        gid[a:b] = -1
                        continue
                    groups[:] = ~sel
                    mujoco.mj_multiRay(m, d, origin, dirs_world[a:b].ravel(), _INCLUDE_GROUP0, True, -1,
                                       gid[a:b], dist[a:b], None if nrm is None else nrm[a:b].ravel(), b - a,
                                       float(cutoff))
        finally:
            groups[:] = saved
        miss = gid < 0
        dist[miss] = np.nan
        if nrm is not None:
            nrm[miss] = np.nan
        # back to image order (np.take is several times faster than fancy indexing here)
        inv = bundle.inverse
        return Hits(np.take(dist, inv), np.take(gid, inv), None if nrm is None else np.take(nrm, inv, axis=0))

    def refine_meshes(self, origin: np.ndarray, R_world_sensor: np.ndarray, dirs_sensor: np.ndarray,
                      hits: Hits) -> Hits:
        """Move mesh hits onto the analytic feature surface and replace their normals by analytic ones.

        Parameters
        ----------
        origin : (3,) world; R_world_sensor : (3, 3) sensor rotation.
        dirs_sensor : (N, 3) unit ray directions (sensor frame, image order).
        hits : from :meth:`cast`.
        """
        if not self.mesh_feature:
            return hits
        gid = hits.geom_id
        idx = np.flatnonzero((gid >= 0) & self.is_mesh[np.maximum(gid, 0)])
        if len(idx) == 0:
            return hits
        dist, nrm = hits.dist.copy(), hits.normal_world.copy() if hits.normal_world is not None else None
        order = np.argsort(gid[idx], kind="stable")
        idx = idx[order]
        g_sorted = gid[idx]
        bounds = np.flatnonzero(np.diff(g_sorted)) + 1
        for group in np.split(idx, bounds):
            feature = self.mesh_feature.get(int(gid[group[0]]))
            if feature is None:
                continue
            t, n = refine_on_feature(feature, origin, matmul_rows(dirs_sensor[group], R_world_sensor.T),
                                     dist[group])
            dist[group] = t
            if nrm is not None:
                nrm[group] = n
        return Hits(dist, gid, nrm)

    # -- free space ------------------------------------------------------------------------------------
    def _from_point(self, point: np.ndarray, n_dirs: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays from ``point`` over the sphere: (geom ids, distances, whether each hit is from inside a
        primitive geom)."""
        p = np.ascontiguousarray(point, dtype=np.float64)
        dirs = fibonacci_sphere(n_dirs)
        gid = np.empty(n_dirs, dtype=np.int32)
        dist = np.empty(n_dirs)
        nrm = np.empty(3 * n_dirs)
        mujoco.mj_multiRay(self.model, self.data, p, dirs.ravel(), None, True, -1, gid, dist, nrm, n_dirs, 1e6)
        hit = gid >= 0
        facing = np.einsum("ij,ij->i", nrm.reshape(-1, 3), dirs)
        return gid, np.where(hit, dist, np.inf), hit & (facing > 1e-6) & ~self.is_mesh[np.maximum(gid, 0)]

    def containing(self, point: np.ndarray, n_dirs: int = 162) -> np.ndarray:
        """Geoms whose solid contains ``point`` (world, (3,)), as a (G,) bool mask: primitives that rays from
        the point hit from inside, mesh features by their own inside test. Only geoms whose bounding spheres
        hold the point are tested (none, the usual case for a sensor in free space: no rays are cast)."""
        p = np.asarray(point, dtype=np.float64)
        near = np.logical_or.reduceat(np.linalg.norm(self.sphere_centre - p, axis=1) <= self.sphere_radius,
                                      self.sphere_starts[:-1])
        out = np.zeros(self.model.ngeom, dtype=bool)
        if not near.any():
            return out
        gid, _, from_inside = self._from_point(p, n_dirs)
        out[gid[from_inside]] = True
        for g, feature in self.mesh_feature.items():
            if near[g] and inside_solid(feature, p[None, :])[0]:
                out[g] = True
        return out & near

    def probe(self, point: np.ndarray, n_dirs: int = 162) -> tuple[float, str | None]:
        """Clearance and containment at ``point`` (world, (3,)).

        Returns ``(clearance, inside)``: the shortest hit distance over ``n_dirs`` directions spread over
        the sphere (metres, inf if nothing is hit) and the name of the geom or feature containing the point
        (None when in free space).
        """
        gid, dist, from_inside = self._from_point(point, n_dirs)
        if from_inside.any():
            return 0.0, self.exported.geom_names[int(gid[np.flatnonzero(from_inside)[0]])]
        p = np.asarray(point, dtype=np.float64)[None, :]
        for feature in self.mesh_feature.values():
            if inside_solid(feature, p)[0]:
                return 0.0, feature.id
        return float(dist.min()), None


def matmul_rows(a: np.ndarray, b: np.ndarray, max_elements: int = 32768) -> np.ndarray:
    """``a @ b`` for a tall ``a`` (N, k) and a small ``b`` (k, m), computed in row blocks.

    Blocks keep OpenBLAS single-threaded: its threaded small-matrix product can take 100x longer on a
    busy machine (measured: 0.6 ms vs 115 ms for (307200, 3) @ (3, 3)). The result does not depend on
    the machine's load, and is deterministic.
    """
    out = np.empty((a.shape[0], b.shape[1]))
    chunk = max(1, max_elements // max(1, b.size))
    for i in range(0, a.shape[0], chunk):
        np.matmul(a[i:i + chunk], b, out=out[i:i + chunk])
    return out


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` unit vectors spread evenly over the sphere, shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def feature_normals(feature: Feature, points: np.ndarray) -> np.ndarray:
    """Outward unit normals of ``feature``'s surface at (or near) ``points`` (N, 3), world frame."""
    p = np.asarray(points, dtype=np.float64)
    if isinstance(feature, Plane):
        return np.broadcast_to(feature.normal, p.shape).copy()
    if isinstance(feature, Sphere):
        return _unit(p - feature.centre)
    if isinstance(feature, Cylinder | Cone | Torus):
        base = feature.apex if isinstance(feature, Cone) else feature.centre
        w = p - base
        h = w @ feature.axis
        radial = _unit(w - h[:, None] * feature.axis)
        if isinstance(feature, Cylinder):
            return radial
        if isinstance(feature, Cone):
            return radial * math.cos(feature.half_angle) - feature.axis * math.sin(feature.half_angle)
        return _unit(p - (feature.centre + feature.major_radius * radial))
    eps = 1e-6 * feature.size()  # any other feature type: numerical gradient
    grad = np.stack([(feature.signed_distance(p + eps * e) - feature.signed_distance(p - eps * e)) / (2 * eps)
                     for e in np.eye(3)], axis=1)
    return _unit(grad)


def refine_on_feature(feature: Feature, origin: np.ndarray, dirs: np.ndarray, t: np.ndarray,
                      iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Newton steps along each ray onto the feature's implicit surface.

    Parameters
    ----------
    feature : the analytic feature the rays hit (its mesh).
    origin : (3,) world; dirs : (N, 3) unit directions; t : (N,) hit distances on the mesh (metres).

    Returns
    -------
    (t, normals) : refined distances (N,) and analytic unit normals (N, 3). A ray whose refinement does
    not reduce the surface distance, or moves farther than 1 % of the feature size, keeps its mesh hit.
    """
    t0 = t.copy()
    cur = t.copy()
    limit = 0.01 * feature.size()
    for _ in range(iterations):
        p = origin + cur[:, None] * dirs
        f = feature.signed_distance(p)
        n = feature_normals(feature, p)
        slope = np.einsum("ij,ij->i", n, dirs)
        step = np.divide(f, slope, out=np.zeros_like(f), where=np.abs(slope) > 1e-6)
        cur = cur - step
    p = origin + cur[:, None] * dirs
    f_new = np.abs(feature.signed_distance(p))
    f_old = np.abs(feature.signed_distance(origin + t0[:, None] * dirs))
    bad = ~np.isfinite(cur) | (np.abs(cur - t0) > limit) | (f_new > f_old)
    cur[bad] = t0[bad]
    p = origin + cur[:, None] * dirs
    return cur, feature_normals(feature, p)


def inside_solid(feature: Feature, points: np.ndarray) -> np.ndarray:
    """Whether ``points`` (N, 3) lie strictly inside the solid bounded by ``feature`` (planes: never)."""
    p = np.asarray(points, dtype=np.float64)
    if isinstance(feature, Plane):
        return np.zeros(len(p), dtype=bool)
    if isinstance(feature, Sphere):
        w = p - feature.centre
        ins = np.linalg.norm(w, axis=1) < feature.radius
        if feature.cap_axis is not None:
            ins &= w @ feature.cap_axis > feature.radius - feature.cap_height
        return ins
    if isinstance(feature, Cylinder):
        w = p - feature.centre
        h = w @ feature.axis
        return (np.abs(h) < feature.length / 2) & (feature.signed_distance(p) < 0)
    if isinstance(feature, Cone):
        h = (p - feature.apex) @ feature.axis
        return (h > feature.start) & (h < feature.end) & (feature.signed_distance(p) < 0)
    if isinstance(feature, Torus):
        w = p - feature.centre
        e2 = np.cross(feature.axis, feature.start)
        ang = np.mod(np.arctan2(w @ e2, w @ feature.start), 2 * np.pi)
        return (ang <= feature.sweep) & (feature.signed_distance(p) < 0)
    return feature.signed_distance(p) < 0


def surface_of_hits(exported: ExportedScene, geom_ids: np.ndarray, normals_world: np.ndarray) -> np.ndarray:
    """Truth surface index per hit, (N,) int32 (-1 = no hit); same result as
    ``ExportedScene.surface_of_hits`` without its per-hit (3, 3) gather (about 8x faster).

    Parameters
    ----------
    exported : the scene export; geom_ids : (N,) int (-1 = none); normals_world : (N, 3) hit normals (world).
    """
    g = np.asarray(geom_ids)
    out = np.full(g.shape, -1, dtype=np.int32)
    hit = np.flatnonzero(g >= 0)
    gh = g[hit]
    kind = exported.geom_kind[gh]
    col = np.zeros(len(hit), dtype=np.int64)
    cyl = np.flatnonzero(kind == GEOM_CYLINDER)
    if len(cyl):
        nz = np.einsum("ij,ij->i", exported.geom_frame[gh[cyl], :, 2], normals_world[hit[cyl]])
        col[cyl] = np.where(nz > 0.5, 2, np.where(nz < -0.5, 1, 0))
    box = np.flatnonzero(kind == GEOM_BOX)
    if len(box):
        nb = normals_world[hit[box]]
        frames = exported.geom_frame[gh[box]]
        local = np.stack([np.einsum("ij,ij->i", frames[:, :, k], nb) for k in range(3)], axis=1)
        k = np.argmax(np.abs(local), axis=1)
        col[box] = 2 * k + (local[np.arange(len(k)), k] < 0)
    out[hit] = exported.geom_surface[gh, col]
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.divide(v, n, out=np.zeros_like(v), where=n > 0)


__all__ = ["RayCaster", "RayBundle", "Hits", "feature_normals", "refine_on_feature", "inside_solid",
           "fibonacci_sphere", "matmul_rows", "surface_of_hits"]
