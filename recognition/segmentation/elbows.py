"""Segmentation step 9b (decimated grids only), elbow joins: adjacent patches that one ring torus fits, and no
cylinder, become one patch (the pieces of a pipe elbow).

An elbow is a torus section, which no quadric fits: its inner side is hyperbolic and its outer side elliptic,
so its H-K seeds differ across it, and merging (step 5) tests unions with a quadric. Close to the sensor a large
elbow is then left in two to four pieces (on the calibration suite's Kinect-like frames, elbows of 5000 pixels
or more were found whole in 2 of 10). Here each pair of adjacent curved patches is fitted with a cylinder and a
ring torus (:func:`recognition.fitting.fit_torus`) on a regular sample of their union: they join when the torus
fits within ``torus_join_k`` sigma, bends no wider than ``torus_join_max_bend`` tube radii (an elbow, not a
slightly bowed pipe), and the cylinder fits ``torus_join_cylinder_ratio`` times worse (a straight tube is
merging's, and the torus of a straight tube fits it as well). A pipe and its elbow do not join: their union
bends at one end only, which neither fits.
"""

from __future__ import annotations

import numpy as np

from recognition.fitting.cylinder import fit_cylinder
from recognition.fitting.torus import fit_torus

from .grid import _border_pairs, _groups, _State, _subsample
from .types import SegmentationParams

__all__: list[str] = []


def _join_elbow_pieces(labels: np.ndarray, st: _State, params: SegmentationParams, jump_h: np.ndarray,
                       jump_v: np.ndarray) -> np.ndarray:
    """Join adjacent patches that one ring torus fits and no cylinder (module docstring); returns the labels.

    Pairs sharing at least ``torus_join_min_border`` non-jump border pixels, each of at least
    ``torus_join_min_pixels`` pixels and neither planar (its plane fits within ``2 torus_join_k`` sigma), are
    tested longest border first; after a join the pairs of the joined patch are tested again (a third piece of
    the same elbow). Deterministic: ties of border length go by the lower label pair.

    Parameters
    ----------
    labels : ndarray of shape (H, W), int
        Patch labels (-1 none) of the full-resolution grid whose flattened arrays ``st`` holds.
    st : the full-resolution grid's state (points, noise-scaled sigmas).
    jump_h, jump_v : ndarray of shape (H, W - 1) and (H - 1, W), bool
        The grid's jump pairs: patches touching only across a jump are not adjacent.
    """
    if params.torus_join_k is None:
        return labels
    out = labels.copy()
    flat = out.ravel()
    groups = _groups(out)
    pairs, counts = _border_pairs(out, jump_h, jump_v)
    border = {(int(a), int(b)): int(n) for (a, b), n in zip(pairs.tolist(), counts.tolist(), strict=True) if a < b}
    planar: dict[int, bool] = {}
    tested: set[tuple[int, int, int, int]] = set()
    while True:
        joined = None
        for (a, b), n in sorted(border.items(), key=lambda kv: (-kv[1], kv[0])):
            ga, gb = groups[a], groups[b]
            if n < params.torus_join_min_border or min(ga.size, gb.size) < params.torus_join_min_pixels:
                continue
            key = (a, b, ga.size, gb.size)
            if key in tested:
                continue
            tested.add(key)
            if _is_planar(a, ga, st, params, planar) or _is_planar(b, gb, st, params, planar):
                continue
            if _one_elbow(np.union1d(ga, gb), st, params):
                joined = (a, b)
                break
        if joined is None:
            return out
        a, b = joined
        flat[groups[b]] = a
        groups[a] = np.union1d(groups[a], groups.pop(b))
        planar.pop(a, None)
        merged: dict[tuple[int, int], int] = {}
        for (p, q), n in border.items():  # b's borders become a's; a's border with b is inside it now
            p, q = (a if p == b else p), (a if q == b else q)
            if p != q:
                key2 = (min(p, q), max(p, q))
                merged[key2] = merged.get(key2, 0) + n
        border = merged


def _is_planar(label: int, idx: np.ndarray, st: _State, params: SegmentationParams, memo: dict[int, bool]) -> bool:
    """Whether the total-least-squares plane of a regular sample of the patch's pixels ``idx`` fits within
    ``2 torus_join_k`` sigma (RMS of the residuals in units of their sigmas); memoised in ``memo``."""
    if label not in memo:
        sub = _subsample(idx, params.torus_join_fit_points)
        pts, sig = st.X[sub], st.S[sub]
        centred = pts - pts.mean(axis=0)
        normal = np.linalg.svd(centred, full_matrices=False)[2][2]
        memo[label] = bool(np.sqrt(np.mean((centred @ normal / sig) ** 2)) <= 2 * params.torus_join_k)
    return memo[label]


def _one_elbow(idx: np.ndarray, st: _State, params: SegmentationParams) -> bool:
    """Whether a ring torus fits the pixels ``idx`` (a regular sample of ``torus_join_fit_points``) as an elbow
    and a cylinder does not (module docstring)."""
    n_pts = params.torus_join_fit_points
    sub = _subsample(idx, n_pts)
    pts, sig = st.X[sub], st.S[sub]
    k = params.torus_join_k
    cylinder = fit_cylinder(pts, sig, max_points=n_pts)
    if cylinder.ok and cylinder.rms_sigma <= k:
        return False  # a straight tube
    torus = fit_torus(pts, sig, cylinder=cylinder if cylinder.ok else None, max_points=n_pts)
    return bool(torus.ok and torus.rms_sigma <= k
                and torus.major_radius <= params.torus_join_max_bend * torus.minor_radius
                and (not cylinder.ok or cylinder.rms_sigma >= params.torus_join_cylinder_ratio * torus.rms_sigma))
