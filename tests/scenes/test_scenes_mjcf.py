"""MJCF export: MuJoCo ray casts land on the analytic surfaces, and hits map to the right truth surface."""

import math

import mujoco
import numpy as np
import pytest

from scenes import builders
from scenes.features import Cone, Cylinder, Plane, Sphere, Torus
from scenes.geometry import rotation_about, unit
from scenes.mjcf import MESH_TOLERANCE, box_of_planes, export_mjcf, feature_mesh, mesh_surface_error, orient_outward
from scenes.model import Object, SceneModel


def _cast(exported, origins, directions):
    """Ray casts one by one with mj_ray (origins differ); returns geom ids, distances and world normals."""
    m = exported.load_model()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    gids, dists, normals = [], [], []
    for o, v in zip(origins, directions, strict=True):
        g = np.zeros(1, np.int32)
        n = np.zeros(3)
        dist = mujoco.mj_ray(m, d, o, v, None, 1, -1, g, n)
        gids.append(g[0]), dists.append(dist), normals.append(n)
    return np.array(gids), np.array(dists), np.array(normals)


def _rays_at(feature, n, rng, standoff=2.0):
    """Rays aimed at random surface samples from outside along their normals (slightly tilted)."""
    pts, normals = feature.sample(n, rng)
    tilt = unit(normals + 0.3 * rng.normal(size=normals.shape))
    tilt = np.where((tilt * normals).sum(1, keepdims=True) > 0.3, tilt, normals)
    origins = pts + standoff * tilt
    return origins, -tilt, pts


R = rotation_about([1, 2, 3], 0.7)
NATIVE = [
    Plane("plane", centre=[0.3, -0.2, 0.5], normal=R[:, 2], u_axis=R[:, 0], half_size=(0.6, 0.4)),
    Cylinder("cyl", centre=[0.1, 0.2, 0.3], axis=R[:, 1], radius=0.25, length=1.2),
    Sphere("sph", centre=[-0.3, 0.4, 1.0], radius=0.35),
]
MESHED = [
    Cone("cone", apex=[0.0, 0.0, 0.0], axis=R[:, 0], half_angle=math.radians(12), start=1.0, end=1.6),
    Torus("torus", centre=[0.2, 0.1, 0.0], axis=R[:, 2], major_radius=0.6, minor_radius=0.12, start=R[:, 0],
          sweep=math.radians(100)),
    Sphere("cap", centre=[0, 0, 0], radius=0.5, cap_axis=R[:, 2], cap_height=0.2),
]


@pytest.mark.parametrize("feature", NATIVE + MESHED, ids=lambda f: f.id)
def test_ray_hits_lie_on_the_analytic_surface(feature):
    exported = export_mjcf(SceneModel("t", (Object("o", "structure", (feature,)),)))
    rng = np.random.default_rng(0)
    origins, dirs, targets = _rays_at(feature, 300, rng)
    gids, dists, normals = _cast(exported, origins, dirs)
    hit = gids >= 0
    assert hit.mean() > 0.97
    hits = origins[hit] + dists[hit, None] * dirs[hit]
    err = np.abs(feature.signed_distance(hits))
    tol = 1e-6 if feature in NATIVE else MESH_TOLERANCE * feature.size()
    assert err.max() <= tol, (err.max(), tol)
    surf = exported.surface_of_hits(gids, normals)
    parts = {exported.surfaces[s].part for s in surf[hit]}
    assert parts <= set(feature.parts)
    assert exported.surfaces[surf[hit][0]].feature_id == feature.id


def test_cylinder_caps_and_side_map_to_their_own_surfaces():
    cyl = NATIVE[1]
    exported = export_mjcf(SceneModel("t", (Object("o", "structure", (cyl,)),)))
    a, c = cyl.axis, cyl.centre
    side_dir = unit(np.cross(a, [1.0, 0, 0]))
    origins = np.array([c + 3 * a, c - 3 * a, c + 3 * side_dir])
    dirs = np.array([-a, a, -side_dir])
    gids, dists, normals = _cast(exported, origins, dirs)
    np.testing.assert_allclose(dists, [3 - cyl.length / 2, 3 - cyl.length / 2, 3 - cyl.radius], atol=1e-9)
    surf = exported.surface_of_hits(gids, normals)
    assert [exported.surfaces[s].part for s in surf] == ["cap_end", "cap_start", "side"]
    assert [exported.surfaces[s].truth_class for s in surf] == ["PLAN", "PLAN", "CYL"]


def test_box_cabinet_is_one_geom_whose_faces_map_back():
    cab = builders.cabinet("cab", [1.0, 2.0, 0.0], 0.4, (0.8, 0.5, 1.5))
    assert box_of_planes(cab.features) is not None
    exported = export_mjcf(SceneModel("t", (cab,)))
    assert exported.geom_names == ("cab",)
    rng = np.random.default_rng(1)
    for face in cab.features:
        origins, dirs, _ = _rays_at(face, 20, rng, standoff=1.0)
        gids, dists, normals = _cast(exported, origins, dirs)
        hits = origins + dists[:, None] * dirs
        assert np.abs(face.signed_distance(hits)).max() < 1e-9
        surf = exported.surface_of_hits(gids, normals)
        assert {exported.surfaces[s].feature_id for s in surf} == {face.id}


def test_tank_hemisphere_is_exported_exactly_as_a_native_sphere():
    tank = builders.tank("tank", [0, 0, 0], 0.5, 1.0)
    exported = export_mjcf(SceneModel("t", (tank,)))
    m = exported.load_model()
    assert m.geom_type[1] == mujoco.mjtGeom.mjGEOM_SPHERE
    assert m.nmesh == 0


@pytest.mark.parametrize("feature", MESHED, ids=lambda f: f.id)
def test_mesh_error_is_within_tolerance_and_outward(feature):
    tol = MESH_TOLERANCE * feature.size()
    V, F = feature_mesh(feature, tol)
    F = orient_outward(feature, V, F)
    assert mesh_surface_error(feature, V, F) <= tol
    tri = V[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(axis=1)
    assert np.all(feature.signed_distance(c + 1e-5 * unit(n)) > feature.signed_distance(c))


def test_exported_scenes_load_and_name_geoms_by_feature(tmp_path):
    from scenes.generator import mockup_model

    model = mockup_model()
    exported = export_mjcf(model)
    path = tmp_path / "scene.xml"
    exported.save(path)
    m = mujoco.MjModel.from_xml_path(str(path))
    names = {m.geom(i).name for i in range(m.ngeom)}
    feature_ids = {f.id for f in model.features}
    assert names <= feature_ids | {o.id for o in model.objects}
    assert m.nbody == 1  # every geom sits in the world body (DESIGN 5: bodies slow ray casting)
    assert len(exported.surfaces) == sum(len(f.parts) for f in model.features)
