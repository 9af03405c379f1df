"""The quick surface fits behind growing, merging and splitting (section 3 of Fillatreau & Fisher: patches
are grown and merged by surface fitting): a total-least-squares plane or a Taubin quadric per group of
pixels, batched over many groups, with the residual of each point along its ray in sigma units; the plane-pair
test of a quadric.

The batched fits give each group the fit :func:`_quick_fit` gives it alone. The quadric's parameters follow
:mod:`recognition.fitting.algebra` (its monomial basis, gradient and normalisation, here applied to all groups
at once).
"""

from __future__ import annotations

import numpy as np

from recognition.fitting import (
    MIN_GRAZING,
    MONOMIAL_GRADIENT,
    gradient,
    monomials,
    normalisation_map,
    plane_params,
    quadric_matrices,
    taubin_fit,
)

from . import kernels
from .derivatives import norm3
from .grid import _planar_groups, _rms, _State, _subsample
from .types import SegmentationParams

#: below this, the second-smallest eigenvalue of a group's normalised monomial moments (``M / trace M``) says
#: that two or more quadrics fit its points exactly: the points determine no quadric
UNDETERMINED_QUADRIC = 1e-12


def _normalised(x: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Points (N, 3) centred and scaled to unit RMS radius: ``(y, scale, mean)``."""
    mean = x.mean(axis=0)
    scale = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1)))) or 1.0
    return (x - mean) / scale, scale, mean


def quadric_undetermined(x: np.ndarray) -> bool:
    """Whether the points ``x`` (N, 3) determine no quadric: fewer than 10, or two or more independent quadrics
    fit them exactly (:data:`UNDETERMINED_QUADRIC`).

    A strip of pixels one row or one column wide lies exactly on the plane through the sensor that holds its
    rays, and every quadric containing that plane fits it; the fit's eigenvector is then any vector of that null
    space, chosen by the rounding of the floating-point path (numpy's SIMD width, the BLAS kernel): labels that
    changed with the machine (``python -m harness.bench.stability``). Such a group is fitted with a plane.
    """
    if len(x) < 10:
        return True
    D = monomials(_normalised(x)[0])
    M = D.T @ D
    tr = float(np.trace(M))
    return bool(tr <= 0 or np.linalg.eigvalsh(M / tr)[1] < UNDETERMINED_QUADRIC)


def _quick_fit(x: np.ndarray, u: np.ndarray, s: np.ndarray, planar: bool,
               want_params: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """Plane (TLS) or quadric (unit-norm LSQ) fit; its parameters (10,) in metres and the ray z-residuals.

    ``x`` points (N, 3), ``u`` their unit rays, ``s`` their sigmas. The residual of each point is the range
    change putting it on the surface to first order, in sigma units (the incidence cosine floored at 0.25).
    Points that determine no quadric (:func:`quadric_undetermined`, fewer than 10 among them) get the plane.
    """
    if planar or quadric_undetermined(x):
        if len(x) < 3:
            return (np.full(10, np.nan) if want_params else None), np.full(len(x), np.inf)
        c = x.mean(axis=0)
        d = x - c
        _, V = np.linalg.eigh(d.T @ d)
        n = V[:, 0]
        f = d @ n
        g = np.broadcast_to(n, x.shape)
        p = plane_params(n, float(n @ c)) if want_params else None
        scale = 1.0
    else:
        y, scale, mean = _normalised(x)
        D = monomials(y)
        pn, _ = taubin_fit(D, y, np.ones(len(y)))
        if pn is None:
            _, V = np.linalg.eigh(D.T @ D)
            pn = V[:, 0]
        f = D @ pn
        g = gradient(pn, y)
        p = None
        if want_params:
            p = normalisation_map(mean, scale) @ pn
            p /= np.linalg.norm(p)
    gr = np.sum(g * u, axis=1)
    floor = MIN_GRAZING * norm3(g)
    gr = np.where(np.abs(gr) < floor, floor, np.abs(gr))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = scale * np.abs(f) / (gr * s)
    return p, np.where(np.isfinite(z), z, np.inf)


# ------------------------------------------------------------------------------------- batched fits


_UPPER3 = np.triu_indices(3)


def _group_sums(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Sums of ``values`` (N, ...) over the contiguous groups beginning at ``starts``."""
    return np.add.reduceat(values, starts, axis=0)


def _group_grams(A: np.ndarray, starts: np.ndarray, cnt: np.ndarray) -> np.ndarray:
    """Gram matrices ``A_g' A_g`` (G, k, k) of the contiguous row groups of ``A`` (N, k)."""
    return np.stack([A[s:s + c].T @ A[s:s + c] for s, c in zip(starts.tolist(), cnt.tolist(), strict=True)])


def _symmetric(upper: np.ndarray, n: int, iu) -> np.ndarray:
    out = np.zeros((upper.shape[0], n, n))
    out[:, iu[0], iu[1]] = upper
    out[:, iu[1], iu[0]] = upper
    return out


def _plane_fits(X, U, S, gid, starts, cnt):
    """Total-least-squares planes of the groups: parameters (G, 10) and per-point ray z-residuals (N,)."""
    mean = _group_sums(X, starts) / cnt[:, None]
    d = X - mean[gid]
    C = _group_sums(d[:, [0, 0, 0, 1, 1, 2]] * d[:, [0, 1, 2, 1, 2, 2]], starts)
    _, V = np.linalg.eigh(_symmetric(C, 3, _UPPER3))
    n = V[:, :, 0]
    f = np.einsum("ij,ij->i", d, n[gid])
    gr = np.maximum(np.abs(np.einsum("ij,ij->i", U, n[gid])), MIN_GRAZING)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(f) / (gr * S)
    P = np.zeros((len(cnt), 10))
    P[:, 6:9] = n
    P[:, 9] = -np.einsum("ij,ij->i", n, mean)
    bad = cnt < 3
    P[bad] = np.nan
    z[bad[gid]] = np.inf
    return P, np.where(np.isfinite(z), z, np.inf)


# Taubin's normalisation N9 = sum_k G_k' S4 G_k (G_k = MONOMIAL_GRADIENT[k]) as a linear map of S4's 16 entries
_TAUBIN_MAP = np.einsum("kmi,knj->mnij", MONOMIAL_GRADIENT, MONOMIAL_GRADIENT)[:, :, :9, :9].reshape(16, 81)


def _quadric_fits(X, U, S, gid, starts, cnt):
    """Taubin quadrics of the groups (unit-norm algebraic fit where Taubin's is undefined), in normalised
    coordinates per group: parameters (G, 10) in metres and per-point ray z-residuals (N,). The groups whose
    points determine no quadric (:func:`quadric_undetermined`) get their planes (:func:`_plane_fits`).

    Per-point quantities are laid out by rows (one contiguous row per monomial or coordinate): the products
    below then run on contiguous memory.
    """
    G = len(cnt)
    mean = _group_sums(X, starts) / cnt[:, None]
    d = X - mean[gid]
    scale = np.sqrt(_group_sums(np.einsum("ij,ij->i", d, d), starts) / cnt)
    scale = np.where(scale > 0, scale, 1.0)
    yT = (d / scale[gid, None]).T.copy()
    DT = monomials(yT, axis=0)  # (10, N)
    M = np.stack([DT[:, s:s + c] @ DT[:, s:s + c].T for s, c in zip(starts.tolist(), cnt.tolist(), strict=True)])
    S4 = M[:, 6:, 6:]  # the moments of (x, y, z, 1), the last four monomials
    N9 = (S4.reshape(G, 16) @ _TAUBIN_MAP).reshape(G, 9, 9)
    tr = np.trace(M, axis1=1, axis2=2)
    ev = np.linalg.eigvalsh(M / np.where(tr > 0, tr, 1.0)[:, None, None])
    undetermined = (tr <= 0) | (ev[:, 1] < UNDETERMINED_QUADRIC)
    evn = np.linalg.eigvalsh(N9)
    ok = ~undetermined & (evn[:, 0] > 1e-12 * np.maximum(evn[:, -1], 1e-300)) & (M[:, 9, 9] > 0)
    N9 = np.where(ok[:, None, None], N9, np.eye(9))
    m99 = np.where(ok, M[:, 9, 9], 1.0)
    Sg = M[:, :9, :9] - M[:, :9, 9:10] @ M[:, 9:10, :9] / m99[:, None, None]
    L = np.linalg.cholesky(N9)
    A = np.linalg.solve(L, Sg)
    A = np.linalg.solve(L, A.transpose(0, 2, 1))
    _, W = np.linalg.eigh(0.5 * (A + A.transpose(0, 2, 1)))
    q = np.linalg.solve(L.transpose(0, 2, 1), W[:, :, :1])[:, :, 0]
    c = -np.einsum("gi,gi->g", M[:, 9, :9], q) / m99
    pn = np.column_stack([q, c])
    if not ok.all():
        _, V = np.linalg.eigh(M[~ok])
        pn[~ok] = V[:, :, 0]
    pn /= np.linalg.norm(pn, axis=1, keepdims=True)
    p = pn.T if G == 1 else pn.T.take(gid, axis=1)  # (10, 1) broadcast, or (10, N): each point's quadric
    f = np.einsum("ij,ij->j", DT, np.broadcast_to(p, DT.shape))
    z = _ray_z(p, yT, U, S, scale[gid] * f)  # |s f| = s |f|: back to metres
    # back to metres (normalisation_map of every group at once, written out): A / s², b / s - 2 A m / s², ...
    Ay = pn[:, [0, 3, 4, 3, 1, 5, 4, 5, 2]].reshape(G, 3, 3)
    Am = np.einsum("gij,gj->gi", Ay, mean)
    is2 = 1.0 / scale**2
    P = np.empty((G, 10))
    P[:, :6] = pn[:, :6] * is2[:, None]
    P[:, 6:9] = pn[:, 6:9] / scale[:, None] - 2.0 * Am * is2[:, None]
    P[:, 9] = np.einsum("gi,gi->g", mean, Am) * is2 - np.einsum("gi,gi->g", pn[:, 6:9], mean) / scale + pn[:, 9]
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    if undetermined.any():
        sel = np.flatnonzero(undetermined)
        rows = undetermined[gid]  # the groups' rows are contiguous and in order
        sub = cnt[sel]
        P[sel], z[rows] = _plane_fits(X[rows], U[rows], S[rows], np.repeat(np.arange(sel.size), sub),
                                      np.concatenate([[0], np.cumsum(sub)[:-1]]), sub)
    return P, z


def _quick_fits(idx_list: list[np.ndarray], planar: np.ndarray, st: _State):
    """:func:`_quick_fit` of many groups (flat pixel indices each): parameters (G, 10), per-group z arrays.

    Groups of fewer than 10 points get planes, as in :func:`_quick_fit`. The compiled
    :func:`.kernels.quick_fits` (one pass over each group's points for its moments, then the same solution as
    :func:`_quadric_fits`); :func:`_quick_fits_reference` is the batched numpy of the same fits. A group
    fitted before on ``st`` (the same pixels in the same order, plane or quadric alike) takes that fit from
    ``st.fits``; the z arrays are read only.
    """
    G = len(idx_list)
    idx_list = [np.asarray(i).astype(np.int64, copy=False) for i in idx_list]
    plane = np.asarray(planar, np.bool_)
    # a group's fit depends on its pixels, their order and whether it gets a plane, not on the other groups:
    # those fitted before on this state come from its cache (st.fits), the others are fitted in one batch
    keys = [(bool(plane[g]) or i.size < 10, i.tobytes()) for g, i in enumerate(idx_list)]
    todo = [g for g in range(G) if keys[g] not in st.fits]
    if todo:
        cnt = np.fromiter((idx_list[g].size for g in todo), np.int64, len(todo))
        starts = np.zeros(len(todo), np.int64)
        np.cumsum(cnt[:-1], out=starts[1:])
        ix = np.concatenate([idx_list[g] for g in todo])
        P, z, singular = kernels.quick_fits(st.X, st.U, st.S, ix, starts, cnt, plane[todo], _TAUBIN_MAP,
                                            UNDETERMINED_QUADRIC)
        for k in np.flatnonzero(singular):  # a numerically singular Taubin system: the one-by-one fit's fallback
            i = idx_list[todo[k]]
            P[k], z[starts[k]:starts[k] + cnt[k]] = _quick_fit(st.X[i], st.U[i], st.S[i], False)
        z.flags.writeable = False  # shared by the cache's entries: read only
        for k, g in enumerate(todo):
            st.fits[keys[g]] = (P[k], z[starts[k]:starts[k] + cnt[k]])
    fits = [st.fits[key] for key in keys]
    return np.array([f[0] for f in fits]).reshape(G, 10), [f[1] for f in fits]


def _quick_fits_reference(idx_list: list[np.ndarray], planar: np.ndarray, st: _State):
    """:func:`_quick_fits` in batched numpy (its reference): parameters (G, 10), per-group z arrays."""
    G = len(idx_list)
    P = np.full((G, 10), np.nan)
    zs: list[np.ndarray] = [np.zeros(0)] * G
    cnt_all = np.array([len(i) for i in idx_list])
    use_plane = np.asarray(planar, bool) | (cnt_all < 10)
    for flag, fitter in ((True, _plane_fits), (False, _quadric_fits)):
        sel = np.flatnonzero((use_plane == flag) & (cnt_all > 0))
        if sel.size == 0:
            continue
        cnt = cnt_all[sel]
        ix = np.concatenate([idx_list[k] for k in sel])
        gid = np.repeat(np.arange(sel.size), cnt)
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        try:
            Pk, z = fitter(st.X.take(ix, axis=0), st.U.take(ix, axis=0), st.S.take(ix), gid, starts, cnt)
        except np.linalg.LinAlgError:  # a numerically singular group: fit them one by one
            fits = [_quick_fit(st.X[idx_list[k]], st.U[idx_list[k]], st.S[idx_list[k]], flag) for k in sel]
            Pk, z = np.array([f[0] for f in fits]), np.concatenate([f[1] for f in fits])
        P[sel] = Pk
        for j, s0, n in zip(sel.tolist(), starts.tolist(), cnt.tolist(), strict=True):
            zs[j] = z[s0:s0 + n]
    for k in np.flatnonzero(cnt_all == 0):
        zs[k] = np.zeros(0)
    return P, zs


def _quick_fits_of(groups: dict[int, np.ndarray], keys: list[int], st: _State,
                   params: SegmentationParams) -> dict[int, np.ndarray]:
    """The quick fit (plane or quadric by the patch's H-K classes, on a subsample) of each patch ``keys`` of
    ``groups``, in one batch: ``{label: parameters (10,)}``."""
    P, _ = _quick_fits([_subsample(groups[k], params.max_fit_points) for k in keys],
                       _planar_groups([groups[k] for k in keys], st.hk), st)
    return dict(zip(keys, P, strict=True))


def _trim_threshold(z: np.ndarray, trim: float) -> float:
    """``max(trim, 3 median(z))`` for residuals ``z >= 0``; counting instead of sorting when the middle
    element(s) are within ``trim / 3``."""
    n = z.size
    m = (n + 1) // 2  # rank of the (lower) middle element
    within = int(np.count_nonzero(3.0 * z <= trim))
    if within >= m + (n % 2 == 0):  # the middle element(s) within: so is their mean
        return trim
    return max(trim, 3.0 * float(np.median(z)))


def _fit_groups(groups: dict[int, np.ndarray], st: _State, params: SegmentationParams, n_labels: int,
                trim: float | None = None) -> np.ndarray:
    """Plane / quadric parameters (n_labels, 10) of each group (on a subsample of its pixels).

    With ``trim``, each fit is repeated once without the points whose residual exceeds ``trim`` sigma (and
    3x the median residual): a few points of another surface ruin an algebraic quadric fit.
    """
    P = np.full((max(n_labels, 1), 10), np.nan)
    if not groups:
        return P
    labs = list(groups)
    subs = [_subsample(groups[k], params.max_fit_points) for k in labs]
    planar = _planar_groups([groups[k] for k in labs], st.hk)
    Pg, zs = _quick_fits(subs, planar, st)
    # not a plane after all: curvature undefined (thin pipes: every window crosses a jump) or within its
    # noise (a pipe seen close up by a fine-grained sensor, whose windows span a few mm)
    rms = [_rms(z) for z in zs]
    retry = [k for k in range(len(labs)) if planar[k] and subs[k].size >= 20 and not rms[k] <= params.merge_k]
    if retry:
        Pq, zq = _quick_fits([subs[k] for k in retry], np.zeros(len(retry), bool), st)
        for j, k in enumerate(retry):
            # ... but not two faces across a blurred crease, which a plane pair fits exactly
            if _rms(zq[j]) < 0.5 * rms[k] and not _is_plane_pair(Pq[j], st.X[subs[k]], params.plane_pair_tol):
                planar[k], Pg[k], zs[k] = False, Pq[j], zq[j]
    if trim is not None:
        redo = []
        for k in range(len(labs)):
            if subs[k].size < 10:
                continue
            keep = zs[k] <= _trim_threshold(zs[k], trim)
            if 10 <= keep.sum() < subs[k].size:
                subs[k] = subs[k][keep]
                redo.append(k)
        if redo:
            Pg[redo], _ = _quick_fits([subs[k] for k in redo], planar[redo], st)
    P[labs] = Pg
    return P


# ---------------------------------------------------------------------------------------- residuals


def _pixel_residuals(P: np.ndarray, lab: np.ndarray, X: np.ndarray, U: np.ndarray, S: np.ndarray) -> np.ndarray:
    """|range residual| in sigma of points X (N, 3) to the surfaces P[lab] (per point), as in _quick_fit: the
    compiled :func:`.kernels.ray_z_by_label`, equal to ``_ray_z(P.T.take(lab, axis=1), X.T.copy(), U, S)``."""
    f64 = np.float64
    return kernels.ray_z_by_label(np.ascontiguousarray(P, f64), np.ascontiguousarray(lab, np.int64),
                                  np.ascontiguousarray(X, f64), np.ascontiguousarray(U, f64),
                                  np.ascontiguousarray(S, f64))


def _ray_z(p: np.ndarray, x: np.ndarray, U: np.ndarray, S: np.ndarray, f: np.ndarray | None = None) -> np.ndarray:
    """|range residual| in sigma of points to quadrics, as in :func:`_quick_fit`: the quadric's value over its
    gradient's component along the ray (floored at ``MIN_GRAZING`` of the gradient's norm), inf where undefined.

    Laid out by rows, so that the element-wise products run on contiguous memory: ``p`` (10, N) each point's
    quadric, or (10, 1) one for all; ``x`` (3, N) the points' coordinates; ``U`` (N, 3) unit rays; ``S`` (N,)
    sigmas; ``f`` (N,) the quadric's values at the points, when already at hand.
    """
    x0, x1, x2 = x
    g0, g1, g2 = gradient(p, x, axis=0)
    if f is None:  # m(x) . p, written out
        f = (p[0] * x0 * x0 + p[1] * x1 * x1 + p[2] * x2 * x2
             + 2 * (p[3] * x0 * x1 + p[4] * x0 * x2 + p[5] * x1 * x2)
             + p[6] * x0 + p[7] * x1 + p[8] * x2 + p[9])
    u0, u1, u2 = U.T
    gr = np.abs(g0 * u0 + g1 * u1 + g2 * u2)
    floor = MIN_GRAZING * np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.abs(f) / (np.maximum(gr, floor) * S)
    return np.where(np.isfinite(z), z, np.inf)


# -------------------------------------------------------------------------------------- plane pairs


def _is_plane_pair(p: np.ndarray, x: np.ndarray, tol: float) -> bool:
    """True when the quadric ``p`` (10,) is, over the extent of points ``x`` (N, 3), two intersecting planes.

    ``A`` of rank 2 with eigenvalues of opposite signs, the linear term within its range and the canonical
    constant near zero: ``(n1 . y)(n2 . y) = 0``. Each test is relative to the largest eigenvalue, on the
    scale of the points' RMS radius ``R`` (``tol`` for the rank and constant).
    """
    if not np.all(np.isfinite(p)):
        return False
    A, b, c = quadric_matrices(p)
    lam, V = _eig_by_magnitude(A)
    l1 = abs(lam[0])
    if l1 == 0 or abs(lam[2]) > tol * l1 or lam[0] * lam[1] >= 0:
        return False  # (decided by A alone: before the points' moments)
    mean = x.mean(axis=0)
    R = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1)))) or 1.0
    # in centred coordinates: f = y'Ay + (2 A mean + b)'y + f(mean)
    b0 = 2 * A @ mean + b
    c0 = float(mean @ A @ mean + b @ mean + c)
    bv = V.T @ b0
    if abs(bv[2]) > tol * l1 * R:
        return False
    t = -0.5 * bv[:2] / lam[:2]  # centre within the range of A
    c_cano = c0 + 0.5 * float(bv[:2] @ t)
    return abs(c_cano) <= tol * l1 * R * R


def _eig_by_magnitude(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (3,) of the symmetric ``A`` by decreasing magnitude, and their eigenvectors (columns)."""
    lam, V = np.linalg.eigh(A)
    order = np.argsort(-np.abs(lam))
    return lam[order], V[:, order]


def _plane_pair_sides(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Side (0 or 1) of each point ``x`` (N, 3): the nearer of the two planes of the plane-pair quadric ``p``.

    With ``A = l1 v1 v1' + l2 v2 v2'`` (``l1 > 0 > l2``) and centre ``t`` (``2 A t = -b``, in the range of
    ``A``), the quadric is ``(m+ . (y - t)) (m- . (y - t))`` with ``m± = sqrt(l1) v1 ± sqrt(-l2) v2``.
    """
    A, b, _ = quadric_matrices(p)
    lam, V = _eig_by_magnitude(A)
    if lam[0] < 0:
        lam = -lam
    t = np.linalg.pinv(A, rcond=1e-6) @ (-0.5 * b)
    m1 = np.sqrt(lam[0]) * V[:, 0] + np.sqrt(-lam[1]) * V[:, 1]
    m2 = np.sqrt(lam[0]) * V[:, 0] - np.sqrt(-lam[1]) * V[:, 1]
    y = x - t
    d1 = np.abs(y @ m1) / np.linalg.norm(m1)
    d2 = np.abs(y @ m2) / np.linalg.norm(m2)
    return (d2 < d1).astype(np.int8)
