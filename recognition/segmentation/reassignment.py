"""Segmentation step 9 (decimated grids only), border reassignment: a border pixel moves to the neighbouring
patch whose surface fits it clearly better (the paper's patches are maximal sets one surface fits, section 3 of
Fillatreau & Fisher; the coarse grid's blocks and tiles leave borders a few pixels off); and step 11, border
completion (:func:`_complete_borders`: unlabelled pixels join the linked patch whose surface fits them)."""

from __future__ import annotations

import numpy as np

from recognition.fitting.algebra import gradient

from . import kernels
from .grid import _groups, _State
from .quick_fits import _fit_groups, _pixel_residuals
from .types import SegmentationParams


def _flat_links(links, width: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`._neighbour_links` on the flattened image: the flat index offset of each direction (4,) and whether
    each pixel's link that way is allowed (4, H*W)."""
    return (np.array([dr * width + dc for dr, dc, _ in links]), np.stack([o.ravel() for _, _, o in links]))


def _reassign(labels: np.ndarray, st: _State, params: SegmentationParams, links, jump_h: np.ndarray,
              jump_v: np.ndarray) -> np.ndarray:
    """Move border pixels to the neighbouring patch whose surface fits them clearly better (returns new labels).

    Tiles, blocks of the coarse grid and merges leave patches whose border runs a few pixels past the
    surface's own (a tile straddling a pipe and its reducer, a pipe strip that took a row of its elbow). A
    pixel linked (no jump) to another patch moves there when its range residual to that patch's surface is
    within ``2 grow_k`` sigma and ``reassign_margin`` sigma smaller than to its own; the patches that changed are
    refitted (those of more than ``reassign_refit_pixels`` pixels hardly move and are not) and the pixels next to the
    moved ones tested again, for at most ``reassign_rounds`` rounds. Pixels near a crease fit both faces within the
    margin and stay. ``links``: :func:`_neighbour_links` of the grid.

    A fragment (fewer than ``min_patch_pixels`` pixels: a strip of limb and mixed returns along a jump) has
    no residual of its own worth comparing, since its fit follows its few pixels: each of its pixels moves to
    a linked patch whose surface fits it within ``2 grow_k`` sigma. Hoover's metric counts a fragment lying
    inside a truth region as an over-segmentation of it (correct detection 0.758 -> 0.800 on the default
    suite, 0.740 -> 0.811 on the calibration suite).
    """
    rounds, margin = params.reassign_rounds, params.reassign_margin
    H, W = labels.shape
    out = labels.copy()
    flat = out.ravel()
    n = int(flat.max()) + 1
    if n < 2:
        return out
    thr = 2.0 * params.grow_k
    groups = _groups(out)
    P = _fit_groups(groups, st, params, n, trim=thr)
    steps, ok = _flat_links(links, W)
    # first candidates: labelled pixels with a linked neighbour of another patch
    diff_h = (out[:, :-1] != out[:, 1:]) & ~jump_h & (out[:, :-1] >= 0) & (out[:, 1:] >= 0)
    diff_v = (out[:-1, :] != out[1:, :]) & ~jump_v & (out[:-1, :] >= 0) & (out[1:, :] >= 0)
    border = np.zeros((H, W), bool)
    border[:, :-1] |= diff_h
    border[:, 1:] |= diff_h
    border[:-1, :] |= diff_v
    border[1:, :] |= diff_v
    cand = np.flatnonzero(border)
    small = {k: v for k, v in groups.items() if v.size <= params.reassign_refit_pixels}
    fragment = np.zeros(n, bool)
    fragment[[k for k, v in groups.items() if v.size < params.min_patch_pixels]] = True
    for _ in range(rounds):
        if cand.size == 0:
            break
        own = flat[cand]
        best_l = _targets(flat, P, st, cand, steps, ok, fragment, margin, thr)
        mv = best_l != own
        if not mv.any():
            break
        moved, src, dst = cand[mv], own[mv], best_l[mv]
        flat[moved] = dst
        # refit the small patches that lost or gained pixels (a large one hardly changes); a patch's pixels that
        # moved are those no longer labelled with it, the others keep their order and the gained ones follow
        redo = {}
        for lab in np.unique(np.concatenate([src, dst])).tolist():
            if lab in small:
                v = small[lab]
                v = np.concatenate([v[flat[v] == lab], moved[dst == lab]])
                small[lab] = redo[lab] = v
        redo = {k: v for k, v in redo.items() if v.size}
        if redo:
            Pc = _fit_groups(redo, st, params, n, trim=thr)
            keys = list(redo)
            P[keys] = Pc[keys]
        cand = kernels.next_candidates(flat, cand, moved, steps, ok)
    return out


def _targets(flat: np.ndarray, P: np.ndarray, st: _State, cand: np.ndarray, steps: np.ndarray, ok: np.ndarray,
             fragment: np.ndarray, margin: float, thr: float) -> np.ndarray:
    """Each candidate pixel's label after one round of :func:`_reassign` (N,): the compiled
    :func:`.kernels.reassign_targets`, whose reference is :func:`_targets_reference`.

    ``flat`` (H*W,) labels, ``P`` (G, 10) each label's quadric, ``cand`` (N,) flat pixel indices (labelled),
    ``steps`` and ``ok`` of :func:`_flat_links`, ``fragment`` (G,) bool, ``margin`` and ``thr`` in sigma.
    """
    return kernels.reassign_targets(flat, P, st.X, st.U, st.S, cand, steps, ok, fragment, float(margin), float(thr))


def _targets_reference(flat: np.ndarray, P: np.ndarray, st: _State, cand: np.ndarray, steps: np.ndarray,
                       ok: np.ndarray, fragment: np.ndarray, margin: float, thr: float) -> np.ndarray:
    """:func:`_targets` in numpy, one direction at a time for all candidates."""
    nb = cand[None, :] + steps[:, None]
    nl = np.where(ok[:, cand], flat[np.clip(nb, 0, flat.size - 1)], -1)
    own = flat[cand]
    x, u, s = st.X[cand], st.U[cand], st.S[cand]
    best_z = _pixel_residuals(P, own, x, u, s)
    best_z[fragment[own]] = np.inf
    best_l = own.astype(np.int64)
    for k in range(len(steps)):
        m = (nl[k] >= 0) & (nl[k] != own)
        if not m.any():
            continue
        z = np.full(cand.size, np.inf)
        z[m] = _pixel_residuals(P, nl[k, m], x[m], u[m], s[m])
        b = (z + margin < best_z) & (z <= thr)
        best_z[b] = z[b]
        best_l[b] = nl[k, b]
    return best_l


def _completion_targets(flat: np.ndarray, P: np.ndarray, st: _State, cand: np.ndarray, steps: np.ndarray,
                        ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each candidate pixel ``cand`` (N,) of :func:`_complete_borders`: the linked neighbour's patch whose
    surface ``P`` leaves it the smallest residual and that residual: the compiled
    :func:`.kernels.completion_targets`, whose reference is :func:`_completion_targets_reference`."""
    return kernels.completion_targets(flat, P, st.X, st.U, st.S, cand, steps, ok)


def _completion_targets_reference(flat: np.ndarray, P: np.ndarray, st: _State, cand: np.ndarray, steps: np.ndarray,
                                  ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each candidate pixel ``cand`` (N,) of :func:`_complete_borders`: the linked neighbour's patch whose
    surface ``P`` leaves it the smallest residual (a tie goes to the lower label) and that residual, -1 and inf
    without one; numpy, one direction at a time (the reference of :func:`.kernels.completion_targets`)."""
    nb = np.where(ok[:, cand], flat[np.clip(cand[None, :] + steps[:, None], 0, flat.size - 1)], -1)
    x, u, s = st.X[cand], st.U[cand], st.S[cand]
    best_z = np.full(cand.size, np.inf)
    best_l = np.full(cand.size, -1)
    for k in range(len(steps)):
        m = nb[k] >= 0
        if not m.any():
            continue
        z = np.full(cand.size, np.inf)
        z[m] = _pixel_residuals(P, nb[k, m], x[m], u[m], s[m])
        b = (z < best_z) | ((z == best_z) & (nb[k] >= 0) & (nb[k] < best_l))  # a tie goes to the lower label
        best_z[b] = z[b]
        best_l[b] = nb[k, b]
    return best_l, best_z


def _next_candidates_reference(flat: np.ndarray, cand: np.ndarray, moved: np.ndarray, steps: np.ndarray,
                               ok: np.ndarray) -> np.ndarray:
    """The sorted union of the candidates ``cand`` and the labelled pixels linked to a ``moved`` one (the
    reference of :func:`.kernels.next_candidates`)."""
    nxt = (moved[None, :] + steps[:, None])[ok[:, moved]]
    return np.union1d(cand, nxt[flat[nxt] >= 0])


def _complete_borders(labels: np.ndarray, st: _State, params: SegmentationParams, links,
                      normals: np.ndarray) -> np.ndarray:
    """Give unlabelled pixels with a return to the linked patch whose surface fits them best (returns new
    labels).

    Growing admits a pixel within ``grow_k`` sigma of a patch's surface as it stands during growing; the peel
    and the fragment drop then leave borders and limbs unlabelled: the band along a thin pipe's limbs (where a
    quadric fitted to a few pixels across errs most along the grazing rays), the border of a face the
    coarse grid's blocks did not reach, the pixels of a dropped fragment. Each round, every unlabelled pixel
    with a return linked (no jump) to a patch of ``min_region_pixels`` or more joins the one whose trimmed
    fit (:func:`._fit_groups`, fitted once, so that a patch cannot creep along its own extrapolation) leaves
    it the smallest range residual, when that is within ``complete_k`` sigma and its normal (where defined) is
    within ``face_min_angle_deg`` of the surface's there (near a crease the neighbouring face's pixels fit the
    face's plane within the noise: a far box's faces, a wall's top seen at grazing); at most
    ``complete_rounds`` rounds, a ring of pixels each. A smaller patch's fit does not extrapolate, and grown
    past that size it would be scored and classified on pixels it did not grow to. The pixels given stay out
    of the patch's fit and classification (:attr:`Segmentation.support`). ``links``:
    :func:`._neighbour_links` of the image; ``normals`` (H*W, 3) the pixels' unit normals
    (NaN where undefined). Off when ``complete_k`` is None.
    """
    if params.complete_k is None:
        return labels
    # only patches of a region's size: a smaller one's fit does not extrapolate, and grown past that size it
    # would be scored, and classified, on pixels it did not grow to
    groups = {k: v for k, v in _groups(labels).items() if v.size >= params.min_region_pixels}
    if not groups:
        return labels
    W = labels.shape[1]
    out = labels.copy()
    flat = out.ravel()
    P = _fit_groups(groups, st, params, int(flat.max()) + 1, trim=2.0 * params.grow_k)
    steps, ok = _flat_links(links, W)
    has_return = np.isfinite(st.X[:, 2])
    min_cos = np.cos(np.deg2rad(params.face_min_angle_deg))
    for _ in range(params.complete_rounds):
        cand = np.flatnonzero((flat < 0) & has_return)
        if cand.size == 0:
            break
        best_l, best_z = _completion_targets(flat, P, st, cand, steps, ok)
        take = best_z <= params.complete_k
        if not take.any():
            break
        g = gradient(P[best_l[take]], st.X[cand[take]])
        cos = np.abs(np.einsum("ij,ij->i", g, normals[cand[take]])) / np.linalg.norm(g, axis=1)
        take[take] = ~(cos < min_cos)  # NaN (no normal, or no gradient) passes
        if not take.any():
            break
        flat[cand[take]] = best_l[take]
    return out
