"""One's own segmentation into the core's: :func:`segmentation_from_labels` turns a label image (from any
segmenter) into a :class:`recognition.segmentation.Segmentation`, so that the core's classifiers, matching and
change detection run on it (``describe(scan, params, segmentation=...)``)."""

from __future__ import annotations

import numpy as np

from recognition.describe import core_sigma
from recognition.fitting import PlaneFit, QuadricSurfaceFit, fit_plane_lsq, fit_quadric_lsq
from recognition.segmentation import (
    Patch,
    Segmentation,
    SegmentationParams,
    SurfaceType,
    classify_hk,
    curvature_images,
)
from sensors.range_image import Scan

__all__ = ["segmentation_from_labels"]


def segmentation_from_labels(labels: np.ndarray, scan: Scan, params: SegmentationParams | None = None) -> Segmentation:
    """The core's segmentation of ``scan`` with the patches of a label image.

    Each distinct non-negative value of ``labels`` on the scan's returns becomes one patch (a value whose
    pixels are not connected stays one patch); patches are renumbered ``0 .. n-1`` by decreasing size (ties:
    the first pixel in raster order), as :func:`recognition.segmentation.segment` numbers them. What the
    classifier needs of a segmentation is computed as the segmenter computes it, from the scan alone: unit
    normals and H-K curvature from its masked local quadratic fits (``params.window``, never across depth
    jumps) with the noise model's sigma, each patch's dominant H-K class (its ``surface_type``: planar patches
    get the planar hint), its final plane or quadric fit and its ``small`` / ``noisy`` flags
    (``params.min_patch_pixels``, ``params.noisy_k``). Edges are not computed (all 0).

    Parameters
    ----------
    labels : ndarray of shape (H, W), integer
        Patch label per pixel; negative for none. Pixels without a return are left out whatever their label.
    scan : Scan
        The scan the labels segment (its sensor and noise model give the per-pixel sigma).
    params : SegmentationParams, optional
        ``window``, ``zero_k``, ``jump_k``, ``jump_tan``, ``sigma_floor_m``, ``final_fit_points``,
        ``min_patch_pixels`` and ``noisy_k`` are used.

    Returns
    -------
    Segmentation
        ``labels`` (int32, -1 for none), curvature images, normals (NaN where undefined), patches;
        ``noise_scale`` None.

    Raises
    ------
    ValueError
        For labels of another shape than the scan's range image, or not integers.

    Examples
    --------
    >>> segmentation = segmentation_from_labels(my_labels, scan)                  # doctest: +SKIP
    >>> description = describe(scan, DescribeParams(), segmentation=segmentation)  # doctest: +SKIP
    """
    params = SegmentationParams() if params is None else params
    lab = np.asanyarray(labels)
    shape = tuple(np.shape(scan.range))
    if lab.shape != shape:
        raise ValueError(f"labels must have the scan's shape {shape} (H, W), got {lab.shape}")
    if not (np.issubdtype(lab.dtype, np.integer) or lab.dtype == bool):
        raise ValueError(f"labels must be integers (negative for none), got dtype {lab.dtype}")
    sigma = core_sigma(scan)
    valid = np.asarray(scan.valid, dtype=bool) & np.isfinite(sigma)
    sig = np.where(valid, np.maximum(sigma, params.sigma_floor_m), np.nan)
    pts = np.where(valid[..., None], np.asarray(scan.points, dtype=np.float64), np.nan)
    h, w = shape
    if valid.any():
        cur = curvature_images(pts, sig, params)
        curv = (cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals)
        hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    else:  # no returns: no curvature, no patch
        nan = np.full(shape, np.nan)
        curv = (nan, nan.copy(), nan.copy(), nan.copy(), np.full((*shape, 3), np.nan))
        hk = np.zeros(shape, np.int8)
    flat = np.where(valid & (lab >= 0), lab, -1).reshape(-1).astype(np.int64)
    pix = np.flatnonzero(flat >= 0)
    values, first, inverse, counts = np.unique(flat[pix], return_index=True, return_inverse=True, return_counts=True)
    order = sorted(range(len(values)), key=lambda k: (-int(counts[k]), int(pix[first[k]])))
    out = np.full(h * w, -1, dtype=np.int32)
    by_value = np.argsort(inverse, kind="stable")
    groups = np.split(pix[by_value], np.cumsum(counts)[:-1]) if len(values) else []
    flat_pts, flat_sig, flat_hk = pts.reshape(-1, 3), sig.reshape(-1), hk.reshape(-1)
    patches = []
    for new, k in enumerate(order):
        idx = groups[k]
        out[idx] = new
        n_class = np.bincount(flat_hk[idx], minlength=5)
        stype = SurfaceType(int(np.argmax(n_class[1:])) + 1) if n_class[1:].sum() else SurfaceType.NONE
        sub = idx[:: max(1, -(-idx.size // params.final_fit_points))]
        fit: PlaneFit | QuadricSurfaceFit
        if stype in (SurfaceType.PLANAR, SurfaceType.NONE) or sub.size < 10:
            fit = fit_plane_lsq(flat_pts[sub], flat_sig[sub])
        else:
            fit = fit_quadric_lsq(flat_pts[sub], flat_sig[sub])
        r, c = np.divmod(idx, w)
        patches.append(Patch(id=new, pixels=np.stack([r, c], axis=1), n_pixels=int(idx.size), surface_type=stype,
                             fit=fit, small=bool(idx.size < params.min_patch_pixels),
                             noisy=bool((not fit.ok) or not (fit.rms_sigma <= params.noisy_k)),
                             class_counts=tuple(int(v) for v in n_class)))
    H, K, sigma_H, sigma_K, normals = curv
    return Segmentation(out.reshape(shape), hk, H, K, sigma_H, sigma_K, normals, np.zeros(shape, np.uint8),
                        tuple(patches))
