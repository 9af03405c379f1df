"""Segmentation's last step (section 3 of Fillatreau & Fisher: "planes or quadrics are fitted to the patches"):
patches relabelled by decreasing size, each with its plane or quadric fit and its flags."""

from __future__ import annotations

import numpy as np

from recognition.fitting import PlaneFit, QuadricSurfaceFit, fit_plane_lsq, fit_quadric_lsq

from .grid import _groups, _State, _subsample
from .types import Patch, SegmentationParams, SurfaceType


def _finalise(labels: np.ndarray, st: _State, params: SegmentationParams, declared: np.ndarray,
              support: np.ndarray | None = None):
    """Relabel 0..n-1 by decreasing size and fit the final plane / quadric of every patch.

    Fits (and so ``rms_sigma`` and the ``noisy`` flag) are in units of the *declared* sigma, not of the
    self-calibrated one: a sensor much noisier than its model says still gives noisy patches. ``support``
    (H*W,) bool: the pixels the fits rest on (:attr:`Segmentation.support`; all when None).
    """
    groups = _groups(labels)
    order = sorted(groups, key=lambda k: (-groups[k].size, int(groups[k][0])))
    out = np.full(labels.shape, -1, dtype=np.int32)
    flat = out.ravel()
    W = labels.shape[1]
    patches = []
    for new, old in enumerate(order):
        idx = groups[old]
        flat[idx] = new
        counts = np.bincount(st.hk[idx], minlength=5)
        stype = SurfaceType(int(np.argmax(counts[1:])) + 1) if counts[1:].sum() else SurfaceType.NONE
        sub = _subsample(idx if support is None else idx[support[idx]], params.final_fit_points)
        x, s = st.X[sub], declared[sub]
        fit: PlaneFit | QuadricSurfaceFit
        if stype == SurfaceType.PLANAR or sub.size < 10:
            fit = fit_plane_lsq(x, s)
        else:
            fit = fit_quadric_lsq(x, s)
        noisy = (not fit.ok) or not (fit.rms_sigma <= params.noisy_k)
        r, c = np.divmod(idx, W)
        patches.append(
            Patch(
                id=new,
                pixels=np.stack([r, c], axis=1),
                n_pixels=int(idx.size),
                surface_type=stype,
                fit=fit,
                small=bool(idx.size < params.min_patch_pixels),
                noisy=bool(noisy),
                class_counts=tuple(int(v) for v in counts),
            )
        )
    return out, tuple(patches)
