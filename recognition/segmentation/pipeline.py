"""The segmentation's entry point, :func:`segment`: the steps of section 3 of Fillatreau & Fisher (and this
implementation's additions, numbered as in :mod:`recognition.segmentation`) in one explicit list."""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from recognition.tuning import AUTO

from .curvature import _curvature_step, classify_hk, curvature_images
from .edges import _edge_image, _image_grid
from .elbows import _join_elbow_pieces
from .final_fits import _finalise
from .grid import _Grid, _neighbour_links, _upsampler
from .growing import _grow_patches
from .merging import _merge, _merge_patches
from .peel import _drop_fragments, _peel_weak
from .reassignment import _complete_borders, _reassign
from .refinement import _refine_full
from .seeds import _seeds
from .splits import _split_patches
from .types import CurvatureImages, EdgeType, Segmentation, SegmentationParams

__all__ = ["segment"]


def segment(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams | None = None,
            steps: dict[str, float] | None = None) -> Segmentation:
    """Segment an organised range image into H-K surface patches with plane / quadric fits.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame (x right, y down, z forward)
        NaN where there is no return.
    sigma : ndarray of shape (H, W), metres
        Range-noise sigma along the ray per pixel (NaN where no return); floored at ``sigma_floor_m``.
    params : SegmentationParams, optional
    steps : dict, optional
        Receives the process time (s) of each step, added to what it holds under the step's name (``edges``,
        ``curvature``, ``seeds``, ``growing``, ``merging`` on the segmentation grid, then ``full resolution``,
        ``merging at full resolution``, ``splits``, ``reassignment``, ``elbow joins``, ``peel``, ``border completion``,
        ``final fits``): where a frame's time goes, for ``python -m harness.bench.segmentation --steps``.

    Returns
    -------
    Segmentation
        Empty (no patches, all labels -1) for an image without usable returns (e.g. all NaN, 1x1).

    Raises
    ------
    ValueError
        For arrays of the wrong shape or negative sigma.
    """
    params = SegmentationParams() if params is None else params
    lap = _Laps(steps)
    pts, sig = _check_inputs(points, sigma)
    shape = sig.shape
    image = _image_grid(pts, sig, params)  # 4, 6: jump pairs (edges) and the self-calibrated noise
    if image is None:
        return _empty(shape)
    full, declared, scale = image
    d = params.step(shape)
    coarse = d > 1  # VGA-class images (>= 400 rows, unless `decimation` says otherwise)
    if params.split_seeds == AUTO:
        params = replace(params, split_seeds=coarse)
    # steps 2-5 run on the segmentation grid: every d-th pixel of a coarse image (pixel counts of the params
    # scaled by 1 / d²), the image itself otherwise
    grid, grid_params = (full.decimated(d, params), params.scaled(d)) if coarse else (full, params)
    lap("edges")
    cur, hk, crease, wide, edges = _curvature_step(grid, grid_params)  # 1-4: curvature, H-K classes, creases
    lap("curvature")
    if not (hk > 0).any():
        return _curvature_only(full, params)
    st = grid.state(hk)
    links = _neighbour_links(grid.shape, grid.valid, grid.jump_h, grid.jump_v)
    seeds = _seeds(hk, edges, wide, st, grid_params)  # 5, 8: seeds, cut where one surface does not fit them
    lap("seeds")
    labels = _grow_patches(seeds, st, grid_params, grid.valid, links, grid.jump_h, grid.jump_v)  # 5: growing
    lap("growing")
    labels = _merge_patches(labels, st, grid_params, grid.valid, grid.jump_h, grid.jump_v)  # 5: merging
    lap("merging")
    if coarse:  # the grid's images back at full resolution
        up = _upsampler(shape, d)
        labels, hk, crease = up(labels), up(hk), up(crease)
        cur = CurvatureImages(*(up(a) for a in (cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals,
                                                 cur.sigma_normal)))
        st = full.state(hk)
    # steps 7-9b run on coarse images only: 7 brings the coarse labels back to full resolution, and the merge at
    # full resolution, the splits (8) and the reassignment (9) were built and tuned on what the coarse grid
    # leaves (its blocks and tiles) on VGA-class frames. An image under 400 rows is segmented at full resolution
    # without them (on the real box scans, 245 x 276, the reassignment turned two warped faces into CONE:
    # SegmentationParams.reassign_rounds)
    if coarse:
        links = _neighbour_links(shape, full.valid, full.jump_h, full.jump_v)  # (the full-resolution grid's)
        labels = _refine_full(labels, st, params, full.valid, links, full.jump_h, full.jump_v, d)  # 7
        lap("full resolution")
        labels = _merge(labels, st, params, full.jump_h, full.jump_v)  # 5 again (before the cuts: it would undo them)
        lap("merging at full resolution")
        labels = _split_patches(labels, st, params, cur.normals.reshape(-1, 3), full.jump_h, full.jump_v)  # 8
        lap("splits")
        if params.reassign_rounds:
            labels = _reassign(labels, st, params, links, full.jump_h, full.jump_v)  # 9
        lap("reassignment")
        labels = _join_elbow_pieces(labels, st, params, full.jump_h, full.jump_v)  # 9b
        lap("elbow joins")
    edges = _edge_image(shape, full.jump_h, full.jump_v)
    edges[crease] |= np.uint8(EdgeType.CREASE)
    labels = _peel_weak(labels, params, full.jump_h, full.jump_v)  # 10
    labels = _drop_fragments(labels, params, full.ranges, full.jump_h, full.jump_v)  # 10
    lap("peel")
    support = labels >= 0  # what the fits rest on: not the pixels the completion adds
    labels = _complete_borders(labels, st, params, links, cur.normals.reshape(-1, 3))  # 11
    lap("border completion")
    labels, patches = _finalise(labels, st, params, declared.ravel(), support.ravel())  # plane / quadric fits
    lap("final fits")
    return Segmentation(labels, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges, patches, scale,
                        support)


def _check_inputs(points: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = np.asanyarray(points, dtype=np.float64)
    if p.ndim != 3 or p.shape[2] != 3 or p.shape[0] < 1 or p.shape[1] < 1:
        raise ValueError(f"expected points of shape (H, W, 3), got {p.shape}")
    s = np.asanyarray(sigma, dtype=np.float64)
    if s.shape != p.shape[:2]:
        raise ValueError(f"expected sigma of shape {p.shape[:2]} (H, W), got {s.shape}")
    if np.any(s < 0):
        raise ValueError("sigma must be >= 0 (NaN where no return)")
    return p, s


def _empty(shape: tuple[int, int], hk=None, Hc=None, Kc=None, sH=None, sK=None, nrm=None, edges=None):
    nan = np.full(shape, np.nan)
    return Segmentation(
        labels=np.full(shape, -1, dtype=np.int32),
        hk_class=np.zeros(shape, np.int8) if hk is None else hk,
        H=nan.copy() if Hc is None else Hc,
        K=nan.copy() if Kc is None else Kc,
        sigma_H=nan.copy() if sH is None else sH,
        sigma_K=nan.copy() if sK is None else sK,
        normals=np.full(shape + (3,), np.nan) if nrm is None else nrm,
        edges=np.zeros(shape, np.uint8) if edges is None else edges,
        patches=(),
    )


def _curvature_only(grid: _Grid, params: SegmentationParams) -> Segmentation:
    """An image without any patch (no defined curvature anywhere): curvature images and edges only."""
    cur = curvature_images(grid.points, grid.sigma, params, (grid.jump_h, grid.jump_v))
    hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    edges = _edge_image(grid.shape, grid.jump_h, grid.jump_v)
    return _empty(grid.shape, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges)


class _Laps:
    """Process time of consecutive steps, added to ``into[name]`` in seconds (nothing when ``into`` is None)."""

    def __init__(self, into: dict[str, float] | None):
        self.into = into
        self.t = time.process_time()

    def __call__(self, name: str) -> None:
        if self.into is not None:
            t = time.process_time()
            self.into[name] = self.into.get(name, 0.0) + t - self.t
            self.t = t
