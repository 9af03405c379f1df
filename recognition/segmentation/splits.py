"""Segmentation step 8 (decimated grids only): patches that one surface does not fit are cut - along the
crease of a plane pair, into the faces k-planes finds, or along a pipe's axis where its radius profile bends (a
pipe merged with its reducer or elbow). Section 3 of Fillatreau & Fisher merges by surface fitting; these cuts
undo the merges of pieces of different surfaces that the noise let through."""

from __future__ import annotations

import numpy as np

from recognition.fitting import MIN_GRAZING, fit_cylinder
from scenes.geometry import perpendicular_basis

from .grid import _bin_medians, _groups, _rms, _State, _subsample
from .merging import _absorb_fragments
from .quick_fits import _is_plane_pair, _plane_pair_sides, _quick_fits
from .types import SegmentationParams


def _split_patches(labels: np.ndarray, st: _State, params: SegmentationParams, normals: np.ndarray,
                   jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Step 8 at full resolution: plane pairs and faces (:func:`_split_plane_pairs`), the fragments that leaves
    into the face they belong to, then cuts along the axis (:func:`_split_along_axis`, ``normals`` (H*W, 3))."""
    split = _split_plane_pairs(labels, st, params, cut_faces=True)
    if split is not labels:  # a split-off side too small to stand alone goes to the face it belongs to
        labels = _absorb_fragments(split, st, params, jump_h, jump_v)
    if params.axis_split_pixels is not None:
        labels = _split_along_axis(labels, st, params, normals)
    return labels


def _split_plane_pairs(labels: np.ndarray, st: _State, params: SegmentationParams,
                       cut_faces: bool = False) -> np.ndarray:
    """Cut each patch that no plane fits (RMS beyond ``merge_k``) but a plane pair does (two faces of a far,
    small box whose crease the curvature could not see, reassembled from noisy tiles) along its crease,
    when each side then fits its own plane. With ``cut_faces``, a patch that no quadric fits either is cut
    into the two or three faces that fit planes (:func:`_faces`)."""
    groups = {k: v for k, v in _groups(labels).items() if v.size >= 2 * params.min_patch_pixels}
    if not groups:
        return labels
    labs = list(groups)
    subs = [_subsample(groups[k], params.max_fit_points) for k in labs]
    _, zp = _quick_fits(subs, np.ones(len(labs), bool), st)
    bad = [j for j in range(len(labs)) if not _rms(zp[j]) <= params.merge_k]
    if not bad:
        return labels
    Pq, zq = _quick_fits([subs[j] for j in bad], np.zeros(len(bad), bool), st)
    out = labels
    nxt = int(labels.max()) + 1
    for q, z, j in zip(Pq, zq, bad, strict=True):
        idx = groups[labs[j]]
        if _is_plane_pair(q, st.X[subs[j]], params.plane_pair_tol):
            side = _plane_pair_sides(q, st.X[idx])
            pieces = [idx[side == 0], idx[side == 1]]
            if min(h.size for h in pieces) < params.min_patch_pixels:
                continue
            _, zh = _quick_fits([_subsample(h, params.max_fit_points) for h in pieces], np.ones(2, bool), st)
            if not all(_rms(z) <= params.merge_k for z in zh):
                continue
        elif not _rms(z) <= params.merge_k and cut_faces:
            # no quadric fits either: the pixels mixed at the crease spoil the plane pair
            pieces = _faces(idx, st, params)
        else:
            continue
        if out is labels and pieces:
            out = labels.copy()
        for piece in pieces[1:]:
            out.reshape(-1)[piece] = nxt
            nxt += 1
    return out


def _k_planes(x: np.ndarray, u: np.ndarray, s: np.ndarray, k: int, params: SegmentationParams) -> np.ndarray | None:
    """Part (0 .. k-1) of each point ``x`` (N, 3) by k planes fitted alternately (k-planes, at most
    ``kplanes_iterations`` times): each point goes to the plane nearest along its ray ``u`` (in its sigmas
    ``s``), each plane is refitted to its points.

    Started by sequential RANSAC: the plane through three of the points (``kplanes_trials`` triples, a fixed
    seed: deterministic) with most points within ``kplanes_inlier_k`` sigmas, refitted on them, then the next
    one among the points left. A start from the pixels' normals (k mutually distant ones) put a far box's
    narrow top and its front in one part: its normals are too noisy there. None when a part empties."""
    iterations, inlier_z, trials = params.kplanes_iterations, params.kplanes_inlier_k, params.kplanes_trials
    n_pts = len(x)
    if n_pts < 3 * k:
        return None
    gen = np.random.default_rng(0)

    def dist(c, n):
        return np.abs((x - c) @ n) / (np.maximum(np.abs(u @ n), MIN_GRAZING) * s)

    def plane_of(m):
        c = x[m].mean(axis=0)
        return c, np.linalg.eigh((x[m] - c).T @ (x[m] - c))[1][:, 0]

    left = np.ones(n_pts, bool)
    planes = []
    for _ in range(k):
        pool = np.flatnonzero(left)
        if pool.size < 3:
            return None
        tri = x[pool[gen.integers(0, pool.size, size=(trials, 3))]]  # (trials, 3 points, 3)
        nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(nrm, axis=1)
        good = norm > 1e-12
        if not good.any():
            return None
        nrm, c0 = nrm[good] / norm[good, None], tri[good, 0]
        # inlier counts of all candidates at once: (candidates, points) distances along the rays
        z = np.abs(np.einsum("cj,cj->c", nrm, c0)[:, None] - nrm @ x[pool].T)
        z /= np.maximum(np.abs(nrm @ u[pool].T), MIN_GRAZING) * s[pool]
        b = int(np.argmax((z <= inlier_z).sum(axis=1)))
        inl = np.zeros(n_pts, bool)
        inl[pool[z[b] <= inlier_z]] = True
        for _ in range(3):
            if inl.sum() < 3:
                return None
            inl = (dist(*plane_of(inl)) <= inlier_z) & left
        if inl.sum() < 3:
            return None
        planes.append(plane_of(inl))
        left &= ~inl
    part = np.argmin(np.stack([dist(c, n) for c, n in planes]), axis=0)
    for _ in range(iterations):
        z = np.full((k, n_pts), np.inf)
        for j in range(k):
            m = part == j
            if m.sum() < 3:
                return None
            z[j] = dist(*plane_of(m))
        new = np.argmin(z, axis=0)
        if np.array_equal(new, part):
            break
        part = new
    return part


def _broad(x: np.ndarray, s: np.ndarray, ratio: float) -> bool:
    """Whether points ``x`` (N, 3) spread across their plane (the narrower in-plane standard deviation) over
    ``ratio`` times their median sigma ``s``: a face, not a strip of a pipe that the noise lets pass for flat."""
    c = x.mean(axis=0)
    w = np.linalg.eigvalsh((x - c).T @ (x - c) / len(x))
    return bool(np.sqrt(max(w[1], 0.0)) >= ratio * float(np.median(s)))


def _trimmed_rms(z: np.ndarray, keep: float) -> float:
    """RMS of the smallest ``keep`` share of ``z`` (the pixels mixed at a crease are the rest)."""
    return _rms(np.sort(z)[: max(int(keep * z.size), 1)])


def _faces(idx: np.ndarray, st: _State, params: SegmentationParams) -> list[np.ndarray]:
    """The two or three faces (:func:`_k_planes`) of the patch of pixels ``idx`` that each fit a plane within
    ``1.5 merge_k`` (but for the ``1 - face_keep`` of their pixels mixed at the creases: a far box's faces are a
    few pixels wide), are broad against the noise (:func:`_broad`, ``face_broad_ratio``) and meet at
    ``face_min_angle_deg`` or more (not one face with a few stray pixels); [] when there are none. Of three
    parts, one parallel to a face, at that angle or more from the other and of at most half that face's pixels
    is the face's layer (returns mixed at its edge, or a piece of the surface behind it) and goes with it,
    unchecked. (Larger parallel parts were facets of a near pipe on the first phase's ``calibration`` suite.)"""
    face_cos = np.cos(np.radians(params.face_min_angle_deg))
    for k in (2, 3):
        part = _k_planes(st.X[idx], st.U[idx], st.S[idx], k, params)
        if part is None:
            continue
        faces = [idx[part == j] for j in range(k)]
        Pf, zf = _quick_fits([_subsample(f, params.max_fit_points) for f in faces], np.ones(k, bool), st)
        cos = np.abs(Pf[:, 6:9] @ Pf[:, 6:9].T)
        pairs = [(i, j) for i in range(k) for j in range(i + 1, k)]
        parallel = [(i, j) for i, j in pairs if cos[i, j] > face_cos]
        layer = host = None
        if k == 3 and len(parallel) == 1:
            host, layer = sorted(parallel[0], key=lambda j: -faces[j].size)
            if 2 * faces[layer].size > faces[host].size:
                host = layer = None
        keep = [j for j in range(k) if j != layer]
        if min(faces[j].size for j in keep) < params.min_patch_pixels or \
                not all(_broad(st.X[faces[j]], st.S[faces[j]], params.face_broad_ratio) for j in keep):
            continue
        if all(cos[i, j] <= face_cos for i, j in pairs if i in keep and j in keep) and \
                all(_trimmed_rms(zf[j], params.face_keep) <= 1.5 * params.merge_k for j in keep):
            if layer is not None:
                faces[host] = np.sort(np.concatenate([faces[host], faces[layer]]))
            return [faces[j] for j in keep]
    return []


# ----------------------------------------------------------------------------------- along the axis


def _split_along_axis(labels: np.ndarray, st: _State, params: SegmentationParams, normals: np.ndarray) -> np.ndarray:
    """Cut curved patches along their axis where the radius changes.

    Under strong noise a pipe, its reducer and the next pipe (or a pipe and its elbow) join smoothly enough
    for one quadric to fit their union within the noise, and the curvature classes cannot tell a 5 deg cone
    from a cylinder. Along the axis of a cylinder fitted to the patch, the median distance of its points to
    the axis (per slice half a radius long) is constant over a pipe, linear over a reducer, and turns at a
    join: the patch is cut there (:func:`_axial_pieces`). Applied ``axis_split_passes`` times, so that a piece
    holding a reducer and a pipe is cut again.
    """
    out = labels
    for _ in range(params.axis_split_passes):
        nxt = int(out.max()) + 1
        changed = False
        big = [idx for idx in _groups(out).values() if idx.size >= params.axis_split_pixels]
        # curved: no plane fits it (the H-K classes are no guide: under strong noise a pipe's are mostly planar)
        samples = [_subsample(v, params.max_fit_points) for v in big]
        _, zp = _quick_fits(samples, np.ones(len(big), bool), st)
        curved = [k for k in range(len(big)) if not _rms(zp[k]) <= params.merge_k]
        _, zq = _quick_fits([samples[k] for k in curved], np.zeros(len(curved), bool), st)
        for k, z in zip(curved, zq, strict=True):
            idx = big[k]
            # one quadric fits the patch within noise: a sphere or a dome is not cut into pipes
            side = _axial_pieces(st.X[idx], st.S[idx], normals[idx], params.min_region_pixels, params,
                                 several_axes=not _rms(z) <= params.merge_k)
            if side is None:
                continue
            if out is labels:
                out = labels.copy()
            out.reshape(-1)[idx[side == 1]] = nxt
            nxt += 1
            changed = True
        if not changed:
            break
    return out


def _axial_pieces(x: np.ndarray, s: np.ndarray, n: np.ndarray, min_pixels: int, params: SegmentationParams,
                  several_axes: bool = True) -> np.ndarray | None:
    """Two pieces (0 and 1 per point) of a curved patch along its axis, or None when it is one surface.

    The axis is the direction the normals turn about (shared by a pipe and its reducer); the patch is cut
    into slices half a radius long along it (longer on a far, thin pipe, so that they hold ``axial_slice_points``
    points on average: its slices had 5-10, and none was used); a slice counts with ``axial_partial_fraction`` of
    the median slice's points (not one the patch's border crosses). A
    cylinder's slices keep one median distance to the axis, a cone's change it linearly (so does a cylinder's
    under a slightly tilted axis), so the profile of one surface is a line, within
    ``max(3 sigma of the median, axial_flat_fraction * radius)`` per slice. A profile that is not is cut where two
    lines, fitted on either side, explain it best, or, when no two do, at the first cut of the three lines
    that do (a reducer between two pipes: on the default suite's Kinect-like frames, correct detection 0.554
    -> 0.594); each side needs ``axial_min_bins`` slices and at least ``min_pixels`` points and a tenth of the
    patch. A patch whose profile about the axis of a cylinder fitted
    to it is one line is not cut (a pipe whose normals gave a slightly tilted axis).

    ``x`` points (N, 3), ``s`` their range sigmas (N,), ``n`` their unit normals (N, 3) (NaN where undefined);
    the section is fitted on ``axial_fit_points`` of them.
    """
    fit_points = params.axial_fit_points
    ok = np.isfinite(n).all(axis=1)
    if ok.sum() < 20:
        return None
    w = np.linalg.eigvalsh(n[ok].T @ n[ok])
    if w[1] < 0.05 * w.sum():
        return None  # the normals barely turn (a plane)
    if w[0] > 0.05 * w.sum():
        # the normals do not turn about one axis: a doubly curved patch, or two pipes and their elbow
        return _dominant_cylinder(x, s, n, ok, min_pixels, params) if several_axes else None
    # the axis: the direction on which the normals' projection is most nearly constant (zero on a cylinder,
    # the sine of the half-angle on a cone; the normals' scatter itself tilts on a partly seen cone)
    axis = np.linalg.eigh(np.cov(n[ok].T))[1][:, 0]
    e1, e2 = perpendicular_basis(axis)
    sub = _subsample(np.arange(len(x)), fit_points)
    P = np.stack([x[sub] @ e1, x[sub] @ e2], axis=1)  # the section: an algebraic circle across the axis
    sol = np.linalg.lstsq(np.column_stack([2.0 * P, np.ones(len(P))]), np.sum(P**2, axis=1), rcond=None)[0]
    r2 = sol[2] + sol[:2] @ sol[:2]
    if not r2 > 0:
        return None
    centre, radius = sol[0] * e1 + sol[1] * e2, float(np.sqrt(r2))
    def too_small(side: np.ndarray | None) -> bool:
        return side is None or min(np.sum(side == 0), np.sum(side == 1)) < max(min_pixels, len(x) // 10)

    side = _axial_cut(x, s, centre, axis, radius, params)
    if too_small(side):
        return None
    # the normals' axis of a noisy pipe may be a degree off, which bends its profile: a pipe whose fitted
    # cylinder's profile is one line, or bends only where too few points lie to stand alone (its far end), is
    # one surface
    cyl = fit_cylinder(x[sub], s[sub], init=(centre, axis, radius), max_points=600, huber=1.5, max_iter=10)
    if cyl.ok and too_small(_axial_cut(x, s, cyl.point, cyl.axis, cyl.radius, params)):
        return None
    return side


def _dominant_cylinder(x: np.ndarray, s: np.ndarray, n: np.ndarray, ok: np.ndarray, min_pixels: int,
                       params: SegmentationParams) -> np.ndarray | None:
    """Two pieces (0 per point on the patch's dominant cylinder, 1 elsewhere) of a patch whose normals turn
    about more than one axis, or None.

    Two pipes joined by an elbow, merged under strong noise: the normals of each pipe lie on a great circle
    about its axis. The axis of the most populous circle comes from the normals' scatter, trimmed
    ``elbow_cut_rounds`` times to the ``elbow_cut_keep`` fraction nearest the circle; the pipe's section across
    it from the points and normals (``axial_fit_points`` of them, trimmed likewise), then a cylinder fitted from
    there, which takes the points within ``elbow_cut_k`` sigma of it. None unless that axis holds a clean
    circle, the fit succeeds and both pieces hold at least ``min_pixels`` points and a tenth of the patch.
    ``ok``: the points whose normal is defined.
    """
    fit_points, keep = params.axial_fit_points, params.elbow_cut_keep
    rounds, k = params.elbow_cut_rounds, params.elbow_cut_k
    nn = n[ok]
    near = np.ones(len(nn), bool)
    for _ in range(rounds):
        axis = np.linalg.eigh(nn[near].T @ nn[near])[1][:, 0]
        r = np.abs(nn @ axis)
        near = r <= np.quantile(r, keep)
    w = np.linalg.eigvalsh(nn[near].T @ nn[near])
    if w[0] > 0.05 * w.sum() * keep or w[1] < 0.05 * w.sum():
        return None  # no pipe among the normals: a doubly curved surface (a tank's dome, an elbow alone)
    on = np.flatnonzero(ok)[near]
    sub = on[_subsample(np.arange(on.size), fit_points)]
    # the section across the axis: each point of the pipe lies its radius along its normal from the pipe's
    # centre (p = c + R n, linear in c and R; the other pipe's points, seen across, do not); trimmed
    # ``rounds`` times to the points that agree best, it starts the cylinder fit
    e1, e2 = perpendicular_basis(axis)
    P = np.stack([x[sub] @ e1, x[sub] @ e2], axis=1)
    N = np.stack([n[sub] @ e1, n[sub] @ e2], axis=1)
    use = np.ones(len(P), bool)
    for _ in range(rounds):
        m = int(use.sum())
        A = np.zeros((2 * m, 3))
        A[0::2, 0] = A[1::2, 1] = 1.0
        A[:, 2] = N[use].reshape(-1)
        cx, cy, radius = np.linalg.lstsq(A, P[use].reshape(-1), rcond=None)[0]
        off = np.linalg.norm(P - [cx, cy] - radius * N, axis=1)
        use = off <= max(np.quantile(off, keep), k * float(np.median(s[sub])))
    if not radius > 0:
        return None
    sub = sub[use]
    cyl = fit_cylinder(x[sub], s[sub], init=(cx * e1 + cy * e2, axis, float(radius)), max_points=600, huber=1.5,
                       max_iter=10)
    if not cyl.ok:
        return None
    q = x - cyl.point
    t = q @ cyl.axis
    dist = np.abs(np.linalg.norm(q - np.outer(t, cyl.axis), axis=1) - cyl.radius)
    side = (dist > k * s).astype(np.int64)
    if min(np.sum(side == 0), np.sum(side == 1)) < max(min_pixels, len(x) // 10):
        return None
    return side


def _axial_cut(x: np.ndarray, s: np.ndarray, point: np.ndarray, axis: np.ndarray, radius: float,
               params: SegmentationParams) -> np.ndarray | None:
    """The cut of :func:`_axial_pieces` about the axis through ``point``: side (0 or 1) per point, or None."""
    min_bins, flat_fraction = params.axial_min_bins, params.axial_flat_fraction
    q = x - point
    t = q @ axis
    rho = np.linalg.norm(q - np.outer(t, axis), axis=1)
    # slices half a radius long, or longer on a far thin pipe: axial_slice_points points each on average (a
    # slice counts with 20)
    step = max(radius / 2.0, (t.max() - t.min()) * params.axial_slice_points / len(x))
    b = np.floor((t - t.min()) / step).astype(np.int64)
    nb = int(b.max()) + 1
    cnt = np.bincount(b, minlength=nb)
    full = np.flatnonzero(cnt >= 20)
    if full.size:  # not the slices the patch's border crosses (SegmentationParams.axial_partial_fraction)
        full = np.flatnonzero(cnt >= max(20.0, params.axial_partial_fraction * float(np.median(cnt[full]))))
    if full.size < 2 * min_bins:
        return None
    med = _bin_medians(rho, b, nb, full)
    tol = np.maximum(3.0 * 1.25 * np.bincount(b, weights=s, minlength=nb)[full] / cnt[full] ** 1.5,
                     flat_fraction * radius)

    m = full.size
    whole = _line_misfit(full, med, cnt[full], tol, np.array([m]))[0]
    if whole <= 1.0:
        return None
    w = cnt[full]
    cuts = np.arange(min_bins, m - min_bins + 1)
    if cuts.size == 0:
        return None
    head = _line_misfit(full, med, w, tol, cuts)  # of the bins before each cut
    tail = _line_misfit(full[::-1], med[::-1], w[::-1], tol[::-1], m - cuts)  # of the bins from each cut on
    costs = np.maximum(head, tail)
    j = int(np.argmin(costs))
    if costs[j] < whole / 2:
        return (b >= full[cuts[j]]).astype(np.int64)
    # a pipe, its reducer and the next pipe: three lines (flat, ramp, flat) where no two do. Among the pairs
    # of cuts whose largest deviation is small enough, the one of least squared misfit (the largest deviation
    # alone does not place the joins: a kink within tolerance passes for a line); the first cut is returned,
    # the next pass of _split_along_axis cuts the rest
    sse = _line_sse(full, med, 1.0 / tol**2)
    best, at = np.inf, None
    for i, c1 in enumerate(cuts):
        c2 = cuts[cuts >= c1 + min_bins]
        if c2.size == 0:
            break
        mid = _line_misfit(full[c1:], med[c1:], w[c1:], tol[c1:], c2 - c1)
        ok = np.maximum(np.maximum(head[i], mid), tail[np.searchsorted(cuts, c2)]) < whole / 2
        if not ok.any():
            continue
        total = sse(0, c1) + sse(c1, c2[ok]) + sse(c2[ok], m)
        k = int(np.argmin(total))
        if total[k] < best:
            best, at = float(total[k]), c1
    return None if at is None else (b >= full[at]).astype(np.int64)


def _line_sums(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Cumulative weighted moments ``(w, w x, w y, w x², w x y, w y²)`` of the points, shape (6, N + 1) with a
    leading zero column: the sums over ``[i, j)`` are ``c[:, j] - c[:, i]``."""
    x = x.astype(np.float64)
    return np.concatenate([np.zeros((6, 1)), np.cumsum(np.stack([w, w * x, w * y, w * x * x, w * x * y, w * y * y]),
                                                        axis=1)], axis=1)


def _line_of_sums(s0, sx, sy, sxx, sxy):
    """``(slope, intercept)`` of the weighted least-squares line from its moments (arrays broadcast)."""
    slope = (s0 * sxy - sx * sy) / (s0 * sxx - sx * sx)
    return slope, (sy - slope * sx) / s0


def _line_sse(x: np.ndarray, y: np.ndarray, w: np.ndarray):
    """A function ``sse(i, j)`` (broadcasting over integer arrays): the weighted squared misfit of
    ``y[i:j]`` to its weighted least-squares line in ``x``, from cumulative sums."""
    c = _line_sums(x, y, w)

    def sse(i, j):
        i, j = np.broadcast_arrays(np.asarray(i), np.asarray(j))
        s0, sx, sy, sxx, sxy, syy = c[:, j] - c[:, i]
        slope, icpt = _line_of_sums(s0, sx, sy, sxx, sxy)
        return np.maximum(syy - icpt * sy - slope * sxy, 0.0)

    return sse


def _line_misfit(x: np.ndarray, y: np.ndarray, w: np.ndarray, tol: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """For each ``e`` in ``ends``: the largest deviation, in ``tol`` units, of ``y[:e]`` from its line fitted by
    least squares weighted by ``w`` (counts), all prefixes at once from cumulative sums."""
    x = x.astype(np.float64)
    slope, icpt = _line_of_sums(*_line_sums(x, y, w)[:5, ends])
    dev = np.abs(icpt[:, None] + slope[:, None] * x[None, :] - y[None, :]) / tol[None, :]
    return np.where(np.arange(len(x))[None, :] < ends[:, None], dev, -np.inf).max(axis=1)
