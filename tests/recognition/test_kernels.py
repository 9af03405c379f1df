"""The compiled kernels of the segmentation (recognition.segmentation.kernels) against their numpy references,
on random inputs: fast path == slow reference.

The kernels do the references' arithmetic operation by operation; floats are compared to 1e-15 relative, not
bit for bit, since numpy's own summation order of a 3-vector depends on its SIMD path
(``python -m harness.bench.stability``); labels and flags, which follow from them, are compared exactly on
inputs where no value sits within rounding of a threshold.
"""

from __future__ import annotations

import numpy as np
import scipy.ndimage as ndi
from hypothesis import example, given, settings
from hypothesis import strategies as st

from recognition.segmentation import kernels
from recognition.segmentation.curvature import curvatures_reference
from recognition.segmentation.derivatives import jump_pairs, jump_pairs_reference, quadratic_derivatives
from recognition.segmentation.grid import _groups, _groups_reference, _neighbour_links, _State
from recognition.segmentation.growing import _grow, _grow_reference
from recognition.segmentation.quick_fits import _pixel_residuals, _ray_z

SEEDS = st.integers(0, 2**31 - 1)


def _close(a: np.ndarray, b: np.ndarray) -> None:
    """Equal to 1e-15 relative (and NaN / inf where the other has them)."""
    np.testing.assert_allclose(a, b, rtol=1e-15, atol=0.0, equal_nan=True)


def _wavy_image(seed: int, h: int, w: int, holes: float, step: float):
    """A perspective point image of a wavy surface with steps (jumps) and holes: points (h, w, 3), sigma (h, w)."""
    gen = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - w / 2) / (1.2 * w), (v - h / 2) / (1.2 * w), np.ones((h, w))], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    r = 2.0 + 0.1 * np.sin(u / 5.0 + gen.uniform(0, 6)) * np.cos(v / 7.0) + step * (u > gen.integers(1, w - 1))
    r = r + gen.normal(0.0, 1e-3, (h, w))
    pts = rays * r[..., None]
    sigma = np.full((h, w), 1e-3) * gen.uniform(0.5, 2.0, (h, w))
    hole = gen.random((h, w)) < holes
    pts[hole] = np.nan
    sigma[hole] = np.nan
    return pts, sigma


@given(SEEDS, st.integers(1, 30))
@settings(max_examples=40, deadline=None)
def test_ray_z_by_label_equals_ray_z(seed, n_quadrics):
    gen = np.random.default_rng(seed)
    n = int(gen.integers(0, 200))
    P = gen.normal(size=(n_quadrics, 10))
    P[gen.random(n_quadrics) < 0.2] = np.nan  # a patch without a fit
    P[gen.random(n_quadrics) < 0.2, :9] = 0.0  # a constant: no gradient, undefined residual
    lab = gen.integers(0, n_quadrics, n)
    X = gen.normal(size=(n, 3))
    U = gen.normal(size=(n, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    S = gen.uniform(0.0, 0.01, n)
    S[gen.random(n) < 0.1] = np.nan
    got = _pixel_residuals(P, lab, X, U, S)
    want = _ray_z(P.T.take(lab, axis=1), X.T.copy(), U, S)
    assert got.shape == (n,) and np.all(got >= 0)
    _close(got, want)


@given(st.lists(st.integers(-1, 12), min_size=0, max_size=300), st.integers(1, 40))
@settings(max_examples=60, deadline=None)
def test_groups_equal_value_indices(values, width):
    for dtype in (np.int32, np.int64, np.int16):  # the kernel's two compiled widths, and a conversion
        labels = np.array(values + [-1] * (-len(values) % width), dtype).reshape(-1, width)
        got, want = _groups(labels), _groups_reference(labels)
        assert list(got) == list(want)
        for k in want:
            np.testing.assert_array_equal(got[k], want[k])


@given(SEEDS, st.floats(0.0, 0.3), st.floats(0.0, 0.5))
@settings(max_examples=30, deadline=None)
def test_jump_pairs_equal_the_reference(seed, holes, step):
    pts, sigma = _wavy_image(seed, 23, 31, holes, step)
    rng = np.linalg.norm(pts, axis=-1)
    rays = pts / rng[..., None]
    got = jump_pairs(rng, sigma, rays, 3.0, 2.0)
    want = jump_pairs_reference(rng, sigma, rays, 3.0, 2.0)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    # the steps are found: a step beyond the smooth-surface allowance (2 x 2.1 m x the 0.027 rad between
    # neighbouring rays, 0.11 m, plus the noise's) is a jump
    assert want[0].any() or step < 0.2 or holes > 0


@given(SEEDS, st.floats(0.0, 0.2))
@settings(max_examples=20, deadline=None)
def test_curvatures_equal_the_reference(seed, holes):
    pts, sigma = _wavy_image(seed, 21, 27, holes, 0.2)
    der = quadratic_derivatives(pts, sigma, 5, 3.0, 2.0)
    got = kernels.curvatures(pts, sigma, der.Pu, der.Pv, der.Puu, der.Puv, der.Pvv, der.var_u, der.var_v,
                             der.cov2)
    want = curvatures_reference(pts, sigma, der)
    assert np.isfinite(want.H).sum() > 100
    for g, w in zip(got, (want.H, want.K, want.sigma_H, want.sigma_K, want.normals, want.sigma_normal),
                    strict=True):
        _close(g, w)


def _wavy_grid(seed: int, h: int, w: int):
    """A wavy image (5 % holes) as a grid: its valid pixels (h, w), neighbour links (across no jump) and state."""
    pts, sigma = _wavy_image(seed, h, w, 0.05, 0.3)
    valid = np.isfinite(sigma)
    rng = np.linalg.norm(pts, axis=-1)
    rays = pts / rng[..., None]
    jump_h, jump_v = jump_pairs(rng, sigma, rays, 3.0, 2.0)
    links = _neighbour_links(valid.shape, valid, jump_h, jump_v)
    st_ = _State(X=pts.reshape(-1, 3), U=rays.reshape(-1, 3), S=sigma.ravel(), hk=np.ones(valid.size, np.int64))
    return valid, links, st_


@given(SEEDS, st.integers(1, 12), st.floats(0.5, 60.0), st.integers(1, 40))
@settings(max_examples=40, deadline=None)
def test_grow_equals_the_reference(seed, n_seeds, thr, max_iter):
    valid, links, st_ = _wavy_grid(seed, 19, 25)
    gen = np.random.default_rng(seed)
    labels = np.full(valid.shape, -1, np.int32)
    for k in range(n_seeds):  # small square seeds, some overlapping holes
        r, c = gen.integers(0, 17), gen.integers(0, 23)
        labels[r:r + 2, c:c + 2] = np.where(valid[r:r + 2, c:c + 2], k, -1)
    # planes through the middle of each seed, perturbed: some pixels fit, some do not
    P = np.zeros((n_seeds, 10))
    P[:, 6:9] = gen.normal(0.0, 0.05, (n_seeds, 3)) + [0.0, 0.0, 1.0]
    P[:, 9] = -gen.uniform(1.8, 2.3, n_seeds)
    got, want = labels.copy(), labels.copy()
    _grow(got, P, st_, links, max_iter, thr)
    _grow_reference(want, P, st_, links, max_iter, thr)
    np.testing.assert_array_equal(got, want)


def test_grow_fills_a_plane_and_stops_at_a_jump():
    """A closed case: a fronto-parallel plane at 2 m with a step of 0.5 m half-way; one seed on each side
    grows over its own side only."""
    h, w = 10, 12
    v, u = np.mgrid[0:h, 0:w].astype(float)
    rays = np.stack([(u - w / 2) / 20, (v - h / 2) / 20, np.ones((h, w))], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    z = np.where(u < 6, 2.0, 2.5)
    pts = rays * (z / rays[..., 2])[..., None]
    sigma = np.full((h, w), 1e-3)
    valid = np.ones((h, w), bool)
    rng = np.linalg.norm(pts, axis=-1)
    jump_h, jump_v = jump_pairs(rng, sigma, rays, 3.0, 2.0)
    assert jump_h[:, 5].all() and jump_h.sum() == h  # the step, and nothing else
    links = _neighbour_links(valid.shape, valid, jump_h, jump_v)
    st_ = _State(X=pts.reshape(-1, 3), U=rays.reshape(-1, 3), S=sigma.ravel(), hk=np.ones(h * w, np.int64))
    labels = np.full((h, w), -1, np.int32)
    labels[4, 2], labels[4, 9] = 0, 1
    P = np.zeros((2, 10))
    P[:, 8], P[0, 9], P[1, 9] = 1.0, -2.0, -2.5  # z = 2 and z = 2.5
    _grow(labels, P, st_, links, 100, 3.0)
    np.testing.assert_array_equal(labels, np.where(u < 6, 0, 1))
    # the groups of the result, by both paths
    assert {k: v.size for k, v in _groups(labels).items()} == {0: 60, 1: 60}
    assert ndi.label(labels == 0)[1] == 1


def _surface_groups(seed: int, n_groups: int):
    """Groups of noisy points on random spheres, cylinders and planes seen from the origin, some tiny, one a
    strip one pixel wide (points that determine no quadric), as the segmentation's fits see them."""
    gen = np.random.default_rng(seed)
    X, groups = [], []
    for g in range(n_groups):
        n = int(gen.choice([2, 5, 12, 40, 300]))
        kind = g % 4
        uv = gen.uniform(-0.3, 0.3, (n, 2))
        if kind == 3:
            uv[:, 1] = 0.0  # a strip: every point in one plane through the sensor
        r = gen.uniform(0.1, 1.0)
        if kind == 0:  # sphere cap
            p = np.stack([r * np.sin(uv[:, 0]), r * np.sin(uv[:, 1]), -r * np.cos(uv[:, 0]) * np.cos(uv[:, 1])], 1)
        elif kind == 1:  # cylinder piece
            p = np.stack([r * np.sin(uv[:, 0]), uv[:, 1], -r * np.cos(uv[:, 0])], 1)
        else:  # plane
            p = np.stack([uv[:, 0], uv[:, 1], 0.2 * uv[:, 0]], 1)
        p = p + [0.0, 0.0, gen.uniform(2.0, 4.0)] + gen.normal(0.0, 1e-3, (n, 3))
        groups.append(np.arange(len(X) and sum(map(len, X)), sum(map(len, X)) + n))
        X.append(p)
    X = np.concatenate(X)
    U = X / np.linalg.norm(X, axis=1, keepdims=True)
    S = np.full(len(X), 1e-3)
    return _State(X=X, U=U, S=S, hk=np.ones(len(X), np.int64)), groups, gen.random(n_groups) < 0.3


@given(SEEDS, st.integers(1, 12))
@example(seed=496, n_groups=4)  # a coefficient of 0.0065 off by 2e-8: rounding, beyond the former atol of 1e-8
@example(seed=33554433, n_groups=11)  # a grazing point's residual of 2477 off by 1.5e-5 relative (so at db4cc60)
@settings(max_examples=40, deadline=None)
def test_quick_fits_equal_the_batched_reference(seed, n_groups):
    """The compiled fits against the batched numpy ones: the same surfaces (up to the sign an eigenvector
    takes) and residuals, to the rounding of moments summed in another order (of a unit coefficient vector:
    1e-7 absolute)."""
    from recognition.segmentation.quick_fits import _quick_fits, _quick_fits_reference

    st_, groups, planar = _surface_groups(seed, n_groups)
    P, zs = _quick_fits(groups, planar, st_)
    Pr, zr = _quick_fits_reference(groups, planar, st_)
    assert P.shape == Pr.shape == (n_groups, 10)
    for g in range(n_groups):
        if np.isnan(Pr[g]).all():
            assert np.isnan(P[g]).all() and np.isinf(zs[g]).all()
            continue
        sign = np.sign(P[g] @ Pr[g])
        np.testing.assert_allclose(sign * P[g], Pr[g], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(zs[g], zr[g], rtol=3e-5, atol=1e-6)  # (grazing points: 1.5e-5 seen)


@given(SEEDS, st.floats(0.0, 0.3), st.sampled_from([5, 7]))
@settings(max_examples=25, deadline=None)
def test_masked_fits_equal_the_reference(seed, holes, window):
    from recognition.segmentation.derivatives import _masked_fits, _masked_fits_reference

    pts, sigma = _wavy_image(seed, 17, 23, holes, 0.3)
    valid = np.isfinite(pts).all(axis=-1) & np.isfinite(sigma)
    rng = np.linalg.norm(pts, axis=-1)
    rays = pts / rng[..., None]
    masked = valid.copy()

    def outputs():
        return tuple(np.full(shape, np.nan) for shape in [(17, 23, 3)] * 5 + [(17, 23)] * 2 + [(17, 23, 6)])

    got, want = outputs(), outputs()
    args = (pts, sigma, rng, rays, valid, masked, window, 3.0, 2.0, max(9, window * window // 3), 1e3)
    _masked_fits(*args, 64, got)
    _masked_fits_reference(*args, 64, want)
    assert np.isfinite(want[0]).any()
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-12, equal_nan=True)


@given(SEEDS, st.floats(0.0, 0.5))
@settings(max_examples=25, deadline=None)
def test_checked_returns_equal_the_reference(seed, holes):
    from recognition.segmentation.edges import checked_returns, checked_returns_reference

    pts, sigma = _wavy_image(seed, 9, 13, holes, 0.3)
    gen = np.random.default_rng(seed)
    pts[gen.random((9, 13)) < 0.1] = 0.0  # no range
    pts[0, 0] = [1e160, 0.0, 0.0]  # its square overflows: no return
    sigma[gen.random((9, 13)) < 0.1] = 1e-6  # below the floor
    got = checked_returns(pts, sigma, 1e-4)
    want = checked_returns_reference(pts, sigma, 1e-4)
    assert not want[0][0, 0] and np.nanmin(want[2]) >= 1e-4
    np.testing.assert_array_equal(got[0], want[0])
    for g, w in zip(got[1:], want[1:], strict=True):
        _close(g, w)


@given(SEEDS, st.sampled_from([3, 5, 7, 9]), st.integers(1, 30), st.integers(1, 30))
@settings(max_examples=40, deadline=None)
def test_savgol_derivatives_equal_ndimage(seed, window, h, w):
    """The separable Savitzky-Golay kernel sums as scipy.ndimage.correlate1d (mode nearest) does: the same
    bits, on images smaller than the window too."""
    from recognition.segmentation.derivatives import _full_window_derivatives, _full_window_derivatives_reference

    p = np.random.default_rng(seed).normal(size=(h, w, 3)) * 3.0
    for g, r in zip(_full_window_derivatives(p, window), _full_window_derivatives_reference(p, window), strict=True):
        np.testing.assert_array_equal(g, r)


@given(st.lists(st.lists(st.integers(0, 4), min_size=0, max_size=30), min_size=0, max_size=12))
@settings(max_examples=60, deadline=None)
def test_planar_groups_equal_the_per_group_counts(classes):
    """The planar test of many groups in one count (compiled, and its bincount reference) == group by group (a
    group of no pixel is planar); the groups' pixels in any order."""
    from recognition.segmentation.grid import _is_planar_counts, _planar_groups, _planar_groups_reference

    hk = np.array([c for g in classes for c in g], np.int64)
    bounds = np.cumsum([0] + [len(g) for g in classes])
    order = np.random.default_rng(len(hk)).permutation(len(hk))
    groups = [order[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    want = np.array([_is_planar_counts(np.bincount(hk[g], minlength=5)) for g in groups], bool)
    np.testing.assert_array_equal(_planar_groups(groups, hk), want)
    np.testing.assert_array_equal(_planar_groups_reference(groups, hk), want)


def _patchy_state(seed: int, h: int, w: int, n_labels: int):
    """A wavy image cut into random rectangular patches (some pixels unlabelled), each with a perturbed plane:
    the state, flat labels (h*w,), the planes (n_labels, 10) and the links' steps and flags."""
    from recognition.segmentation.reassignment import _flat_links

    valid, links, st_ = _wavy_grid(seed, h, w)
    gen = np.random.default_rng(seed)
    labels = np.full(valid.shape, -1, np.int32)
    for k in range(3 * n_labels):
        r, c = gen.integers(0, h), gen.integers(0, w)
        labels[r:r + gen.integers(1, 8), c:c + gen.integers(1, 8)] = k % n_labels
    labels[~valid] = -1
    P = np.zeros((n_labels, 10))
    P[:, 6:9] = gen.normal(0.0, 0.05, (n_labels, 3)) + [0.0, 0.0, 1.0]
    P[:, 9] = -gen.uniform(1.9, 2.2, n_labels)
    P[gen.random(n_labels) < 0.1] = np.nan  # a patch without a fit
    steps, ok = _flat_links(links, w)
    return st_, labels.ravel(), P, steps, ok


@given(SEEDS, st.integers(1, 12), st.floats(0.0, 3.0), st.floats(0.5, 60.0))
@settings(max_examples=40, deadline=None)
def test_reassign_targets_equal_the_reference(seed, n_labels, margin, thr):
    from recognition.segmentation.reassignment import _targets, _targets_reference

    st_, flat, P, steps, ok = _patchy_state(seed, 19, 25, n_labels)
    gen = np.random.default_rng(seed)
    cand = np.flatnonzero((flat >= 0) & (gen.random(flat.size) < 0.5))
    fragment = gen.random(n_labels) < 0.3
    got = _targets(flat, P, st_, cand, steps, ok, fragment, margin, thr)
    want = _targets_reference(flat, P, st_, cand, steps, ok, fragment, margin, thr)
    np.testing.assert_array_equal(got, want)


@given(SEEDS, st.integers(1, 12))
@settings(max_examples=40, deadline=None)
def test_next_candidates_equal_the_reference(seed, n_labels):
    from recognition.segmentation.reassignment import _next_candidates_reference

    st_, flat, P, steps, ok = _patchy_state(seed, 19, 25, n_labels)
    gen = np.random.default_rng(seed)
    labelled = np.flatnonzero(flat >= 0)
    cand = np.sort(gen.choice(labelled, labelled.size // 3, replace=False)) if labelled.size else labelled
    moved = cand[gen.random(cand.size) < 0.4]
    got = kernels.next_candidates(flat, cand, moved, steps, ok)
    np.testing.assert_array_equal(got, _next_candidates_reference(flat, cand, moved, steps, ok))


@given(SEEDS, st.integers(1, 300), st.integers(1, 12))
@settings(max_examples=60, deadline=None)
def test_bin_medians_equal_the_sorted_ranks(seed, n, n_bins):
    """The median element of each bin by selection == by one sort of all values by bin and value (ties too)."""
    from recognition.segmentation.grid import _bin_medians

    gen = np.random.default_rng(seed)
    values = np.round(gen.normal(size=n), 1)  # ties
    bins = gen.integers(0, n_bins, n)
    cnt = np.bincount(bins, minlength=n_bins)
    which = np.flatnonzero(cnt > 0)
    order = np.lexsort((values, bins))
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    want = values[order[start[which] + cnt[which] // 2]]
    np.testing.assert_array_equal(_bin_medians(values, bins, n_bins, which), want)


@given(SEEDS, st.floats(0.0, 0.3), st.floats(0.0, 0.5), st.floats(1.0, 4.0))
@settings(max_examples=30, deadline=None)
def test_jump_pairs_among_earlier_ones_equal_all(seed, holes, step, max_scale):
    """Tested only among given pairs, the jump flags are those pairs' flags; with a sigma scaled by >= 1 (as
    the noise self-calibration scales it), among the unscaled sigma's jumps they are all the jumps."""
    pts, sigma = _wavy_image(seed, 23, 31, holes, step)
    rng = np.linalg.norm(pts, axis=-1)
    rays = pts / rng[..., None]
    among = jump_pairs(rng, sigma, rays, 3.0, 0.3)
    scaled = sigma * np.random.default_rng(seed).uniform(1.0, max_scale, sigma.shape)
    scaled[0, 0] = sigma[0, 0]  # a scale of exactly 1
    got = kernels.jump_pairs_among(rng, scaled, rays, 3.0, 0.3, *among)
    for g, w, a in zip(got, jump_pairs(rng, scaled, rays, 3.0, 0.3), among, strict=True):
        np.testing.assert_array_equal(g, w)
        np.testing.assert_array_equal(w & a, w)
    some = [a & (np.random.default_rng(seed + 1).random(a.shape) < 0.5) for a in among]
    for g, w, a in zip(kernels.jump_pairs_among(rng, sigma, rays, 3.0, 0.3, *some), among, some, strict=True):
        np.testing.assert_array_equal(g, w & a)


@given(SEEDS, st.integers(1, 12))
@settings(max_examples=30, deadline=None)
def test_quick_fits_from_the_cache_equal_fresh_ones(seed, n_groups):
    """A group's quick fit does not depend on the batch it is fitted in: refitted among other groups, in another
    order, or taken from the state's cache, it is the same, bit for bit (and the cached residuals are read only)."""
    import pytest

    from recognition.segmentation.quick_fits import _quick_fits

    st_, groups, planar = _surface_groups(seed, n_groups)
    P, zs = _quick_fits(groups, planar, st_)
    assert len(st_.fits) == len({(bool(p) or g.size < 10, g.tobytes()) for g, p in zip(groups, planar, strict=True)})
    fresh = _State(X=st_.X, U=st_.U, S=st_.S, hk=st_.hk)
    order = np.random.default_rng(seed).permutation(n_groups)
    Po, zo = _quick_fits([groups[g] for g in order], planar[order], fresh)  # fitted anew, in another batch
    Pc, zc = _quick_fits([groups[g] for g in order], planar[order], st_)  # from the cache
    for j, g in enumerate(order):
        np.testing.assert_array_equal(Po[j], P[g])
        np.testing.assert_array_equal(Pc[j], P[g])
        np.testing.assert_array_equal(zo[j], zs[g])
        np.testing.assert_array_equal(zc[j], zs[g])
    if zs and zs[0].size:
        with pytest.raises(ValueError):
            zs[0][0] = 0.0


@given(SEEDS, st.integers(1, 12), st.floats(0.0, 0.3), st.floats(0.0, 0.5))
@settings(max_examples=40, deadline=None)
def test_fragment_flags_equal_the_reference(seed, n_labels, holes, step):
    from recognition.segmentation.peel import _fragment_flags, _fragment_flags_reference

    pts, sigma = _wavy_image(seed, 19, 25, holes, step)
    rng = np.linalg.norm(pts, axis=-1)
    rays = pts / rng[..., None]
    jump_h, jump_v = jump_pairs(rng, sigma, rays, 3.0, 0.3)
    gen = np.random.default_rng(seed)
    labels = np.full(rng.shape, -1, np.int32)
    for k in range(3 * n_labels):
        r, c = gen.integers(0, 19), gen.integers(0, 25)
        labels[r:r + gen.integers(1, 8), c:c + gen.integers(1, 8)] = k % n_labels
    for lab in (labels, labels.astype(np.int64)):
        want = _fragment_flags_reference(lab, rng, jump_h, jump_v, n_labels)
        np.testing.assert_array_equal(_fragment_flags(lab, rng, jump_h, jump_v, n_labels), want)


@given(SEEDS, st.floats(0.0, 0.3), st.integers(1, 3))
@settings(max_examples=30, deadline=None)
def test_square_dilations_equal_one_maximum_filter(seed, density, d):
    """The full-resolution refinement's pixels near an edge: d dilations by the 3 x 3 square (what it did)
    are one maximum filter of the (2d + 1) square, also at the image's border."""
    edge = np.random.default_rng(seed).random((17, 23)) < density
    want = ndi.binary_dilation(edge, structure=np.ones((3, 3), bool), iterations=d)
    np.testing.assert_array_equal(ndi.maximum_filter(edge, size=2 * d + 1, mode="constant", cval=False), want)


@given(SEEDS, st.integers(1, 12))
@settings(max_examples=40, deadline=None)
def test_completion_targets_equal_the_reference(seed, n_labels):
    from recognition.segmentation.reassignment import _completion_targets, _completion_targets_reference

    st_, flat, P, steps, ok = _patchy_state(seed, 19, 25, n_labels)
    P[np.random.default_rng(seed).random(n_labels) < 0.2] = P[0]  # equal surfaces: ties
    cand = np.flatnonzero(flat < 0)
    got = _completion_targets(flat, P, st_, cand, steps, ok)
    want = _completion_targets_reference(flat, P, st_, cand, steps, ok)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@given(SEEDS, st.integers(1, 12), st.integers(1, 60), st.floats(0.01, 0.5), st.floats(0.01, 1.0))
@settings(max_examples=60, deadline=None)
def test_peel_weak_equals_the_reference(seed, n_labels, min_region, thin, stair):
    """The compiled peel against the numpy one, on blocky patches (with staircase borders and jumps), with
    thresholds that make some patches thin and some not."""
    from dataclasses import replace

    from recognition.segmentation.peel import _peel_weak, _peel_weak_reference
    from recognition.segmentation.types import SegmentationParams

    pts, sigma = _wavy_image(seed, 19, 25, 0.05, 0.3)
    rng = np.linalg.norm(pts, axis=-1)
    jump_h, jump_v = jump_pairs(rng, sigma, pts / rng[..., None], 3.0, 0.3)
    gen = np.random.default_rng(seed)
    labels = np.full(rng.shape, -1, np.int32)
    for k in range(3 * n_labels):
        r, c = gen.integers(0, 19), gen.integers(0, 25)
        labels[r:r + gen.integers(1, 8), c:c + gen.integers(1, 8)] = k % n_labels
    for r in range(19):  # a diagonal strip: a staircase border
        labels[r, r:r + 3] = n_labels
    params = replace(SegmentationParams(), min_region_pixels=min_region, thin_peel_fraction=thin,
                     stair_fraction=stair)
    for lab in (labels, labels.astype(np.int64), np.full_like(labels, -1)):
        got = _peel_weak(lab, params, jump_h, jump_v)
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, _peel_weak_reference(lab, params, jump_h, jump_v))


@given(SEEDS, st.floats(0.0, 0.5), st.booleans())
@settings(max_examples=30, deadline=None)
def test_window_inputs_and_blanking_equal_numpy(seed, holes, strided):
    """The derivatives' valid pixels and zero-filled points, and the blanking of the full-window derivatives
    outside their windows, against the numpy they replace (on a strided view too: the coarse grid's)."""
    from recognition.segmentation.derivatives import _window_inputs, _window_inputs_reference

    pts, sigma = _wavy_image(seed, 18, 22, holes, 0.3)
    gen = np.random.default_rng(seed)
    pts[gen.random((18, 22)) < 0.1, gen.integers(0, 3)] = np.inf  # one coordinate not finite
    sigma[gen.random((18, 22)) < 0.1] = np.nan  # a point without a sigma
    if strided:
        pts, sigma = pts[::2, ::2], sigma[::2, ::2]
    got, want = _window_inputs(pts, sigma), _window_inputs_reference(pts, sigma)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    full = gen.random(sigma.shape) < 0.5
    images = tuple(gen.normal(size=sigma.shape + (3,)) for _ in range(5))
    blanked = tuple(a.copy() for a in images)
    kernels.blank_outside(full, blanked)
    for a, b in zip(images, blanked, strict=True):
        a[~full] = np.nan
        np.testing.assert_array_equal(a, b)


@given(SEEDS, st.integers(1, 12), st.integers(1, 40), st.floats(0.0, 0.05), st.floats(0.0, 0.2))
@settings(max_examples=60, deadline=None)
def test_enclosed_targets_equal_the_reference(seed, n_small, min_pixels, holes, unlabelled):
    """One round of the enclosed-fragment merge, compiled and in numpy: small patches on a host (some beside
    another, unlabelled returns, holes, jumps or the border), on a strided valid mask (the coarse grid's)."""
    from recognition.segmentation.merging import _enclosed_targets, _enclosed_targets_reference

    pts, sigma = _wavy_image(seed, 38, 50, holes, 0.3)
    rng = np.linalg.norm(pts, axis=-1)[::2, ::2]
    valid = np.isfinite(sigma)[::2, ::2]
    jump_h, jump_v = jump_pairs(rng, sigma[::2, ::2], (pts / np.linalg.norm(pts, axis=-1)[..., None])[::2, ::2],
                                3.0, 0.3)
    gen = np.random.default_rng(seed)
    labels = np.zeros(rng.shape, np.int32)  # the host
    labels[:, gen.integers(10, 25):] = 1  # and a second one
    for k in range(2, n_small + 2):
        r, c = gen.integers(0, 19), gen.integers(0, 25)
        labels[r:r + gen.integers(1, 5), c:c + gen.integers(1, 5)] = k
    labels[gen.random(labels.shape) < unlabelled] = -1
    n = int(labels.max()) + 1
    got = _enclosed_targets(labels, valid, jump_h, jump_v, n, min_pixels)
    np.testing.assert_array_equal(got, _enclosed_targets_reference(labels, valid, jump_h, jump_v, n, min_pixels))
