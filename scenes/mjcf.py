"""MJCF export of a scene model, and the map from a ray hit back to the truth surface it landed on.

One geom per feature, named by the feature id, all in the world body (ray casting is much
slower through bodies, DESIGN 5). Exact native geoms where MuJoCo has them:

* ``Plane`` -> a thin box whose front face is the rectangle; a closed six-plane box object
  (a cabinet) -> one box geom, its faces recovered from the hit normal;
* ``Cylinder`` -> a cylinder geom (its side and two caps are distinct truth surfaces);
* ``Sphere`` -> a sphere geom (a hemispherical tank end closed by its tank's cylinder, too);
* ``Cone`` frusta, ``Torus`` sections and other spherical caps -> triangle meshes fine enough that
  the surface error stays below ``mesh_tolerance`` (default 1e-4 m per metre of feature size).

Meshes are embedded in the XML, so the file is self-contained: ``python -m mujoco.viewer --mjcf scene.xml``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.geometry import frame_from_z
from scenes.model import Object, SceneModel

PLANE_THICKNESS = 0.002  # metres, depth of the thin box behind an exported Plane
MESH_TOLERANCE = 1e-4  # metres of surface error per metre of feature size

GEOM_SINGLE, GEOM_CYLINDER, GEOM_BOX = 0, 1, 2


@dataclass(frozen=True)
class Surface:
    """One truth surface: a part of a feature (a plane face, a cylinder side or cap, a sphere...)."""

    index: int
    feature_id: str
    part: str
    truth_class: str


@dataclass(frozen=True)
class ExportedScene:
    """MJCF text plus what is needed to map ray hits (geom id, world normal) to truth surfaces.

    Attributes
    ----------
    xml : the MJCF document.
    surfaces : every truth surface; ``surfaces[i].index == i``.
    geom_kind : (G,) int, how a hit on geom g maps to a surface (single, cylinder side/caps, box faces).
    geom_surface : (G, 6) int, surface indices per geom (column 0 for single geoms; side, cap_start,
        cap_end for cylinders; faces +x, -x, +y, -y, +z, -z of the geom frame for boxes; -1 unused).
    geom_frame : (G, 3, 3) float, world rotation of each geom's local frame (columns = axes).
    geom_names : names of the geoms in MuJoCo's order (the feature id, or the object id for a box).
    mesh_error : dict feature id -> maximum surface error of its mesh in metres (measured on the mesh).
    """

    xml: str
    surfaces: tuple[Surface, ...]
    geom_kind: np.ndarray
    geom_surface: np.ndarray
    geom_frame: np.ndarray
    geom_names: tuple[str, ...]
    mesh_error: dict[str, float]

    def save(self, path: str | Path) -> None:
        Path(path).write_text(self.xml, encoding="utf-8")

    def surface_of_hits(self, geom_ids: np.ndarray, normals_world: np.ndarray) -> np.ndarray:
        """Truth surface index of each ray hit (-1 for no hit).

        Parameters
        ----------
        geom_ids : ndarray of shape (N,), int, MuJoCo geom id (-1 = no hit).
        normals_world : ndarray of shape (N, 3), the hit normals in the world frame.
        """
        geom_ids = np.asarray(geom_ids)
        out = np.full(geom_ids.shape, -1, dtype=np.int32)
        hit = geom_ids >= 0
        g = geom_ids[hit]
        n_local = np.einsum("nji,nj->ni", self.geom_frame[g], normals_world[hit])  # R' n
        kind = self.geom_kind[g]
        col = np.zeros(len(g), dtype=np.int64)
        cyl = kind == GEOM_CYLINDER
        nz = n_local[cyl, 2]
        col[cyl] = np.where(nz > 0.5, 2, np.where(nz < -0.5, 1, 0))
        box = kind == GEOM_BOX
        nb = n_local[box]
        k = np.argmax(np.abs(nb), axis=1)
        sign_neg = nb[np.arange(len(k)), k] < 0
        col[box] = 2 * k + sign_neg
        out[hit] = self.geom_surface[g, col]
        return out

    def load_model(self):
        """The compiled ``mujoco.MjModel`` of this scene."""
        import mujoco

        return mujoco.MjModel.from_xml_string(self.xml)


def _fmt(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in np.ravel(values))


def _quat(R: np.ndarray) -> str:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return _fmt([w, x, y, z])


def _segments(radius: float, tolerance: float, angle: float = 2 * math.pi) -> int:
    """Chords needed so a circle arc of ``radius`` is approximated within ``tolerance`` (sagitta)."""
    c = 1.0 - min(tolerance / radius, 1.0)
    step = 2.0 * math.acos(c)
    return max(3, math.ceil(angle / step))


def box_of_planes(planes: tuple[Feature, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]] | None:
    """``(centre, R, half, order)`` when six planes are exactly the outward faces of a box, else None.

    ``R``'s columns are the box axes, ``half`` its half extents; ``order[k]`` is the index of the plane on
    face k, faces ordered as the box decoding expects (+x, -x, +y, -y, +z, -z of the box frame).
    """
    if len(planes) != 6 or not all(isinstance(p, Plane) for p in planes):
        return None
    normals = np.array([p.normal for p in planes])
    centre = np.mean([p.centre for p in planes], axis=0)
    axes: list[np.ndarray] = []
    order: list[int] = []
    half: list[float] = []
    used: set[int] = set()
    for i in range(6):
        if i in used:
            continue
        opp = [j for j in range(6) if j not in used and j != i and np.dot(normals[i], normals[j]) < -1 + 1e-9]
        if len(opp) != 1:
            return None
        j = opp[0]
        used |= {i, j}
        d_i = float(np.dot(planes[i].centre - centre, normals[i]))
        d_j = float(np.dot(planes[j].centre - centre, normals[j]))
        if d_i <= 0 or abs(d_i - d_j) > 1e-9:
            return None
        axes.append(normals[i])
        order += [i, j]
        half.append(d_i)
    R = np.column_stack(axes)
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-9):
        return None
    if np.linalg.det(R) < 0:
        R[:, 2] *= -1
        order[4], order[5] = order[5], order[4]
    for k in range(3):  # every face must span the full box side
        for idx in order[2 * k: 2 * k + 2]:
            p = planes[idx]
            if not np.allclose(np.abs(p.centre - centre - np.dot(p.centre - centre, R[:, k]) * R[:, k]), 0, atol=1e-9):
                return None
            a, b = (k + 1) % 3, (k + 2) % 3
            want = sorted((half[a], half[b]))
            if not np.allclose(sorted(p.half_size), want, atol=1e-9):
                return None
    return centre, R, np.array(half), order


def _hemisphere_closed_by(sphere: Sphere, obj: Object) -> bool:
    """True when ``sphere`` is a hemisphere whose open side is enclosed by a same-radius cylinder
    of its object (a tank end): then exporting the full sphere is exact for what can be seen."""
    if not sphere.is_cap or abs(sphere.cap_height - sphere.radius) > 1e-12:
        return False
    for f in obj.features:
        if isinstance(f, Cylinder) and abs(f.radius - sphere.radius) < 1e-12 and f.length >= sphere.radius:
            for sign, end in ((-1.0, f.endpoints()[0]), (1.0, f.endpoints()[1])):
                if np.allclose(end, sphere.centre, atol=1e-9) and np.allclose(sphere.cap_axis, sign * f.axis,
                                                                                atol=1e-9):
                    return True
    return False


def feature_mesh(feature: Feature, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh ``(vertices (V, 3), faces (F, 3))`` of a curved feature, outward-wound,
    with surface error at most ``tolerance`` metres."""
    if isinstance(feature, Torus):
        R, r = feature.major_radius, feature.minor_radius
        n_t = _segments(R + r, tolerance / 2, feature.sweep)
        n_p = _segments(r, tolerance / 2)
        t = np.linspace(0.0, feature.sweep, n_t + 1)
        psi = np.linspace(0.0, 2 * np.pi, n_p, endpoint=False)
        e1, e2, a = feature.start, np.cross(feature.axis, feature.start), feature.axis
        T, P = np.meshgrid(t, psi, indexing="ij")
        radial = np.cos(T)[..., None] * e1 + np.sin(T)[..., None] * e2
        V = feature.centre + (R + r * np.cos(P))[..., None] * radial + (r * np.sin(P))[..., None] * a
        return V.reshape(-1, 3), _grid_faces(n_t + 1, n_p, wrap=True)
    if isinstance(feature, Cone):
        n_p = _segments(float(feature.radius_at(feature.end)), tolerance)
        phi = np.linspace(0.0, 2 * np.pi, n_p, endpoint=False)
        Rf = frame_from_z(feature.axis)
        radial = np.cos(phi)[:, None] * Rf[:, 0] + np.sin(phi)[:, None] * Rf[:, 1]
        rings = [feature.apex + d * feature.axis + feature.radius_at(d) * radial
                 for d in (feature.start, feature.end)]
        return np.concatenate(rings), _grid_faces(2, n_p, wrap=True)
    if isinstance(feature, Sphere):
        axis = feature.cap_axis if feature.cap_axis is not None else np.array([0.0, 0.0, 1.0])
        height = feature.cap_height if feature.cap_axis is not None else 2 * feature.radius
        theta_max = math.acos(max(-1.0, 1.0 - height / feature.radius))
        n_th = _segments(feature.radius, tolerance / 2, theta_max)
        n_p = _segments(feature.radius, tolerance / 2)
        theta = np.linspace(0.0, theta_max, n_th + 1)[1:]
        phi = np.linspace(0.0, 2 * np.pi, n_p, endpoint=False)
        Rf = frame_from_z(axis)
        Th, Ph = np.meshgrid(theta, phi, indexing="ij")
        d = (np.sin(Th) * np.cos(Ph))[..., None] * Rf[:, 0] + (np.sin(Th) * np.sin(Ph))[..., None] * Rf[:, 1] \
            + np.cos(Th)[..., None] * Rf[:, 2]
        pole = feature.centre + feature.radius * axis
        V = np.concatenate([[pole], (feature.centre + feature.radius * d).reshape(-1, 3)])
        top = np.array([[0, 1 + j, 1 + (j + 1) % n_p] for j in range(n_p)])
        return V, np.concatenate([top, 1 + _grid_faces(n_th, n_p, wrap=True)])
    raise TypeError(f"no mesh for feature type {type(feature).__name__}")


def _grid_faces(n_rows: int, n_cols: int, wrap: bool) -> np.ndarray:
    """Two triangles per cell of a (n_rows, n_cols) vertex grid (row-major), columns wrapping around."""
    i, j = np.meshgrid(np.arange(n_rows - 1), np.arange(n_cols if wrap else n_cols - 1), indexing="ij")
    a = i * n_cols + j
    b = i * n_cols + (j + 1) % n_cols
    c = a + n_cols
    d = b + n_cols
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])


def orient_outward(feature: Feature, V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Flip faces whose winding normal disagrees with the feature's outward normal (MuJoCo culls back faces)."""
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(axis=1)
    eps = 1e-6 * feature.size()
    outward = feature.signed_distance(c + eps * _unit_rows(n)) > feature.signed_distance(c - eps * _unit_rows(n))
    F = F.copy()
    F[~outward] = F[~outward][:, ::-1]
    return F


def _unit_rows(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def mesh_surface_error(feature: Feature, V: np.ndarray, F: np.ndarray, samples_per_face: int = 4,
                       rng: np.random.Generator | None = None) -> float:
    """Largest |signed distance| to the feature's surface over vertices, edge midpoints, centroids
    and random points of the mesh triangles (metres)."""
    rng = rng or np.random.default_rng(0)
    tri = V[F]
    pts = [V, tri.mean(axis=1), (tri[:, 0] + tri[:, 1]) / 2, (tri[:, 1] + tri[:, 2]) / 2, (tri[:, 2] + tri[:, 0]) / 2]
    for _ in range(samples_per_face):
        w = rng.dirichlet(np.ones(3), size=len(F))
        pts.append(np.einsum("fk,fkd->fd", w, tri))
    return float(np.max(np.abs(feature.signed_distance(np.concatenate(pts)))))


def export_mjcf(model: SceneModel, mesh_tolerance: float = MESH_TOLERANCE,
                measure_mesh_error: bool = False) -> ExportedScene:
    """Export ``model`` to MJCF (see the module docstring).

    Parameters
    ----------
    model : the scene.
    mesh_tolerance : allowed mesh surface error per metre of feature size (``Feature.size``).
    measure_mesh_error : also measure each mesh's actual surface error (slower; for tests and reports).
    """
    if not mesh_tolerance > 0:
        raise ValueError(f"mesh_tolerance must be > 0, got {mesh_tolerance}")
    surfaces: list[Surface] = []
    geoms: list[str] = []
    meshes: list[str] = []
    kinds: list[int] = []
    table: list[list[int]] = []
    frames: list[np.ndarray] = []
    names: list[str] = []
    mesh_error: dict[str, float] = {}

    def add_surfaces(feature: Feature) -> list[int]:
        first = len(surfaces)
        for part, cls in zip(feature.parts, feature.part_classes, strict=True):
            surfaces.append(Surface(len(surfaces), feature.id, part, cls))
        return list(range(first, len(surfaces)))

    def add_geom(name: str, kind: int, surf: list[int], R: np.ndarray, attrs: str) -> None:
        geoms.append(f'    <geom name="{name}" {attrs} quat="{_quat(R)}" contype="0" conaffinity="0" '
                     f'rgba="{_rgba(name)}"/>')
        kinds.append(kind)
        table.append(surf + [-1] * (6 - len(surf)))
        frames.append(R)
        names.append(name)

    for obj in model.objects:
        box = box_of_planes(obj.features) if obj.kind in ("cabinet", "wall", "structure") else None
        if box is not None:
            centre, R, half, order = box
            surf = [add_surfaces(f)[0] for f in obj.features]
            face_surface = [surf[order[pos]] for pos in range(6)]
            add_geom(obj.id, GEOM_BOX, face_surface, R, f'type="box" size="{_fmt(half)}" pos="{_fmt(centre)}"')
            continue
        for f in obj.features:
            surf = add_surfaces(f)
            tol = mesh_tolerance * f.size()
            if isinstance(f, Plane):
                R = np.column_stack([f.u_axis, f.v_axis, f.normal])
                pos = f.centre - f.normal * PLANE_THICKNESS / 2
                size = [f.half_size[0], f.half_size[1], PLANE_THICKNESS / 2]
                add_geom(f.id, GEOM_SINGLE, surf, R, f'type="box" size="{_fmt(size)}" pos="{_fmt(pos)}"')
            elif isinstance(f, Cylinder):
                add_geom(f.id, GEOM_CYLINDER, surf, frame_from_z(f.axis),
                         f'type="cylinder" size="{_fmt([f.radius, f.length / 2])}" pos="{_fmt(f.centre)}"')
            elif isinstance(f, Sphere) and (not f.is_cap or _hemisphere_closed_by(f, obj)):
                add_geom(f.id, GEOM_SINGLE, surf, np.eye(3),
                         f'type="sphere" size="{_fmt([f.radius])}" pos="{_fmt(f.centre)}"')
            else:
                V, F = feature_mesh(f, tol)
                F = orient_outward(f, V, F)
                if measure_mesh_error:
                    mesh_error[f.id] = mesh_surface_error(f, V, F)
                mesh_name = f"mesh:{f.id}"
                faces = " ".join(map(str, F.ravel()))
                meshes.append(f'    <mesh name="{mesh_name}" vertex="{_fmt(V)}" face="{faces}"/>')
                # MuJoCo re-centres meshes on their inertial frame; the geom frame is reported by the model.
                add_geom(f.id, GEOM_SINGLE, surf, np.eye(3), f'type="mesh" mesh="{mesh_name}"')
    asset = "\n".join(["  <asset>", *meshes, "  </asset>"]) if meshes else ""
    xml = "\n".join([
        f'<mujoco model="{_xml_escape(model.name)}">',
        '  <compiler angle="radian"/>',
        '  <visual><global offwidth="1280" offheight="960"/></visual>',
        asset,
        "  <worldbody>",
        '    <light pos="0 0 20" dir="0 0 -1" directional="true"/>',
        *geoms,
        "  </worldbody>",
        "</mujoco>",
        "",
    ])
    return ExportedScene(xml, tuple(surfaces), np.array(kinds, dtype=np.int32),
                         np.array(table, dtype=np.int32).reshape(-1, 6),
                         np.array(frames, dtype=np.float64).reshape(-1, 3, 3), tuple(names), mesh_error)


def _xml_escape(s: str) -> str:
    return s.replace("&", "&amp;").replace('"', "&quot;").replace("<", "&lt;")


def _rgba(name: str) -> str:
    h = (sum(ord(c) * 31**i for i, c in enumerate(name)) % 997) / 997.0
    r, g, b = 0.45 + 0.4 * h, 0.5 + 0.3 * (1 - h), 0.55
    return _fmt([r, g, b, 1.0])


__all__ = ["Surface", "ExportedScene", "export_mjcf", "feature_mesh", "mesh_surface_error", "box_of_planes",
           "orient_outward", "PLANE_THICKNESS", "MESH_TOLERANCE"]
