"""recognition.describe: the scene description, and its merge of touching patches that one primitive explains."""

from dataclasses import replace

import numpy as np
import pytest

from evaluation.oracles import truth_segmentation
from harness.suite import load_suite
from harness.trial import prepare_scene, sensor_for, trial_scan, trial_viewpoints
from recognition.classification import merge_test
from recognition.describe import DescribeParams, core_sigma, describe
from recognition.fitting import fit_cylinder, fit_plane
from recognition.segmentation import Patch


@pytest.fixture(scope="module")
def mockup_scan():
    spec = next(t for t in load_suite("classic").trials if t.trial_id == "mockup-p0-v1-mockup_laser-n0")
    prepared = prepare_scene(spec, None)
    config = sensor_for(spec)
    view = trial_viewpoints(spec, prepared, config).viewpoints[0]
    scan, truth = trial_scan(spec, prepared, config, view.T_world_sensor)
    return scan, truth, truth_segmentation(scan, truth, core_sigma(scan))


def _split(seg, label: int):
    """The segmentation with patch ``label`` cut in two halves by image column (the right half a new patch)."""
    p = seg.patches[label]
    right = p.pixels[:, 1] >= np.median(p.pixels[:, 1])
    new_id = len(seg.patches)
    labels = seg.labels.copy()
    labels[p.pixels[right, 0], p.pixels[right, 1]] = new_id
    a = Patch(p.id, p.pixels[~right], int((~right).sum()), p.surface_type, p.fit, p.small, p.noisy)
    b = Patch(new_id, p.pixels[right], int(right.sum()), p.surface_type, p.fit, p.small, p.noisy)
    patches = list(seg.patches)
    patches[label] = a
    return replace(seg, labels=labels, patches=(*patches, b))


def test_a_surface_left_in_two_pieces_is_one_patch_again(mockup_scan):
    scan, truth, seg = mockup_scan
    whole = describe(scan, segmentation=seg)
    # no two truth patches are merged: touching surfaces of one class are different surfaces
    assert len(whole.patches) == len(describe(scan, DescribeParams(merge_explained=False), segmentation=seg).patches)
    # the largest truth patch of a pipe side: a cylinder the segmenter could have left in two pieces
    cyl = max((p for p in whole.patches if p.label == "CYL"), key=lambda p: p.n_pixels)
    split = _split(seg, cyl.id)
    kept = describe(scan, DescribeParams(merge_explained=False), segmentation=split)
    assert len(kept.patches) == len(whole.patches) + 1
    merged = describe(scan, segmentation=split)
    assert len(merged.patches) == len(whole.patches)  # no truth patch was merged with another
    assert np.array_equal(merged.labels >= 0, whole.labels >= 0)
    p = next(q for q in merged.patches if q.id == cyl.id)
    assert p.n_pixels == cyl.n_pixels and np.array_equal(p.pixels, cyl.pixels)
    assert p.label == "CYL"
    assert p.classification.invariants["radius_m"][0] == pytest.approx(cyl.classification.invariants["radius_m"][0],
                                                                          rel=1e-3)
    assert merged.segmentation is split  # the segmenter's own labels stay as they were


def test_merge_test_tells_one_surface_from_two():
    rng = np.random.default_rng(5)
    # one cylinder (radius 0.1 m, axis along x, 2 m away), seen in two halves along its axis
    x = rng.uniform(-0.4, 0.4, 4000)
    phi = rng.uniform(-1.2, 1.2, 4000)
    pts = np.column_stack([x, 0.1 * np.sin(phi), 2.0 - 0.1 * np.cos(phi)])
    sig = np.full(len(pts), 3e-4)
    pts += rng.normal(0, 3e-4, pts.shape)
    a, b = x < 0, x >= 0
    fa, fb = fit_cylinder(pts[a], sig[a]), fit_cylinder(pts[b], sig[b])
    got = merge_test(fa, pts[a], sig[a], fb, pts[b], sig[b])
    assert got is not None and got[1] < 0 and got[0].radius == pytest.approx(0.1, rel=0.01)
    # the other half of a pipe of another radius (a reducer's next pipe) is not the same surface
    pts2 = pts.copy()
    pts2[b, 1:] = (pts2[b, 1:] - [0.0, 2.0]) * 0.8 + [0.0, 2.0 - 0.02]
    fb2 = fit_cylinder(pts2[b], sig[b])
    assert merge_test(fa, pts[a], sig[a], fb2, pts2[b], sig[b]) is None
    # two parallel planes 5 sigma apart are two surfaces; a cylinder and a plane never merge
    q = np.column_stack([rng.uniform(-1, 1, (2000, 2)), np.full(2000, 3.0)]) + rng.normal(0, 1e-3, (2000, 3))
    s2 = np.full(2000, 1e-3)
    q[1000:, 2] += 5e-3
    assert merge_test(fit_plane(q[:1000], s2[:1000]), q[:1000], s2[:1000], fit_plane(q[1000:], s2[1000:]),
                      q[1000:], s2[1000:]) is None
    assert merge_test(fa, pts[a], sig[a], fit_plane(q[:1000], s2[:1000]), q[:1000], s2[:1000]) is None


def test_local_scatter_measures_neighbouring_ranges_against_the_sigma():
    """About 1 for a surface whose noise is the model's, k for noise k times the model's; NaN and no count
    without three consecutive pixels."""
    from recognition.describe import local_scatter, scatter_limit

    H, W = 40, 50
    rng = np.random.default_rng(3)
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    surface = 2.0 + 0.01 * u + 0.002 * v + 1e-4 * (u - 25.0) ** 2  # a tilted, gently curved surface
    sigma = np.full(H * W, 0.004)
    pix = np.arange(H * W)
    for k in (1.0, 20.0):
        r = (surface + k * 0.004 * rng.standard_normal((H, W))).ravel()
        s, n = local_scatter(r, sigma, pix, (H, W))
        assert n == H * (W - 2) + (H - 2) * W and s == pytest.approx(k, rel=0.1)
    checker = np.flatnonzero((u + v).ravel() % 2 == 0)  # no two pixels of a row or column adjacent
    assert np.isnan(local_scatter(r, sigma, checker, (H, W))[0])
    assert scatter_limit(3.0, 10000, 3.0) == pytest.approx(3.1, abs=0.01) and scatter_limit(3.0, 8, 0.0) == 3.0


def test_a_patch_not_better_than_noise_is_unsure(mockup_scan):
    """A real patch keeps its label; its ranges shuffled among its pixels (the same values, no surface) make it
    OTH at under 0.5 for every class; the test can be switched off."""
    scan, _, seg = mockup_scan  # the truth segmentation: no segmenter run
    desc = describe(scan, DescribeParams(merge_explained=False), seg)
    big = max(desc.patches, key=lambda p: p.n_pixels)
    assert big.label != "OTH" and not big.classification.reason
    noisy = scan.range.copy().ravel()
    noisy[big.pixels] = np.random.default_rng(0).permutation(noisy[big.pixels])
    noisy = noisy.reshape(scan.range.shape)
    shuffled = replace(scan, range=noisy, points=scan.points / scan.range[..., None] * noisy[..., None])
    got = describe(shuffled, DescribeParams(merge_explained=False), seg)
    p = next(q for q in got.patches if q.id == big.id)
    assert p.label == "OTH" and p.classification.reason.startswith("support not better than noise")
    assert max(p.classification.probabilities.values()) < 0.5 and p.classification.primitive is None
    off = describe(shuffled, DescribeParams(merge_explained=False, max_local_scatter=None), seg)
    assert not next(q for q in off.patches if q.id == big.id).classification.reason.startswith("support")
    with pytest.raises(ValueError, match="max_local_scatter"):
        DescribeParams(max_local_scatter=0.0)
    with pytest.raises(ValueError, match="min_scatter_triples"):
        DescribeParams(min_scatter_triples=2)


def test_pixels_outside_the_support_extend_a_patch_but_not_its_classification(mockup_scan):
    """A pipe's patch given a two-pixel band of the surfaces around it, outside Segmentation.support (as the
    border completion gives limb pixels): its classification is the pipe's alone, to the bit; with the band in
    the support the fit sees it."""
    import scipy.ndimage as ndi

    scan, truth, seg = mockup_scan
    params = DescribeParams(merge_explained=False)
    clean = describe(scan, params, segmentation=seg)
    cyl = max((p for p in clean.patches if p.label == "CYL"), key=lambda p: p.n_pixels)
    mask = seg.labels == cyl.id
    band = ndi.binary_dilation(mask, iterations=2) & ~mask & (seg.labels >= 0)
    assert band.sum() >= 50
    labels = np.where(band, cyl.id, seg.labels)
    patches = []
    for p in seg.patches:
        rows, cols = np.nonzero(labels == p.id)
        patches.append(Patch(p.id, np.stack([rows, cols], axis=1), int(rows.size), p.surface_type, p.fit, p.small,
                             p.noisy))
    grown = replace(seg, labels=labels, patches=tuple(patches))
    kept = describe(scan, params, segmentation=replace(grown, support=(seg.labels >= 0) & ~band))
    seen = describe(scan, params, segmentation=replace(grown, support=None))
    pipe_kept, pipe_seen = (next(q for q in d.patches if q.id == cyl.id) for d in (kept, seen))
    assert pipe_kept.n_pixels == cyl.n_pixels + int(band.sum())
    assert pipe_kept.label == "CYL"
    assert pipe_kept.classification.invariants["radius_m"][0] == cyl.classification.invariants["radius_m"][0]
    assert pipe_seen.classification.invariants.get("radius_m", (None,))[0] != \
        cyl.classification.invariants["radius_m"][0]
