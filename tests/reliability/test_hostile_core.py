"""Hostile range images into the core (``describe``, ``segment``) and hostile patches into ``classify_patch``:
a result (an empty description, an OTH patch with its reason) or a clear ValueError, never a traceback from
inside numpy, a hang or unbounded memory."""

from __future__ import annotations

import resource
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from recognition.classification import CLASSES, PatchClassification, classify_patch
from recognition.describe import DescribeParams, SceneDescription, describe
from recognition.segmentation import Segmentation, segment
from sensors.config import MAX_PIXELS
from sensors.models import PinholeCamera
from sensors.noise import NoiseModel
from sensors.range_image import Scan

NOISE = NoiseModel(s0_m=1e-4, s2_per_m=1e-4)


def scan_of(rng: np.ndarray) -> Scan:
    """A pinhole scan whose points are the ranges along the camera's rays (NaN / inf propagate)."""
    h, w = rng.shape
    cam = PinholeCamera.from_fov(w, h, 40.0, min_range=0.1, max_range=10.0)
    with np.errstate(invalid="ignore"):
        pts = cam.ray_directions() * rng[..., None]
    return Scan(rng, pts, cam, NOISE)


def _plane(h: int = 60, w: int = 80) -> np.ndarray:
    cam = PinholeCamera.from_fov(w, h, 40.0, min_range=0.1, max_range=10.0)
    rays = cam.ray_directions()
    return 2.0 / (rays[..., 2] + 0.3 * rays[..., 1])


def _single(h: int = 60, w: int = 80) -> np.ndarray:
    r = np.full((h, w), np.nan)
    r[h // 2, w // 2] = 1.0
    return r


IMAGES = {
    "all_nan": lambda: np.full((60, 80), np.nan),
    "all_inf": lambda: np.full((60, 80), np.inf),
    "all_minus_inf": lambda: np.full((60, 80), -np.inf),
    "all_zero": lambda: np.zeros((60, 80)),
    "all_equal": lambda: np.full((60, 80), 1.5),
    "single_valid_pixel": _single,
    "1x1": lambda: np.ones((1, 1)),
    "1x1_nan": lambda: np.full((1, 1), np.nan),
    "1xN": lambda: np.ones((1, 64)),
    "Nx1": lambda: np.ones((64, 1)),
    "2x2": lambda: np.ones((2, 2)),
    "checkerboard_nan": lambda: np.where(np.indices((60, 80)).sum(0) % 2 == 0, 1.0, np.nan),
    "stripes_of_inf": lambda: np.where(np.arange(60)[:, None] % 3 == 0, np.inf, _plane()),
    "huge_ranges": lambda: np.full((60, 80), 1e300),
    "denormal_ranges": lambda: np.full((60, 80), 1e-310),
    "plane": _plane,
}


@pytest.mark.parametrize("name", IMAGES)
def test_describe_survives_degenerate_images(name):
    scan = scan_of(IMAGES[name]())
    t0 = time.perf_counter()
    desc = describe(scan)
    assert time.perf_counter() - t0 < 20
    assert isinstance(desc, SceneDescription)
    assert desc.labels.shape == scan.shape
    for p in desc.patches:
        assert p.label in CLASSES and p.n_pixels > 0
        assert np.isfinite(scan.range.flat[p.pixels]).all(), "a patch on pixels without a return"
    if name in ("all_nan", "all_inf", "all_minus_inf", "all_zero", "single_valid_pixel", "1x1", "1x1_nan"):
        assert desc.patches == ()


@pytest.mark.parametrize("name", IMAGES)
def test_segment_survives_degenerate_images(name):
    scan = scan_of(IMAGES[name]())
    with np.errstate(invalid="ignore", over="ignore"):
        sigma = NOISE.sigma(scan.range)
    seg = segment(scan.points, np.where(np.isfinite(sigma), sigma, np.nan))
    assert isinstance(seg, Segmentation) and seg.labels.shape == scan.shape


@pytest.mark.parametrize("make, match", [
    (lambda: scan_of(np.full((30, 40), -1.0)), "1200 negative value"),
    (lambda: Scan(np.ones((30, 40)), np.ones((30, 40, 2)), scan_of(np.ones((30, 40))).sensor, NOISE),
     r"scan.points must have shape \(30, 40, 3\)"),
    (lambda: Scan(np.ones((30, 40)), np.ones((30, 40, 3)), scan_of(np.ones((10, 10))).sensor, NOISE),
     r"sensor model's image is \(10, 10\)"),
    (lambda: Scan(np.ones(40), np.ones((40, 3)), scan_of(np.ones((1, 40))).sensor, NOISE),
     r"scan.range must have shape \(H, W\)"),
])
def test_describe_rejects_unusable_scans_clearly(make, match):
    with pytest.raises(ValueError, match=match):
        describe(make())


def test_a_4000x4000_image_is_refused_up_front_in_bounded_memory():
    """16 M pixels would need about 6 GB of working memory (1.5 GB measured at 2000 x 2000): describe refuses
    it before allocating anything, saying what to do; the limit can be raised knowingly."""
    n = 4000
    cam = PinholeCamera.from_fov(n, n, 40.0, min_range=0.1, max_range=10.0)
    rng = np.broadcast_to(np.float64(1.0), (n, n))  # views: no 16 M pixel arrays are allocated by the test
    scan = Scan(rng, np.broadcast_to(np.array([0.0, 0.0, 1.0]), (n, n, 3)), cam, NOISE)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"4000 x 4000 \(16.0 M pixels\) is larger than max_pixels = 4194304 "
                                         r"\(about 6.4 GB"):
        describe(scan)
    assert time.perf_counter() - t0 < 1.0
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # kB: nothing big allocated
    assert DescribeParams(max_pixels=n * n).max_pixels == n * n
    assert MAX_PIXELS == 2048 * 2048


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(h=st.integers(1, 24), w=st.integers(1, 24), seed=st.integers(0, 2**32 - 1),
       specials=st.lists(st.sampled_from([np.nan, np.inf, -np.inf, 0.0, 1e-300, 1e300, 1.0, 5.0]), max_size=4))
def test_describe_on_random_small_images(h, w, seed, specials):
    """Random ranges with runs of special values: a description or the negative-range ValueError."""
    rs = np.random.default_rng(seed)
    r = rs.uniform(0.5, 3.0, (h, w))
    for v in specials:
        r[rs.random((h, w)) < 0.2] = v
    desc = describe(scan_of(r))
    assert desc.labels.shape == (h, w)


# ------------------------------------------------------------------------------------------------ patches

_rs = np.random.default_rng(3)
_t = np.linspace(0.0, 1.0, 200)
_flat = np.c_[_rs.uniform(-0.1, 0.1, (200, 2)), np.full(200, 1.0)]
PATCHES = {
    "collinear": np.c_[_t, 2 * _t, 3 * _t + 1],
    "coplanar": _flat,
    "coplanar_grid": np.c_[np.repeat(np.arange(15), 15) * 0.01, np.tile(np.arange(15), 15) * 0.01, np.ones(225)],
    "one_point_repeated": np.repeat([[0.1, 0.2, 1.0]], 200, axis=0),
    "two_points_repeated": np.r_[np.repeat([[0.1, 0.2, 1.0]], 100, axis=0), np.repeat([[0.2, 0.2, 1.0]], 100, 0)],
    "all_nan": np.full((200, 3), np.nan),
    "some_nan": np.r_[_flat[:150], np.full((50, 3), np.nan)],
    "some_inf": np.r_[_flat[:150], np.full((50, 3), np.inf)],
    "empty": np.zeros((0, 3)),
    "three_points": np.array([[0, 0, 1.0], [1, 0, 1], [0, 1, 1]]),
    "huge_coordinates": _flat * 1e150,
    "tiny_coordinates": _flat * 1e-150,
    "far_from_origin": _flat + 1e8,
}


@pytest.mark.parametrize("method", ["select", "paper"])
@pytest.mark.parametrize("name", PATCHES)
def test_classify_patch_on_degenerate_patches(name, method):
    for sigma in (1e-4, 0.0):
        for hint in (False, True):
            c = classify_patch(PATCHES[name], sigma, method=method, planar_hint=hint)
            assert isinstance(c, PatchClassification) and c.label in CLASSES
            assert abs(sum(c.probabilities.values()) - 1.0) < 1e-9 and all(
                np.isfinite(v) for v in c.probabilities.values())
            if c.label == "OTH":
                assert c.reason, f"{name}: OTH without a reason"


@pytest.mark.parametrize("points, sigma, match", [
    (np.zeros((10, 2)), 1e-4, r"expected points of shape \(N, 3\)"),
    (np.zeros((10, 3, 1)), 1e-4, r"expected points of shape \(N, 3\)"),
    (np.zeros((10, 3)), np.ones(9), "sigma"),
])
def test_classify_patch_misuse_is_a_value_error(points, sigma, match):
    with pytest.raises(ValueError, match=match):
        classify_patch(points, sigma)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 60), seed=st.integers(0, 2**32 - 1), rank=st.sampled_from([0, 1, 2, 3]),
       duplicate=st.booleans(), nan=st.booleans())
def test_classify_patch_on_random_degenerate_clouds(n, seed, rank, duplicate, nan):
    """Points spanning a subspace of dimension ``rank`` (0: one point, 1: a line, 2: a plane), optionally all
    duplicated, optionally with a NaN: a classification (OTH with a reason when it cannot fit)."""
    rs = np.random.default_rng(seed)
    basis = rs.normal(size=(3, 3))[:rank] if rank else np.zeros((0, 3))
    pts = rs.normal(size=(n, rank)) @ basis + np.array([0.0, 0.0, 1.5]) if rank else np.tile([0.0, 0.0, 1.5], (n, 1))
    if duplicate:
        pts = np.r_[pts, pts]
    if nan and len(pts):
        pts[rs.integers(len(pts))] = np.nan
    c = classify_patch(pts, 1e-4)
    assert c.label in CLASSES
    if c.label == "OTH":
        assert c.reason
