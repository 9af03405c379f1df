"""Tests of the H-K range-image segmentation (recognition/segmentation/ and its helpers)."""

from __future__ import annotations

from dataclasses import replace

import _support
import _synthetic_range as S  # tests/ is on sys.path under pytest's default import mode
import numpy as np
import pytest
import scipy.ndimage as ndi
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation.hoover import connected_truth_regions, hoover_score
from recognition.fitting import PlaneFit, QuadricSurfaceFit, fit_plane_lsq, fit_quadric_lsq, ray_residuals
from recognition.segmentation import (
    EdgeType,
    SegmentationParams,
    SurfaceType,
    segment,
)
from recognition.segmentation import derivatives as D

CAM = S.Camera(120, 160, 150.0)
NOISE_FREE_SIGMA = 3e-4  # declared sigma for exact images (sets the zero thresholds)


def _seg(surfaces, sigma=0.0, camera=CAM, seed=0, declared=None, params=None):
    pts, sig, ids = S.render(surfaces, camera, sigma, np.random.default_rng(seed))
    declared = NOISE_FREE_SIGMA if declared is None else declared
    sig_in = np.where(np.isfinite(sig), declared, np.nan)
    return segment(pts, sig_in, params), pts, ids


def _interior(ids, sid, seg, margin=4):
    m = ndi.binary_erosion(ids == sid, iterations=margin)
    return m & (seg.edges == 0) & np.isfinite(seg.H)


def _local(pts, origin, axis):
    R = S.frame(axis)
    return (pts - np.asarray(origin, float)) @ R


def _assert_close(est, exp, rel=0.03, rel90=0.10, abs_tol=1e-9):
    err = np.abs(est - exp) / np.maximum(np.abs(exp), abs_tol)
    assert np.median(err) < rel, np.median(err)
    assert np.percentile(err, 90) < rel90, np.percentile(err, 90)


# ----------------------------------------------------------------------------------- analytic curvature


def test_plane_noise_free():
    seg, pts, ids = _seg([S.plane([0, 0, 2.0], [0.3, -0.2, -1.0], 1)])
    m = _interior(ids, 1, seg)
    assert np.abs(seg.H[m]).max() < 1e-6 and np.abs(seg.K[m]).max() < 1e-9
    assert np.mean(seg.hk_class[m] == SurfaceType.PLANAR) > 0.99
    assert seg.n_patches == 1
    p = seg.patches[0]
    assert p.surface_type == SurfaceType.PLANAR and isinstance(p.fit, PlaneFit)
    n_true = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    assert np.allclose(p.fit.normal, n_true, atol=1e-9)  # faces the sensor
    assert p.fit.offset == pytest.approx(2.0 * n_true[2], abs=1e-9)
    assert not p.small and not p.noisy


def test_sphere_noise_free():
    r = 0.5
    seg, pts, ids = _seg([S.sphere([0, 0, 2.0], r, 1)])
    m = _interior(ids, 1, seg)
    _assert_close(seg.H[m], np.full(m.sum(), -1 / r))
    _assert_close(seg.K[m], np.full(m.sum(), 1 / r**2))
    assert np.mean(seg.hk_class[m] == SurfaceType.ELLIPTIC) > 0.99
    big = seg.patches[0]
    assert big.surface_type == SurfaceType.ELLIPTIC and isinstance(big.fit, QuadricSurfaceFit)
    # the quadric is the sphere: A proportional to I, centre (0, 0, 2)
    A, b = big.fit.A, big.fit.b
    assert np.allclose(A / A[0, 0], np.eye(3), atol=1e-6)
    assert np.allclose(-0.5 * np.linalg.solve(A, b), [0, 0, 2.0], atol=1e-6)


def test_cylinder_noise_free():
    r = 0.3
    seg, pts, ids = _seg([S.cylinder([0, 0, 2.0], [0, 1, 0.2], r, 3.0, 1)])
    m = _interior(ids, 1, seg)
    _assert_close(seg.H[m], np.full(m.sum(), -1 / (2 * r)))
    assert np.percentile(np.abs(seg.K[m]), 90) < 0.01 / r**2
    assert np.mean(seg.hk_class[m] == SurfaceType.CYLINDRICAL) > 0.95
    assert seg.patches[0].surface_type == SurfaceType.CYLINDRICAL


def test_cone_noise_free_is_cylindrical():
    alpha = np.deg2rad(20)
    apex, axis = [0, -0.8, 2.2], [0, 1, 0]
    seg, pts, ids = _seg([S.cone(apex, axis, alpha, 0.3, 1.6, 1)])
    m = _interior(ids, 1, seg)
    q = _local(pts[m], apex, axis)
    rho = np.hypot(q[:, 0], q[:, 1])
    _assert_close(seg.H[m], -np.cos(alpha) / (2 * rho))
    assert np.mean(seg.hk_class[m] == SurfaceType.CYLINDRICAL) > 0.95


def test_saddle_noise_free_is_hyperbolic():
    a, origin, axis = 1.0, [0, 0, 2.0], [0, 0, -1.0]
    seg, pts, ids = _seg([S.saddle(origin, axis, a, 0.5, 1)])
    m = _interior(ids, 1, seg)
    q = _local(pts[m], origin, axis)
    w = 1 + 4 * a**2 * (q[:, 0] ** 2 + q[:, 1] ** 2)
    _assert_close(seg.K[m], -4 * a**2 / w**2)
    h_abs = np.abs(4 * a**3 * (q[:, 1] ** 2 - q[:, 0] ** 2) / w**1.5)
    assert np.median(np.abs(np.abs(seg.H[m]) - h_abs)) < 0.03
    assert np.mean(seg.hk_class[m] == SurfaceType.HYPERBOLIC) > 0.95


def test_torus_noise_free_elliptic_outside_hyperbolic_inside():
    R, a, centre, axis = 0.45, 0.15, [0, 0, 2.5], [0, -0.3, -1.0]
    seg, pts, ids = _seg([S.torus(centre, axis, R, a, 1, steps=300)], camera=S.Camera(150, 190, 280.0), declared=1e-4)
    m = _interior(ids, 1, seg, margin=3)
    q = _local(pts[m], centre, axis)
    cphi = (np.hypot(q[:, 0], q[:, 1]) - R) / a
    K_true = cphi / (a * (R + a * cphi))
    H_true = -(R + 2 * a * cphi) / (2 * a * (R + a * cphi))
    _assert_close(seg.H[m], H_true, rel=0.03, rel90=0.12)
    sure = np.abs(cphi) > 0.3
    assert np.mean(np.sign(seg.K[m][sure]) == np.sign(K_true[sure])) > 0.97
    cls = seg.hk_class[m]
    assert np.mean(cls[cphi > 0.3] == SurfaceType.ELLIPTIC) > 0.95
    assert np.mean(cls[cphi < -0.3] == SurfaceType.HYPERBOLIC) > 0.95
    types = {p.surface_type for p in seg.patches if not p.small}
    assert {SurfaceType.ELLIPTIC, SurfaceType.HYPERBOLIC} <= types


# ----------------------------------------------------------------------------------- noise


def test_noisy_plane_and_cylinder_classified_by_noise_thresholds():
    sigma = 5e-4
    seg, pts, ids = _seg(
        [S.plane([0, 0, 2.5], [0, 0, -1.0], 1), S.cylinder([0, 0, 2.0], [0, 1, 0], 0.2, 3.0, 2)],
        sigma=sigma, declared=sigma, seed=3,
    )
    plane = _interior(ids, 1, seg)
    cyl = _interior(ids, 2, seg)
    assert np.mean(seg.hk_class[plane] == SurfaceType.PLANAR) > 0.95
    assert np.mean(seg.hk_class[cyl] == SurfaceType.CYLINDRICAL) > 0.85
    # propagated sigmas are calibrated (Monte Carlo over pixels): H / sigma_H on a plane ~ N(0, 1)
    zH = seg.H[plane] / seg.sigma_H[plane]
    assert 0.75 < np.std(zH) < 1.3
    zK = seg.K[cyl] / seg.sigma_K[cyl]
    assert 0.6 < np.std(zK) < 1.4


def test_multi_part_scene_hoover_perfect():
    cam = S.Camera(240, 320, 290.0)
    sigma = 5e-4
    surfaces = [
        S.plane([0, 0, 4.0], [0, 0, -1.0], 1),
        S.cylinder([-0.6, 0, 3.0], [0, 1, 0], 0.15, 1.2, 2),
        S.sphere([0.4, 0.2, 2.6], 0.25, 3),
        S.plane([0, 0.9, 0], [0, -1, 0], 4),
    ]
    seg, pts, ids = _seg(surfaces, sigma=sigma, camera=cam, declared=sigma, seed=1)
    truth = connected_truth_regions(ids)
    score = hoover_score(seg.labels, truth, 0.8, min_truth_pixels=200)
    assert score.n_truth == 4
    assert score.correct_detection_rate == 1.0, (score.truth_class, score.machine_class)
    by_id = {}
    for sid in (1, 2, 3, 4):
        lab = np.bincount(seg.labels[ids == sid][seg.labels[ids == sid] >= 0]).argmax()
        by_id[sid] = seg.patches[lab]
    assert by_id[1].surface_type == SurfaceType.PLANAR and isinstance(by_id[1].fit, PlaneFit)
    assert np.allclose(by_id[1].fit.normal, [0, 0, -1], atol=2e-3)
    assert by_id[1].fit.offset == pytest.approx(-4.0, abs=2e-3)
    assert by_id[2].surface_type == SurfaceType.CYLINDRICAL
    assert by_id[3].surface_type in (SurfaceType.ELLIPTIC, SurfaceType.CYLINDRICAL)
    for sid in (2, 3):
        assert isinstance(by_id[sid].fit, QuadricSurfaceFit)
    for p in by_id.values():
        assert p.fit.rms_sigma < 1.3 and not p.noisy
    # jump edges separate the objects from the wall
    assert (seg.edges & EdgeType.JUMP).any()
    # patch bookkeeping
    for p in seg.patches:
        assert np.all(seg.labels[p.pixels[:, 0], p.pixels[:, 1]] == p.id)
        assert p.n_pixels == len(p.pixels) == np.sum(seg.labels == p.id)


def test_jump_windows_do_not_cross_the_step():
    surfaces = [S.plane([0, 0, 2.0], [0, 0, -1.0], 1, half_extent=0.4), S.plane([0, 0, 2.6], [0, 0, -1.0], 2)]
    seg, pts, ids = _seg(surfaces, sigma=3e-4, declared=3e-4, seed=2)
    near_step = ndi.binary_dilation(ids == 1, iterations=3) & ~ndi.binary_erosion(ids == 1, iterations=3)
    m = near_step & np.isfinite(seg.H)
    # no fake curvature next to the depth step: the windows exclude the other side
    assert np.mean(seg.hk_class[m] == SurfaceType.PLANAR) > 0.9
    assert np.all((seg.edges[ids == 1] & EdgeType.JUMP)[~ndi.binary_erosion(ids == 1, iterations=1)[ids == 1]])
    score = hoover_score(seg.labels, connected_truth_regions(ids), 0.9)
    assert score.correct_detection_rate == 1.0


def test_crease_between_planes_gives_two_patches():
    # a roof: two planes meeting along a vertical line at x = 0, z = 2
    n1, n2 = np.array([1.0, 0, -1.0]), np.array([-1.0, 0, -1.0])
    s1 = S.Surface(lambda d: _halfplane(d, n1, x_sign=-1), 1)
    s2 = S.Surface(lambda d: _halfplane(d, n2, x_sign=1), 2)
    seg, pts, ids = _seg([s1, s2], sigma=3e-4, declared=3e-4, seed=4)
    score = hoover_score(seg.labels, connected_truth_regions(ids), 0.8)
    assert score.correct_detection_rate == 1.0
    assert (seg.edges & EdgeType.CREASE).any()


def test_fragments_are_dropped_but_small_objects_in_front_stay():
    """_drop_fragments on a hand-made label image (range 2 m; two 10-pixel patches ringed by jumps, one nearer,
    one farther): a 10-pixel patch on the large patch's surface and the one behind its jumps go; the one in
    front of everything around it stays; None keeps all."""
    from recognition.segmentation.peel import _drop_fragments

    labels = np.zeros((20, 30), np.int32)
    rng = np.full(labels.shape, 2.0)
    labels[2:4, 2:7] = 1  # on the big patch's surface
    labels[10:12, 2:7] = 2  # in front: nearer than everything around it, across jumps
    rng[10:12, 2:7] = 1.5
    labels[15:17, 20:25] = 3  # behind: farther than its neighbours
    rng[15:17, 20:25] = 2.5
    jump_h = np.zeros((20, 29), bool)
    jump_v = np.zeros((19, 30), bool)
    for r0, c0 in ((10, 2), (15, 20)):
        jump_h[r0:r0 + 2, c0 - 1] = jump_h[r0:r0 + 2, c0 + 4] = True
        jump_v[r0 - 1, c0:c0 + 5] = jump_v[r0 + 1, c0:c0 + 5] = True
    out = _drop_fragments(labels, SegmentationParams(min_kept_pixels=20), rng, jump_h, jump_v)
    assert set(np.unique(out)) == {-1, 0, 2}
    assert np.all(out[labels == 1] == -1) and np.all(out[labels == 3] == -1) and np.all(out[labels == 2] == 2)
    assert _drop_fragments(labels, SegmentationParams(min_kept_pixels=None), rng, jump_h, jump_v) is labels


def test_border_completion_gives_a_patch_its_border_but_not_the_next_face():
    """A roof's two faces, each labelled but for a band at the crease and two columns at the image border: completion
    gives each face back its own band pixels (within complete_k sigma and face_min_angle_deg of its plane),
    never the other face's; with complete_k None nothing changes."""
    from recognition.segmentation.grid import _neighbour_links, _State
    from recognition.segmentation.reassignment import _complete_borders

    sigma = 1e-3
    n1, n2 = np.array([1.0, 0, -1.0]), np.array([-1.0, 0, -1.0])
    surfaces = [S.Surface(lambda d: _halfplane(d, n1, x_sign=-1), 1),
                S.Surface(lambda d: _halfplane(d, n2, x_sign=1), 2)]
    pts, _, ids = S.render(surfaces, CAM, sigma, np.random.default_rng(3))
    valid = ids > 0
    crease = np.abs(pts[..., 0]) < 0.02
    labels = np.where(valid & ~crease, ids - 1, -1).astype(np.int32)
    labels[:, :2] = -1
    normals = np.where((ids == 1)[..., None], n1 / np.linalg.norm(n1), n2 / np.linalg.norm(n2))
    X = pts.reshape(-1, 3)
    U = X / np.linalg.norm(X, axis=1, keepdims=True)
    # a sigma 5x the noise (as the self-calibration may set it): the other face's first pixels fit within 6 sigma
    st = _State(X=X, U=U, S=np.where(valid.ravel(), 5 * sigma, np.nan), hk=np.ones(X.shape[0], np.int64))
    no_jump_h = np.zeros((CAM.height, CAM.width - 1), bool)
    no_jump_v = np.zeros((CAM.height - 1, CAM.width), bool)
    links = _neighbour_links(valid.shape, valid, no_jump_h, no_jump_v)
    out = _complete_borders(labels, st, SegmentationParams(), links, normals.reshape(-1, 3))
    band = valid & (labels < 0)
    assert band.sum() > 300
    assert np.mean(out[band] >= 0) > 0.95  # the band is given back...
    assert np.all(out[band & (out >= 0)] == ids[band & (out >= 0)] - 1)  # ...each pixel to its own face
    # with the second face unlabelled, the first face's plane fits its pixels near the crease within the noise:
    # the normals alone keep them out (without normals, some go)
    alone = np.where(ids == 1, labels, -1)
    reach = SegmentationParams(complete_rounds=4)  # through the crease band into the other face
    kept = _complete_borders(alone, st, reach, links, normals.reshape(-1, 3))
    assert np.all(kept[ids == 2] == -1)
    blind = _complete_borders(alone, st, reach, links, np.full((X.shape[0], 3), np.nan))
    assert np.any(blind[ids == 2] == 0)
    assert _complete_borders(labels, st, SegmentationParams(complete_k=None), links,
                             normals.reshape(-1, 3)) is labels


def _halfplane(d, n, x_sign):
    n = n / np.linalg.norm(n)
    p0 = np.array([0, 0, 2.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p0 @ n) / (d @ n)
    x = t * d[..., 0]
    return np.where((t > 0) & (x * x_sign >= 0), t, np.inf)


def test_small_patches_are_kept_and_flagged():
    surfaces = [S.plane([0, 0, 3.0], [0, 0, -1.0], 1), S.sphere([0.3, 0.0, 2.5], 0.06, 2)]
    seg, pts, ids = _seg(surfaces, sigma=3e-4, declared=3e-4, seed=5)
    small = [p for p in seg.patches if p.small]
    assert small, "the tiny sphere must give a small patch"
    on_sphere = seg.labels[ids == 2]
    assert np.mean(on_sphere >= 0) > 0.8
    assert all(seg.patches[k].small for k in np.unique(on_sphere[on_sphere >= 0]))


def test_noisy_patches_are_flagged_not_dropped():
    # true noise 10x the declared sigma: the patches remain, flagged noisy
    seg, pts, ids = _seg([S.plane([0, 0, 2.0], [0, 0, -1.0], 1)], sigma=2e-3, declared=2e-4, seed=6)
    assert seg.n_patches >= 1
    assert any(p.noisy for p in seg.patches)
    assert np.mean(seg.labels >= 0) > 0.5


def test_measured_noise_scale_is_reported():
    # true noise 3x the declared sigma on a plane: the calibration measures it (within its median's spread)
    seg, _, _ = _seg([S.plane([0, 0, 2.0], [0, 0, -1.0], 1)], sigma=6e-4, declared=2e-4, seed=8)
    assert seg.noise_scale.shape == seg.labels.shape
    assert np.median(seg.noise_scale) == pytest.approx(3.0, rel=0.15)
    off, _, _ = _seg([S.plane([0, 0, 2.0], [0, 0, -1.0], 1)], sigma=6e-4, declared=2e-4, seed=8,
                     params=SegmentationParams(calibrate_noise=False))
    assert off.noise_scale is None


def test_segmentation_is_deterministic():
    a, _, _ = _seg([S.sphere([0, 0, 2.0], 0.5, 1)], sigma=5e-4, declared=5e-4, seed=7)
    b, _, _ = _seg([S.sphere([0, 0, 2.0], 0.5, 1)], sigma=5e-4, declared=5e-4, seed=7)
    assert np.array_equal(a.labels, b.labels) and np.array_equal(a.hk_class, b.hk_class)


def test_step_times_are_reported_and_change_nothing():
    pts, sig, _ = S.render([S.sphere([0, 0, 2.0], 0.5, 1)], CAM, 5e-4, np.random.default_rng(7))
    steps = {"edges": 1.0}  # times are added to what the dict holds
    timed = segment(pts, sig, steps=steps)
    plain = segment(pts, sig)
    assert np.array_equal(timed.labels, plain.labels)
    # this image is below the coarse grid's size: the grid's steps, then the last three
    assert list(steps) == ["edges", "curvature", "seeds", "growing", "merging", "peel", "border completion",
                           "final fits"]
    assert steps["edges"] >= 1.0 and all(t >= 0 for t in steps.values())


# ----------------------------------------------------------------------------------- inputs and params


@pytest.mark.parametrize(
    "shape, msg",
    [((4, 5), r"expected points of shape \(H, W, 3\), got \(4, 5\)"),
     ((4, 5, 2), r"expected points of shape \(H, W, 3\), got \(4, 5, 2\)"),
     ((0, 5, 3), r"expected points of shape \(H, W, 3\)")],
)
def test_bad_point_shapes(shape, msg):
    with pytest.raises(ValueError, match=msg):
        segment(np.zeros(shape), np.zeros(shape[:2]))


def test_bad_sigma():
    with pytest.raises(ValueError, match="expected sigma of shape"):
        segment(np.ones((4, 5, 3)), np.ones((5, 4)))
    with pytest.raises(ValueError, match="sigma must be >= 0"):
        segment(np.ones((4, 5, 3)), -np.ones((4, 5)))


@pytest.mark.parametrize("shape", [(1, 1), (10, 12), (3, 200)])
def test_empty_images(shape):
    seg = segment(np.full(shape + (3,), np.nan), np.full(shape, np.nan))
    assert seg.n_patches == 0 and np.all(seg.labels == -1) and seg.labels.dtype == np.int32
    assert seg.hk_class.dtype == np.int8 and seg.edges.dtype == np.uint8
    assert seg.H.shape == shape and np.all(np.isnan(seg.K))


def test_one_pixel_image_with_a_return():
    seg = segment(np.array([[[0.0, 0.0, 2.0]]]), np.array([[1e-3]]))
    assert seg.n_patches == 0 and seg.labels.shape == (1, 1)


@pytest.mark.parametrize(
    "kwargs, msg",
    [({"window": 6}, "window must be an odd integer"), ({"window": 1}, "window"), ({"window": -3}, "window"),
     ({"zero_k": 0}, "zero_k"), ({"merge_k": -1.0}, "merge_k"), ({"jump_tan": -1}, "jump_tan"),
     ({"sigma_floor_m": 0}, "sigma_floor_m"), ({"min_patch_pixels": 0}, "min_patch_pixels"),
     ({"connectivity": 6}, "connectivity"), ({"seed_erosion": -1}, "seed_erosion"),
     ({"crease_min_angle": 4.0}, "crease_min_angle"), ({"max_fit_points": 5}, "max_fit_points")],
)
def test_param_validation(kwargs, msg):
    with pytest.raises(ValueError, match=msg):
        SegmentationParams(**kwargs)


def test_params_defaults_and_window_choice():
    p = SegmentationParams()
    assert p.window % 2 == 1 and p.erosion == p.window // 2
    seg, _, ids = _seg([S.sphere([0, 0, 2.0], 0.5, 1)], params=SegmentationParams(window=5))
    m = _interior(ids, 1, seg)
    assert np.median(np.abs(seg.H[m] + 2.0)) < 0.05


# ----------------------------------------------------------------------------------- derivative filters


def test_fast_separable_path_equals_masked_reference():
    pts, sig, ids = S.render([S.sphere([0, 0, 2.0], 0.6, 1)], CAM, 5e-4, np.random.default_rng(8))
    sig = np.where(np.isfinite(sig), 5e-4, np.nan)
    der = D.quadratic_derivatives(pts, sig, 7, 4.0, 5.0)
    assert der.full.sum() > 1000
    H, W = sig.shape
    outs = tuple(np.full((H, W, 3), np.nan) for _ in range(5)) + (
        np.full((H, W), np.nan), np.full((H, W), np.nan), np.full((H, W, 6), np.nan))
    rng = D.norm3(pts)
    valid = np.isfinite(rng)
    D._masked_fits(pts, sig, rng, pts / rng[..., None], valid, der.full, 7, 4.0, 5.0, 9, np.inf, 4096, outs)
    f = der.full
    for fast, slow in zip((der.Pu, der.Pv, der.Puu, der.Puv, der.Pvv), outs[:5], strict=True):
        assert np.allclose(fast[f], slow[f], rtol=1e-7, atol=1e-12)
    assert np.allclose(der.var_u[f], outs[5][f]) and np.allclose(der.cov2[f], outs[7][f], atol=1e-12)


def test_spd_inverse_matches_numpy():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(50, 6, 6))
    M = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(6)
    assert np.allclose(D.spd_inverse(M), np.linalg.inv(M), rtol=1e-8, atol=1e-10)


def test_savgol_kernels_exact_on_quadratics():
    k = D.savgol_kernels(7)
    t = np.arange(-3, 4, dtype=float)
    f = 0.7 + 1.3 * t - 0.4 * t**2
    assert np.dot(k["d1"], f) == pytest.approx(1.3)
    assert np.dot(k["d2"], f) == pytest.approx(-0.4)


# ----------------------------------------------------------------------------------- surface fits


def test_fit_plane_lsq_recovers_and_covariance_matches_monte_carlo():
    rng = np.random.default_rng(1)
    n_true = np.array([0.2, -0.1, -1.0])
    n_true /= np.linalg.norm(n_true)
    uv = rng.uniform(-0.3, 0.3, size=(200, 2))
    base = np.column_stack([uv, np.full(200, 2.0)])
    base[:, 2] = (-1.5 - n_true[0] * base[:, 0] - n_true[1] * base[:, 1]) / n_true[2]
    normals, ds, covs = [], [], []
    for _ in range(300):
        x = base + 1e-3 * rng.standard_normal(base.shape)
        fit = fit_plane_lsq(x)
        normals.append(fit.normal)
        ds.append(fit.offset)
        covs.append(fit.cov)
    normals = np.array(normals)
    assert np.allclose(normals.mean(axis=0), n_true, atol=1e-3)
    assert np.mean(ds) == pytest.approx(-1.5, abs=1e-3)
    emp = np.cov(np.column_stack([normals, ds]).T)
    pred = np.mean(covs, axis=0)
    ratio = np.diag(emp)[[0, 1, 3]] / np.diag(pred)[[0, 1, 3]]
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio


@pytest.mark.parametrize("pts, reason", [(np.zeros((2, 3)), "fewer than 3"),
                                         (np.column_stack([np.arange(5.0)] * 3), "collinear")])
def test_fit_plane_lsq_degenerate(pts, reason):
    fit = fit_plane_lsq(pts)
    assert not fit and reason in fit.reason


def test_fit_quadric_lsq_sphere_and_degenerate():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(400, 3))
    d[:, 2] = -np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = np.array([0.1, 0.0, 3.0]) + 0.4 * d
    fit = fit_quadric_lsq(x, np.full(len(x), 1e-3))
    assert fit.ok and fit.rms_m < 1e-9
    A, b, c = fit.A, fit.b, fit.c
    centre = -0.5 * np.linalg.solve(A, b)
    assert np.allclose(centre, [0.1, 0.0, 3.0], atol=1e-8)
    assert np.sqrt(centre @ A @ centre - c) / np.sqrt(A[0, 0]) == pytest.approx(0.4, abs=1e-8)
    # sign gauge: f > 0 on the sensor side
    assert np.sum(fit.params * np.r_[0, 0, 0, 0, 0, 0, 0, 0, 0, 1.0]) > 0  # f(origin) > 0
    assert np.allclose(fit.cov @ fit.params, 0, atol=1e-12)
    _, ray, z = ray_residuals(fit.params, x + np.array([0, 0, 1e-3]), np.full(len(x), 1e-3))
    assert np.all(np.isfinite(z))
    bad = fit_quadric_lsq(x[:5])
    assert not bad and "fewer than 10" in bad.reason
    with pytest.raises(ValueError, match=r"expected points of shape \(N, 3\)"):
        fit_quadric_lsq(np.zeros((20, 2)))


# ----------------------------------------------------------------------------------- simulated-scan regression


def test_simulated_factory_scan_quality():
    """Hoover correct detection on realistic simulated scans (mixed pixels, outliers, dropouts, incidence-
    dependent noise the core's sigma under-states), VGA so the coarse-grid path runs. Measured 10/15 truth
    regions of >= 200 pixels at T = 0.8 (the segmenter before the simulated-suite work: 7/15)."""
    from evaluation.patches import MIN_TRUTH_PIXELS, TOLERANCE, truth_regions
    from recognition.describe import core_sigma
    from scenes import builders
    from scenes.geometry import look_at
    from scenes.model import SceneModel
    from sensors.config import load_sensor
    from sensors.simulate import Simulator

    scene = SceneModel("seg_regression", (
        builders.floor("floor", 8.0, 6.0),
        builders.wall("wall", (0.0, 2.0, 0.0), 0.0, 8.0, 3.0, 0.2),
        builders.pipe_run("pipe", [[-2.5, 1.3, 1.4], [0.5, 1.3, 1.4]], 0.15, 0.3),
        builders.sphere_tank("tank", (1.4, 0.6, 0.0), 0.5, 0.3),
        builders.cabinet("cab", (-1.0, 0.5, 0.0), 0.4, (0.8, 0.5, 0.9)),
    ))
    sim = Simulator.from_scene(scene)
    config = load_sensor("factory_scanner")
    n_correct = n_truth = 0
    for eye, seed in (([0.3, -3.5, 1.8], 0), ([-0.8, -3.0, 2.2], 1)):
        scan, truth = sim.simulate(config, look_at(eye, [0.0, 1.0, 0.8]), np.random.default_rng(seed))
        assert scan.range.shape == (480, 640)
        seg = segment(scan.points, core_sigma(scan))
        score = hoover_score(seg.labels, truth_regions(truth, scan.valid), TOLERANCE,
                             min_truth_pixels=MIN_TRUTH_PIXELS)
        n_correct += score.n_correct
        n_truth += score.n_truth
    assert n_truth == 15
    assert n_correct >= 9, f"correct detection {n_correct}/{n_truth}"


def test_quick_quadric_fit_of_a_small_piece_of_cylinder_is_within_the_noise():
    # a 12 x 12-pixel tile of a pipe, as merging and seed splitting fit them: the plain algebraic fit
    # (unit-norm eigenvector) is biased on such a small arc (RMS 1.86 sigma here, 7 sigma on the tiles of
    # simulated factory pipes); the Taubin fit normalises by the gradient and stays at the noise (1.00)
    from recognition.segmentation.quick_fits import _quick_fit

    sigma = 5e-4
    pts, sig, ids = S.render([S.cylinder([0, 0, 2.0], [0, 1, 0.2], 0.15, 3.0, 1)], CAM, sigma,
                             np.random.default_rng(3))
    r0, c0 = 54, 74
    tile = pts[r0:r0 + 12, c0:c0 + 12].reshape(-1, 3)
    tile = tile[np.isfinite(tile).all(axis=1)]
    rays = tile / np.linalg.norm(tile, axis=1, keepdims=True)
    _, z = _quick_fit(tile, rays, np.full(len(tile), sigma), planar=False)
    assert len(tile) == 144
    assert np.sqrt(np.mean(z**2)) < 1.5


def test_batched_quick_fits_equal_one_by_one_fits():
    # _fit_groups fits all groups in one numpy pass; each group's fit is the one _quick_fit gives alone
    from recognition.segmentation.grid import _State
    from recognition.segmentation.quick_fits import _quick_fit, _quick_fits

    surfaces = [S.plane([0, 0, 2.5], [0.2, 0, -1.0], 1), S.cylinder([0.3, 0, 2.0], [0, 1, 0.2], 0.2, 3.0, 2)]
    pts, sig, ids = S.render(surfaces, CAM, 5e-4, np.random.default_rng(4))
    X = pts.reshape(-1, 3)
    st = _State(X=X, U=X / np.linalg.norm(X, axis=1, keepdims=True), S=np.full(len(X), 5e-4),
                hk=np.zeros(len(X), np.int64))
    flat = ids.ravel()
    groups = [np.flatnonzero(flat == 1)[::7], np.flatnonzero(flat == 2)[::5], np.flatnonzero(flat == 2)[:60],
              np.flatnonzero(flat == 1)[:5], np.zeros(0, np.int64)]
    for planar in (True, False):
        P, zs = _quick_fits(groups, np.full(len(groups), planar), st)
        for k, idx in enumerate(groups):
            if not planar and k == 0:
                continue  # a quadric through a plane is not unique (any plane pair containing it): no one answer
            if idx.size == 0:
                assert zs[k].size == 0
                continue
            p, z = _quick_fit(X[idx], st.U[idx], st.S[idx], planar)
            np.testing.assert_allclose(zs[k], z, rtol=1e-6, atol=1e-9)
            np.testing.assert_allclose(P[k], p * np.sign(p @ P[k]), rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("angle_deg", [90.0, 150.0, 170.0])
def test_plane_pair_is_recognised_and_other_quadrics_are_not(angle_deg):
    from recognition.fitting import quadric_params
    from recognition.segmentation.quick_fits import _is_plane_pair

    rng = np.random.default_rng(5)
    T = rng.normal(size=3)
    R, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    x = rng.uniform(-0.5, 0.5, size=(200, 3)) @ R.T + T  # points spanning the quadric's neighbourhood

    def moved(A, b, c):
        # the quadric y'Ay + b'y + c = 0 in coordinates y = R'(x - T)
        A2 = R @ A @ R.T
        b2 = R @ b - 2 * A2 @ T
        return quadric_params(A2, b2, float(c + T @ A2 @ T - (R @ b) @ T))

    a = np.deg2rad(angle_deg)
    n1, n2 = np.array([0, 0, 1.0]), np.array([np.sin(a), 0, np.cos(a)])
    pair = moved(0.5 * (np.outer(n1, n2) + np.outer(n2, n1)), np.zeros(3), 0.0)
    assert _is_plane_pair(pair, x, SegmentationParams().plane_pair_tol)
    others = {
        "cylinder": moved(np.diag([1.0, 1.0, 0.0]), np.zeros(3), -0.09),
        "sphere": moved(np.eye(3), np.zeros(3), -0.25),
        "cone": moved(np.diag([1.0, 1.0, -0.3]), np.zeros(3), 0.0),
        "hyperbolic cylinder": moved(np.diag([1.0, -1.0, 0.0]), np.zeros(3), -0.2),
        "saddle": moved(np.diag([1.0, -1.0, 0.0]), np.array([0, 0, 1.0]), 0.0),
        "plane": moved(np.zeros((3, 3)), np.array([0, 0, 1.0]), -0.1),
    }
    for name, p in others.items():
        assert not _is_plane_pair(p, x, SegmentationParams().plane_pair_tol), name


@pytest.mark.parametrize("curved_planar_merge", [True, False])
def test_two_flat_looking_halves_of_a_gentle_cylinder_merge_as_a_quadric(curved_planar_merge):
    # each half of a 3 m radius cylinder seen over 1 m fits a plane within the noise, their union does not:
    # they merge as one quadric only with curved_planar_merge (two faces at a crease never do: plane pair)
    from recognition.segmentation.grid import _State
    from recognition.segmentation.merging import _merge

    sigma = 2e-3
    pts, sig, ids = S.render([S.cylinder([0, 0, 5.0], [0, 1.0, 0], 3.0, 3.0, 1)], CAM, sigma,
                             np.random.default_rng(9))
    valid = ids == 1
    cols = np.flatnonzero(valid.any(axis=0))
    mid = (cols.min() + cols.max()) // 2
    labels = np.where(valid, np.where(np.arange(CAM.width)[None, :] < mid, 0, 1), -1).astype(np.int32)
    X = pts.reshape(-1, 3)
    U = X / np.linalg.norm(X, axis=1, keepdims=True)
    st = _State(X=X, U=U, S=np.where(valid.ravel(), sigma, np.nan), hk=np.ones(X.shape[0], np.int64))
    params = SegmentationParams(curved_planar_merge=curved_planar_merge)
    no_jump_h = np.zeros((CAM.height, CAM.width - 1), bool)
    no_jump_v = np.zeros((CAM.height - 1, CAM.width), bool)
    merged = _merge(labels, st, params, no_jump_h, no_jump_v)
    n_labels = len(np.unique(merged[valid]))
    assert n_labels == (1 if curved_planar_merge else 2)


@pytest.mark.parametrize("roof", [True, False])
def test_a_patch_spanning_two_faces_is_split_along_its_crease(roof):
    """One label over both faces of a roof (a far box's corner reassembled from noisy tiles) is cut in two
    along the crease, each side on its own face; one over a cylinder, which no plane pair fits, is kept."""
    from recognition.segmentation.grid import _State
    from recognition.segmentation.splits import _split_plane_pairs

    sigma = 1e-3
    if roof:
        n1, n2 = np.array([1.0, 0, -1.0]), np.array([-1.0, 0, -1.0])
        surfaces = [S.Surface(lambda d: _halfplane(d, n1, x_sign=-1), 1),
                    S.Surface(lambda d: _halfplane(d, n2, x_sign=1), 2)]
    else:
        surfaces = [S.cylinder([0, 0, 2.0], [0, 1.0, 0], 0.4, 3.0, 1)]
    pts, _, ids = S.render(surfaces, CAM, sigma, np.random.default_rng(3))
    valid = ids > 0
    labels = np.where(valid, 0, -1).astype(np.int32)
    X = pts.reshape(-1, 3)
    U = X / np.linalg.norm(X, axis=1, keepdims=True)
    st = _State(X=X, U=U, S=np.where(valid.ravel(), sigma, np.nan), hk=np.ones(X.shape[0], np.int64))
    out = _split_plane_pairs(labels, st, SegmentationParams())
    if not roof:
        assert out is labels
        return
    assert len(np.unique(out[valid])) == 2
    dominant = []
    for face in (1, 2):
        got, n = np.unique(out[ids == face], return_counts=True)
        assert n.max() >= 0.99 * n.sum(), (face, got, n)
        dominant.append(got[np.argmax(n)])
    assert dominant[0] != dominant[1]


def _pipe_run_points(profile, length: float, sigma: float, seed: int = 0, n: int = 6000):
    """Points and normals of the front half of a surface of revolution about the x axis, radius ``profile(t)``
    for t in [0, length], with radial noise ``sigma``."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, length, n)
    phi = rng.uniform(-1.2, 1.2, n)  # the side facing a sensor on -z
    r = profile(t)
    slope = np.gradient(profile(np.linspace(0, length, 2001)), np.linspace(0, length, 2001))
    dr = np.interp(t, np.linspace(0, length, 2001), slope)
    radial = np.stack([np.zeros(n), np.sin(phi), -np.cos(phi)], axis=1)
    x = np.column_stack([t, np.zeros(n), np.full(n, 3.0)]) + (r + rng.normal(0.0, sigma, n))[:, None] * radial
    normals = radial - dr[:, None] * np.array([1.0, 0.0, 0.0])
    return x, normals / np.linalg.norm(normals, axis=1, keepdims=True)


@pytest.mark.parametrize("shape", ["pipe+reducer", "pipe", "cone"])
def test_a_pipe_and_its_reducer_are_cut_apart_along_the_axis(shape):
    """A pipe (r = 0.1 m, 1.2 m) and a 6 deg reducer merged under 5 mm noise: cut within a slice of the join.
    A pipe or a cone alone is one surface along its axis: never cut."""
    from recognition.segmentation.splits import _axial_pieces

    join, tan = 1.2, np.tan(np.radians(6.0))
    profiles = {"pipe+reducer": lambda t: np.where(t < join, 0.1, 0.1 - (t - join) * tan),
                "pipe": lambda t: np.full_like(t, 0.1), "cone": lambda t: 0.14 - t * tan}
    length = {"pipe+reducer": 1.6, "pipe": 1.2, "cone": 0.8}[shape]
    x, normals = _pipe_run_points(profiles[shape], length, 0.005)
    side = _axial_pieces(x, np.full(len(x), 0.005), normals, 200, SegmentationParams())
    if shape != "pipe+reducer":
        assert side is None
        return
    assert side is not None
    t = x[:, 0]
    reducer = t > join
    wrong = np.mean(side != np.where(reducer, side[np.argmax(t)], side[np.argmin(t)]))
    assert side[np.argmax(t)] != side[np.argmin(t)]
    assert wrong < 0.06  # a slice is half a radius (5 cm): at most about one slice on the wrong side


def test_a_long_pipe_whose_profile_bends_only_at_its_end_is_not_cut():
    """A metal pipe's patch (every third point, float32) from the calibration suite's factory-scanner frame
    s2004-p10-v0, 6.5 m away with specular dropouts: about the normals' axis its profile bends half-way, about
    the fitted cylinder's only over its last points, too few to stand alone. One surface, not cut (it was, at
    full size into 5282 and 2871 pixels)."""
    from recognition.segmentation.splits import _axial_pieces

    z = np.load(_support.DATA / "long_metal_pipe_patch.npz")
    x, s, n = (z[k].astype(np.float64) for k in ("points", "sigma", "normals"))
    assert len(x) == 2718
    assert _axial_pieces(x, s, n, 200, SegmentationParams()) is None


def test_a_far_box_corner_that_no_quadric_fits_is_cut_into_its_faces():
    """Two faces of a far box (12 m, 3 mm noise) meeting at 90 deg, with pixels mixed at the crease: the
    k-planes cut gives each face (one stray face pixel in twenty at most); a face with a parallel layer
    behind it and a noisy pipe seen as a strip are not cut."""
    from recognition.segmentation.grid import _State
    from recognition.segmentation.splits import _faces

    rng = np.random.default_rng(3)
    n = 400
    a, b = rng.uniform(0.0, 0.6, n), rng.uniform(-0.3, 0.3, n)
    top = np.column_stack([a * 0.7, b, np.full(n, 12.0) - a * 0.7])  # two faces meeting at the crease x = 0
    side = np.column_stack([-a * 0.7, b, np.full(n, 12.0) - a * 0.7])
    x = np.concatenate([top, side])
    u = x / np.linalg.norm(x, axis=1, keepdims=True)
    x = x + u * rng.normal(0.0, 0.003, len(x))[:, None]
    mixed = np.abs(x[:, 0]) < 0.02
    x[mixed] += u[mixed] * rng.uniform(0.0, 0.05, mixed.sum())[:, None]  # mixed returns behind the crease

    def split(points, rays, sigma=0.003):
        """Face index per point (0 everywhere when the patch is not cut)."""
        st = _State(X=points, U=rays, S=np.full(len(points), sigma), hk=np.ones(len(points), np.int64))
        lab = np.zeros(len(points), np.int32)
        for j, face in enumerate(_faces(np.arange(len(points)), st, SegmentationParams())):
            lab[face] = j
        return lab

    lab = split(x, u)
    assert set(lab) == {0, 1}
    truth = np.arange(len(x)) >= n
    agree = max(np.mean(lab == truth), np.mean(lab != truth))
    assert agree >= 0.95
    # one face and a parallel layer of a fifth of its pixels behind it: not two faces of a corner
    one = np.concatenate([top, top[:100] + [0.0, 0.0, 0.2]])
    assert set(split(one, one / np.linalg.norm(one, axis=1, keepdims=True))) == {0}
    # a pipe of radius 5 cm under 1 cm noise, 3 m away: its facets would pass for planes, but are strips
    t, phi = rng.uniform(0, 1.0, 800), rng.uniform(-1.3, 1.3, 800)
    pipe = np.column_stack([t, 0.05 * np.sin(phi), 3.0 - 0.05 * np.cos(phi)])
    up = pipe / np.linalg.norm(pipe, axis=1, keepdims=True)
    pipe += up * rng.normal(0.0, 0.01, 800)[:, None]
    assert set(split(pipe, up, sigma=0.01)) == {0}


def test_a_far_box_corner_keeps_the_layer_behind_a_face_with_that_face():
    """Two faces of a far box and, behind one of them, a parallel layer of 15 % of its pixels (the wall seen
    past the box's edge, merged into the patch): cut into the two faces, the layer with the face it lies
    behind. A layer as large as the face is not a layer: the patch is not cut."""
    from recognition.segmentation.grid import _State
    from recognition.segmentation.splits import _faces

    rng = np.random.default_rng(11)
    n, m = 400, 60
    a, b = rng.uniform(0.0, 0.6, n), rng.uniform(-0.3, 0.3, n)
    top = np.column_stack([a * 0.7, b, np.full(n, 12.0) - a * 0.7])
    side = np.column_stack([-a * 0.7, b, np.full(n, 12.0) - a * 0.7])
    behind = np.array([-1.0, 0.0, 1.0]) / np.sqrt(2.0)  # the side face's normal, away from the sensor

    def faces_of(n_layer):
        layer = side[:n_layer] + 0.3 * behind
        x = np.concatenate([top, side, layer])
        u = x / np.linalg.norm(x, axis=1, keepdims=True)
        x = x + u * rng.normal(0.0, 0.003, len(x))[:, None]
        st = _State(X=x, U=u, S=np.full(len(x), 0.003), hk=np.ones(len(x), np.int64))
        return _faces(np.arange(len(x)), st, SegmentationParams())

    got = faces_of(m)
    assert len(got) == 2
    which = np.zeros(2 * n + m, int)
    for j, f in enumerate(got):
        which[f] = j
    face_top, face_side = np.bincount(which[:n]).argmax(), np.bincount(which[n:2 * n]).argmax()
    assert face_top != face_side
    assert np.mean(which[:n] == face_top) >= 0.95 and np.mean(which[n:2 * n] == face_side) >= 0.95
    assert np.all(which[2 * n:] == face_side)
    assert faces_of(n) == []


@pytest.mark.parametrize("seed", range(5))
def test_k_planes_parts_a_far_box_corner_with_a_narrow_face(seed):
    """Three faces of a box corner pointing at the sensor from 18 m (8 mm noise), one of them a narrow strip
    (a cabinet's top at a grazing angle): each part of the 3-plane cut is one face, and each point that lies
    4 sigmas off the other faces is in its own face's part (the others are ambiguous near a crease).
    The start from the pixels' normals put the strip into a broad face on such a frame of the default suite."""
    from scipy.spatial.transform import Rotation

    from recognition.segmentation.splits import _k_planes

    rng = np.random.default_rng(seed)
    # box frame: the corner at its origin, the box in x, y, z >= 0, turned so (1, 1, 1) points away from the
    # sensor, then spun about the line of sight
    R = Rotation.align_vectors([[0.0, 0.0, 1.0]], [np.ones(3) / np.sqrt(3.0)])[0]
    R = Rotation.from_rotvec([0.0, 0.0, rng.uniform(0, 2 * np.pi)]) * R
    sizes = (450, 300, 100)
    faces = []
    for i, m in enumerate(sizes):
        q = np.zeros((m, 3))
        j, k = [a for a in range(3) if a != i]
        q[:, j] = rng.uniform(0.0, 0.6, m)
        q[:, k] = rng.uniform(0.0, 0.6 if i < 2 else 0.06, m)  # the third face is 6 cm wide
        faces.append(q)
    x = R.apply(np.concatenate(faces)) + [0.0, 0.0, 18.0]
    u = x / np.linalg.norm(x, axis=1, keepdims=True)
    x = x + u * rng.normal(0.0, 0.008, len(x))[:, None]
    truth = np.repeat(np.arange(3), sizes)
    part = _k_planes(x, u, np.full(len(x), 0.008), 3, SegmentationParams())
    assert part is not None
    face_of_part = [int(np.argmax(np.bincount(truth[part == j], minlength=3))) for j in range(3)]
    assert sorted(face_of_part) == [0, 1, 2]
    # face i is the plane (x - corner) . n_i = 0; a point 4 sigmas (along its ray) off every other face can
    # only be on its own
    normal = R.apply(np.eye(3))
    off = np.abs((x - [0.0, 0.0, 18.0]) @ normal.T) / (np.abs(u @ normal.T) * 0.008)
    off[np.arange(len(x)), truth] = np.inf
    clear = off.min(axis=1) > 4.0
    assert clear.mean() > 0.7
    assert np.mean(np.asarray(face_of_part)[part[clear]] == truth[clear]) >= 0.99


@given(st.lists(st.tuples(st.integers(-2, 40), st.integers(-2, 40)), max_size=60))
@settings(max_examples=60, deadline=None)
def test_unique_pairs_equal_numpy_unique_rows(rows):
    from recognition.segmentation.grid import _unique_pairs

    pairs = np.array(rows, np.int64).reshape(-1, 2)
    got, counts = _unique_pairs(pairs, return_counts=True)
    if pairs.size == 0:
        assert got.shape == (0, 2) and counts.size == 0
        return
    want, want_counts = np.unique(pairs, axis=0, return_counts=True)
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(counts, want_counts)


def _roof(seed: int):
    """A roof of two half-planes meeting at a crease, rendered with sigma 0.2 mm and no jumps: the valid
    mask, the crease's first column, the right labels (face 0 and 1), the state and links of ``_reassign``."""
    from recognition.segmentation.grid import _neighbour_links, _State

    sigma = 2e-4
    n1, n2 = np.array([1.0, 0, -1.0]), np.array([-1.0, 0, -1.0])
    surfaces = [S.Surface(lambda d: _halfplane(d, n1, x_sign=-1), 1),
                S.Surface(lambda d: _halfplane(d, n2, x_sign=1), 2)]
    pts, _, ids = S.render(surfaces, CAM, sigma, np.random.default_rng(seed))
    valid = ids > 0
    crease = int(np.flatnonzero((ids == 2).any(axis=0)).min())
    right = np.where(valid, ids - 1, -1).astype(np.int32)
    X = pts.reshape(-1, 3)
    st = _State(X=X, U=X / np.linalg.norm(X, axis=1, keepdims=True), S=np.where(valid.ravel(), sigma, np.nan),
                hk=np.ones(X.shape[0], np.int64))
    no_jump_h = np.zeros((CAM.height, CAM.width - 1), bool)
    no_jump_v = np.zeros((CAM.height - 1, CAM.width), bool)
    return valid, crease, right, st, _neighbour_links(valid.shape, valid, no_jump_h, no_jump_v), no_jump_h, no_jump_v


def test_border_pixels_on_the_wrong_face_move_to_the_face_they_lie_on():
    """A label border four columns past a roof's crease: the columns of the other face that fit it clearly
    better go back to it; no pixel leaves the face it lies on, and a right labelling is left alone."""
    from recognition.segmentation.reassignment import _reassign

    valid, crease, right, st, links, no_jump_h, no_jump_v = _roof(5)
    shifted = np.where(valid, (np.arange(CAM.width)[None, :] >= crease + 4).astype(np.int32), -1)

    params = SegmentationParams(reassign_rounds=16, reassign_margin=1.0)
    out = _reassign(shifted, st, params, links, no_jump_h, no_jump_v)
    wrong_before = int((shifted != right).sum())
    wrong_after = int((out != right).sum())
    assert wrong_before == 4 * valid[:, crease].sum()
    assert wrong_after <= wrong_before // 4  # at most the column at the crease, which fits both faces
    assert not ((out != shifted) & (shifted == right)).any()  # nothing moved off its own face
    assert np.array_equal(_reassign(right, st, params, links, no_jump_h, no_jump_v), right)
    assert np.array_equal(_reassign(shifted, st, replace(params, reassign_rounds=0), links, no_jump_h, no_jump_v),
                          shifted)


def test_fragments_go_to_the_face_they_lie_on():
    """A fragment's own fit follows its few pixels, so it never loses a residual comparison: its pixels go
    to the linked patch whose surface fits them (here: 30 pixels inside one face of a roof, and 30 pixels of
    the other face just past the crease, both linked to each face)."""
    from recognition.segmentation.reassignment import _reassign

    valid, crease, right, st, links, no_jump_h, no_jump_v = _roof(6)
    rows = np.flatnonzero(valid[:, crease - 20] & valid[:, crease + 2])
    r0 = int(rows[rows.size // 2])
    labels = right.copy()
    labels[r0:r0 + 2, crease - 25:crease - 10] = 2  # inside face 0
    labels[r0 + 10:r0 + 12, crease:crease + 15] = 3  # face 1, touching face 0 at the crease
    assert (labels == 2).sum() == 30 and (labels == 3).sum() == 30

    params = SegmentationParams(reassign_rounds=16, reassign_margin=1.0)
    out = _reassign(labels, st, params, links, no_jump_h, no_jump_v)
    assert np.array_equal(out[labels == 2], np.zeros(30))
    frag = labels == 3
    assert np.array_equal(out[frag & (np.arange(CAM.width) > crease)[None, :]], np.ones(28))
    assert set(out[frag].tolist()) <= {0, 1}
    # a patch of min_patch_pixels or more keeps its own fit: the rule is for fragments only
    big = replace(params, min_patch_pixels=30)
    kept = _reassign(labels, st, big, links, no_jump_h, no_jump_v)
    assert (kept[labels == 2] == 2).all()


@pytest.mark.parametrize("field,value", [("reassign_rounds", -1), ("reassign_margin", float("nan")),
                                         ("reassign_margin", -0.5)])
def test_impossible_reassignment_parameters_are_refused(field, value):
    with pytest.raises(ValueError, match=field):
        SegmentationParams(**{field: value})


@pytest.mark.parametrize("field,value", [
    ("crease_baseline", 0), ("crease_baseline", "window"), ("class_min_pixels", 0), ("max_tiled_leftover", 0),
    ("axis_split_pixels", 0), ("seed_erosion", None), ("decimation", None), ("decimation", 0),
    ("split_seeds", None), ("split_seeds", "yes"), ("max_variance_ratio", 0.0), ("noise_block", 0),
    ("absorb_rounds", 0), ("plane_pair_tol", -0.1), ("kplanes_iterations", 0), ("kplanes_inlier_k", 0.0),
    ("kplanes_trials", 0), ("face_broad_ratio", 0.0), ("face_keep", 1.5), ("face_min_angle_deg", 120.0),
    ("axis_split_passes", 0), ("axial_fit_points", 5), ("axial_flat_fraction", 0.0), ("axial_min_bins", 0),
    ("axial_slice_points", 0), ("elbow_cut_keep", 0.0), ("elbow_cut_rounds", 0), ("elbow_cut_k", -3.0),
    ("reassign_refit_pixels", 0), ("thin_peel_fraction", 0.0), ("stair_fraction", 2.0)])
def test_impossible_step_parameters_are_refused(field, value):
    """Off is None (never 0), a value derived from the image is "auto" (never None): anything else is refused
    with a one-line error naming the field."""
    with pytest.raises(ValueError, match=field):
        SegmentationParams(**{field: value})


def test_off_and_auto_spellings():
    p = SegmentationParams()
    assert p.crease_baseline is None and p.baseline == 0  # off
    assert SegmentationParams(crease_baseline="auto").baseline == p.window
    assert SegmentationParams(crease_baseline=3).baseline == 3
    assert p.seed_erosion == "auto" and p.erosion == p.window // 2
    assert p.decimation == "auto" and p.step((480, 640)) == 2 and p.step((245, 276)) == 1
    assert SegmentationParams(decimation=3).step((480, 640)) == 3
    assert p.class_min_pixels is None and p.scaled(2).class_min_pixels is None
    assert SegmentationParams(class_min_pixels=40).scaled(2).class_min_pixels == 10


@pytest.mark.parametrize("n_cols, fitted", [(2, False), (3, True)])
def test_masked_fits_need_three_rows_and_three_columns(n_cols, fitted):
    """A window whose returns span fewer than 3 columns cannot fix the second derivatives: NaN, not a fit
    (with the variance rule off, the support rule alone decides)."""
    v, u = np.mgrid[0:20, 0:20].astype(float)
    pts = np.stack([(u - 10) * 0.01, (v - 10) * 0.01, np.full((20, 20), 2.0)], axis=-1)
    cols = slice(9, 9 + n_cols)
    keep = np.zeros((20, 20), bool)
    keep[:, cols] = True
    pts[~keep] = np.nan
    sig = np.where(keep, 1e-3, np.nan)
    der = D.quadratic_derivatives(pts, sig, 5, 4.0, 5.0, max_variance_ratio=np.inf)  # 2 x 5 pixels: support enough
    assert not der.full.any()
    assert np.isfinite(der.Puu[10, 10]).all() == fitted
    if fitted:  # a plane: zero second derivatives, the pixel pitch as first ones
        assert np.allclose(der.Pu[5:15, 10], [0.01, 0, 0], atol=1e-12)
        assert np.allclose(der.Puu[5:15, 10], 0.0, atol=1e-12)


@given(st.lists(st.integers(-3, 70000), min_size=0, max_size=80), st.booleans())
@settings(max_examples=60, deadline=None)
def test_groups_list_each_labels_pixels_in_order(values, small):
    from recognition.segmentation.grid import _groups

    labels = np.array(values, np.int32)
    if small:  # few labels, many pixels each
        labels = np.where(labels >= 0, labels % 300, labels).astype(np.int32)
    got = _groups(labels.reshape(1, -1))
    want = {int(k): np.flatnonzero(labels == k) for k in np.unique(labels[labels >= 0])}
    assert list(got) == sorted(want)
    for k, idx in want.items():
        np.testing.assert_array_equal(got[k], idx)


@given(st.lists(st.floats(0.0, 20.0) | st.just(np.inf), min_size=1, max_size=40), st.sampled_from([2.0, 6.0, 7.5]))
@settings(max_examples=200, deadline=None)
def test_trim_threshold_is_max_of_trim_and_three_medians(z, trim):
    from recognition.segmentation.quick_fits import _trim_threshold

    z = np.array(z)
    assert _trim_threshold(z, trim) == max(trim, 3.0 * float(np.median(z)))


@settings(max_examples=30, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), m=st.integers(3, 60))
def test_line_misfit_of_all_prefixes_matches_weighted_polyfit(seed, m):
    from recognition.segmentation.splits import _line_misfit

    g = np.random.default_rng(seed)
    x = np.sort(g.choice(200, m, replace=False))
    y = g.normal(0.1, 0.01, m) + 1e-3 * x
    w = g.integers(20, 60, m).astype(np.float64)
    tol = g.uniform(1e-3, 5e-3, m)
    ends = np.arange(2, m + 1)
    got = _line_misfit(x, y, w, tol, ends)
    for e, v in zip(ends, got, strict=True):
        c = np.polyfit(x[:e], y[:e], 1, w=np.sqrt(w[:e]))
        assert v == pytest.approx(np.max(np.abs(np.polyval(c, x[:e]) - y[:e]) / tol[:e]), rel=1e-6, abs=1e-9)


def test_a_pipe_reducer_pipe_run_is_cut_into_its_three_parts():
    """A pipe (r = 0.1 m, 0.4 m long), a 6 deg reducer (0.3 m) and a thinner pipe (1.2 m) merged under 5 mm
    noise, cut as the splitter's passes do: no single cut leaves a line on both sides, three lines fit.
    In at least 6 of 8 noise draws (7 when written) the run ends in three or more pieces with under 10 % of
    its points in a piece whose majority is another part (the joins are placed to a slice or two)."""
    from recognition.segmentation.splits import _axial_pieces

    j1, j2, tan = 0.4, 0.7, np.tan(np.radians(6.0))
    good = 0
    for seed in range(8):
        x, normals = _pipe_run_points(lambda t: 0.1 - np.clip(t - j1, 0.0, j2 - j1) * tan, 1.9, 0.005, seed=seed)
        lab = np.zeros(len(x), int)
        for _ in range(3):  # the passes of _split_along_axis
            for piece in np.unique(lab):
                idx = np.flatnonzero(lab == piece)
                side = _axial_pieces(x[idx], np.full(idx.size, 0.005), normals[idx], 200, SegmentationParams())
                if side is not None:
                    lab[idx[side == 1]] = lab.max() + 1
        part = np.digitize(x[:, 0], [j1, j2])
        stray = sum((lab == p).sum() - np.bincount(part[lab == p]).max() for p in np.unique(lab)) / len(x)
        good += len(np.unique(lab)) >= 3 and stray < 0.1
    assert good >= 6


def test_a_partial_end_slice_does_not_keep_a_pipe_reducer_pipe_run_whole():
    """A thin pipe (r = 7.5 cm, 0.2 m), a 6 deg reducer and a pipe (r = 12 cm, 0.6 m) under 4 mm noise, whose far
    end slice holds 40 points of mixed pixels 2.5 cm off the surface (the patch's border crosses it: part of
    the circumference and a blend with the background), as on a calibration Kinect-like frame
    (factory-s2100-p11-v0): with every slice of 20 points in the profile, that slice kept any three lines
    from fitting and the run was cut in 1 of 8 noise draws; without it in most (8 of 8 when written). The same
    pipe alone with such an end slice is never cut."""
    from recognition.segmentation.splits import _axial_pieces

    j1, j2, tan = 0.2, 0.2 + 0.045 / np.tan(np.radians(6.0)), np.tan(np.radians(6.0))
    length = j2 + 0.6
    cut = 0
    for seed in range(8):
        x, normals = _pipe_run_points(lambda t: 0.075 + np.clip(t - j1, 0.0, j2 - j1) * tan, length, 0.004,
                                      seed=seed)
        g = np.random.default_rng(100 + seed)
        t_end = g.uniform(length, length + 0.03, 40)
        phi = g.uniform(0.8, 1.2, 40)
        radial = np.stack([np.zeros(40), np.sin(phi), -np.cos(phi)], axis=1)
        end = np.column_stack([t_end, np.zeros(40), np.full(40, 3.0)]) + 0.145 * radial
        pts, nrm = np.vstack([x, end]), np.vstack([normals, radial])
        side = _axial_pieces(pts, np.full(len(pts), 0.004), nrm, 200, SegmentationParams())
        cut += side is not None
        x, normals = _pipe_run_points(lambda t: np.full_like(t, 0.12), 0.8, 0.004, seed=seed)
        pts, nrm = np.vstack([x, end - [length - 0.8, 0, 0]]), np.vstack([normals, radial])
        assert _axial_pieces(pts, np.full(len(pts), 0.004), nrm, 200, SegmentationParams()) is None
    assert cut >= 6


def test_a_far_thin_pipe_and_its_reducer_are_cut_with_longer_slices():
    """A far pipe (r = 7 cm, 1 m) and a 6 deg reducer (0.5 m), 700 points under 8 mm noise: slices half a
    radius long would hold about 10 points (none usable, never cut); with slices of 25 points the run is cut
    in most noise draws (6 of 8 when written), the median cut within 0.1 m of the join (slices are 5 cm).
    The same pipe alone is never cut."""
    from recognition.segmentation.splits import _axial_pieces

    join, tan = 1.0, np.tan(np.radians(6.0))
    errors = []
    for seed in range(8):
        x, normals = _pipe_run_points(lambda t: np.where(t < join, 0.07, 0.07 - (t - join) * tan), 1.5, 0.008,
                                      seed=seed, n=700)
        side = _axial_pieces(x, np.full(len(x), 0.008), normals, 50, SegmentationParams())
        if side is not None:
            t = x[:, 0]
            errors.append(abs(t[side != side[np.argmin(t)]].min() - join))
        x, normals = _pipe_run_points(lambda t: np.full_like(t, 0.07), 1.0, 0.008, seed=seed, n=700)
        assert _axial_pieces(x, np.full(len(x), 0.008), normals, 50, SegmentationParams()) is None
    assert len(errors) >= 5 and np.median(errors) < 0.1


def _elbow_run_points(sigma: float, seed: int = 0, n: int = 6000, r: float = 0.1, bend: float = 0.25,
                      len_a: float = 1.0, len_b: float = 0.75):
    """Points, normals and part (0: pipe along x, 1: its 90 deg elbow, 2: pipe along y) of the front half of a
    pipe run of radius ``r`` at z = 3 m seen from the origin, with radial noise ``sigma``."""
    rng = np.random.default_rng(seed)
    s = rng.uniform(0.0, len_a + 0.5 * np.pi * bend + len_b, n)
    part = np.digitize(s, [len_a, len_a + 0.5 * np.pi * bend])
    th = np.clip((s - len_a) / bend, 0.0, 0.5 * np.pi)
    centre = np.where((part == 0)[:, None], np.column_stack([s, np.zeros(n), np.zeros(n)]),
                      np.where((part == 1)[:, None],
                               np.column_stack([len_a + bend * np.sin(th), bend - bend * np.cos(th), np.zeros(n)]),
                               np.column_stack([np.full(n, len_a + bend), bend + s - len_a - 0.5 * np.pi * bend,
                                                np.zeros(n)])))
    tangent = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])  # (1, 0, 0) on pipe 0, (0, 1, 0) on pipe 2
    towards_sensor = np.array([0.0, 0.0, -1.0])
    phi = rng.uniform(-1.2, 1.2, n)
    radial = np.cos(phi)[:, None] * towards_sensor + np.sin(phi)[:, None] * np.cross(tangent, towards_sensor)
    x = centre + [0.0, 0.0, 3.0] + (r + rng.normal(0.0, sigma, n))[:, None] * radial
    return x, radial, part


@pytest.mark.parametrize("seed", range(4))
def test_two_pipes_merged_with_their_elbow_are_cut_apart(seed):
    """Two perpendicular pipes (1 m and 0.75 m) and their elbow merged under 8 mm noise, normals 0.1 rad off:
    the normals turn about two axes, so the cut follows the longer pipe's fitted cylinder, not an axial
    profile. Every point of the other pipe leaves it, at most 1 % of its own do (the elbow splits between
    them)."""
    from recognition.segmentation.splits import _axial_pieces

    x, normals, part = _elbow_run_points(0.008, seed)
    normals = normals + np.random.default_rng(seed + 100).normal(0.0, 0.1, normals.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    side = _axial_pieces(x, np.full(len(x), 0.008), normals, 200, SegmentationParams())
    assert side is not None
    assert np.mean(side[part == 0] == 0) >= 0.99
    assert np.all(side[part == 2] == 1)


def test_a_sphere_is_not_cut_into_pipes():
    """A close sphere's normals turn about every axis; a band of them passes for a pipe's, and cut about a
    cylinder alone it would be (``several_axes``). The splitter first asks whether one quadric fits the
    patch within noise: it does, and the sphere stays whole."""
    from recognition.segmentation.grid import _State
    from recognition.segmentation.splits import _axial_pieces, _split_along_axis

    pts, sig, ids = S.render([S.sphere([0.2, 0.1, 1.2], 0.6, 1)], CAM, 0.002, np.random.default_rng(0))
    on = ids.ravel() == 1
    X = np.where(np.isfinite(pts), pts, 0.0).reshape(-1, 3)
    normals = np.full(X.shape, np.nan)
    normals[on] = (X[on] - [0.2, 0.1, 1.2]) / 0.6
    sigma = np.where(on, 0.002, np.nan)
    assert _axial_pieces(X[on], sigma[on], normals[on], 200, SegmentationParams(), several_axes=True) is not None
    params = SegmentationParams()
    st = _State(X=X, U=X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12), S=sigma,
                hk=np.full(len(X), int(SurfaceType.ELLIPTIC), np.int64))
    labels = np.where(ids == 1, 0, -1).astype(np.int32)
    np.testing.assert_array_equal(_split_along_axis(labels, st, params, normals), labels)


def test_peeling_keeps_the_staircase_border_of_a_thin_diagonal_strip():
    """The peel removes a patch's corners and spurs, but a strip eight pixels wide running down a steep
    diagonal (three columns per row) has a weak pixel at each end of every row: those close a 2 x 2 block of
    the strip and stay, or the strip would lose a quarter of its pixels. A rectangle still loses its four
    corners, and a one-pixel spur still goes."""
    from recognition.segmentation.peel import _peel_weak

    labels = np.full((60, 240), -1, np.int32)
    for r in range(60):
        labels[r, 200 - 3 * r:208 - 3 * r] = 0
    labels[5:35, 210:238] = 1
    labels[20, 209] = 1  # a spur
    no_jump_h = np.zeros((60, 239), bool)
    no_jump_v = np.zeros((59, 240), bool)
    out = _peel_weak(labels, SegmentationParams(min_region_pixels=200), no_jump_h, no_jump_v)
    strip = labels == 0
    assert (out[strip] == 0).sum() >= strip.sum() - 6  # the overhangs of its first and last rows go
    assert (out[1:-1][strip[1:-1]] == 0).all()
    for r, c in ((5, 210), (5, 237), (34, 210), (34, 237), (20, 209)):
        assert out[r, c] == -1
    assert (out == 1).sum() == (labels == 1).sum() - 5


@given(width=st.integers(4, 18), shift=st.integers(1, 5), rows=st.integers(30, 60), left=st.booleans())
@settings(max_examples=60, deadline=None)
def test_peeling_keeps_every_interior_row_of_a_diagonal_strip(width, shift, rows, left):
    """Property: a strip ``width`` pixels wide moving ``shift`` columns per row (either way), of 200 pixels or
    more, keeps all the pixels of its interior rows (only its first and last rows' overhangs go). Each pixel
    needs a neighbour in the next or the previous row (``width >= 2 shift``): a thinner strip is a chain of
    one-pixel lines, which the peel takes."""
    from recognition.segmentation.peel import _peel_weak

    shift = min(shift, width // 2)
    W = rows * shift + width + 4
    labels = np.full((rows, W), -1, np.int32)
    for r in range(rows):
        c0 = 2 + (r * shift if not left else (rows - 1 - r) * shift)
        labels[r, c0:c0 + width] = 0
    if (labels == 0).sum() < 200:
        return
    out = _peel_weak(labels, SegmentationParams(min_region_pixels=200), np.zeros((rows, W - 1), bool),
                     np.zeros((rows - 1, W), bool))
    assert (out[1:-1][labels[1:-1] == 0] == 0).all()


def test_a_one_pixel_strip_determines_no_quadric_and_gets_its_plane():
    """A row of pixels lies exactly on the plane through the sensor that holds its rays: every quadric holding
    that plane fits it, and the fit would be whichever null vector the rounding picks (labels that changed with
    the machine). It gets the plane, alone and batched; a patch of two rows gets its quadric."""
    from recognition.segmentation.grid import _State
    from recognition.segmentation.quick_fits import _quick_fit, _quick_fits, quadric_undetermined

    rng = np.random.default_rng(4)
    cols = np.arange(14)
    rays = np.stack([np.tan(0.01 * (cols - 7)), np.full(14, np.tan(0.05)), np.ones(14)], axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rng_m = 2.0 + 0.1 * np.sin(cols / 3.0) + rng.normal(0, 1e-3, 14)  # a curved surface seen along one row
    strip = rays * rng_m[:, None]
    assert quadric_undetermined(strip)
    two_rows = np.concatenate([strip, (rays + [0, 0.01, 0]) * (rng_m[:, None] + 0.02)])
    assert not quadric_undetermined(two_rows)
    p_one, z_one = _quick_fit(strip, rays, np.full(14, 1e-3), planar=False)
    p_plane, z_plane = _quick_fit(strip, rays, np.full(14, 1e-3), planar=True)
    assert np.allclose(p_one, p_plane) and np.allclose(z_one, z_plane)
    st = _State(X=strip, U=rays, S=np.full(14, 1e-3), hk=np.ones(14, np.int64))
    P, zs = _quick_fits([np.arange(14)], np.array([False]), st)
    assert np.allclose(P[0], p_plane, atol=1e-12) or np.allclose(P[0], -p_plane, atol=1e-12)
    assert np.allclose(zs[0], z_plane)
