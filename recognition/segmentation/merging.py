"""Segmentation step 5, merging (section 3 of Fillatreau & Fisher: patches are merged by surface fitting):
greedy best-first merging of adjacent patches whose union one surface fits, small enclosed fragments into their
host, isolated limb pieces across a jump, fragments into the neighbour that fits them."""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np

from recognition.fitting import MIN_GRAZING, ray_residuals

from . import kernels
from .grid import (
    _adjacency,
    _border_pairs,
    _class_counts,
    _groups,
    _is_planar_counts,
    _kernel_labels,
    _rms,
    _State,
    _subsample,
    _unique_pairs,
)
from .quick_fits import (
    _group_grams,
    _group_sums,
    _is_plane_pair,
    _pixel_residuals,
    _quick_fits,
    _quick_fits_of,
)
from .types import SegmentationParams, SurfaceType


def _merge_patches(labels: np.ndarray, st: _State, params: SegmentationParams, valid: np.ndarray,
                   jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """Step 5 on one grid: enclosed fragments, best-first merging, enclosed fragments again, isolated pieces
    across jumps, then fragments into the neighbour that fits them; returns the labels."""
    labels = _merge_enclosed(labels, params, valid, jump_h, jump_v)
    labels = _merge(labels, st, params, jump_h, jump_v)
    labels = _merge_enclosed(labels, params, valid, jump_h, jump_v)
    labels = _attach_isolated(labels, st, params, jump_h, jump_v)
    return _absorb_fragments(labels, st, params, jump_h, jump_v)


def _dominant(counts: np.ndarray, min_pixels: int) -> int:
    """The class holding at least 60 % of a patch's classified pixels (0 when none or too few pixels)."""
    cc = counts[1:]
    n = int(cc.sum())
    if n < min_pixels:
        return 0
    k = int(np.argmax(cc))
    return k + 1 if cc[k] >= 0.6 * n else 0


def _class_boundary(ca: np.ndarray, cb: np.ndarray, min_pixels: int) -> bool:
    """True when one patch is clearly cylindrical and the other clearly doubly curved (elliptic or
    hyperbolic): a G1 join such as pipe / elbow or tank / dome, which a quadric can bridge within the noise.
    Planar-dominated patches (curvature below the noise: large radii) may join anything the fit accepts."""
    a, b = _dominant(ca, min_pixels), _dominant(cb, min_pixels)
    return {a, b} in ({SurfaceType.CYLINDRICAL, SurfaceType.ELLIPTIC},
                      {SurfaceType.CYLINDRICAL, SurfaceType.HYPERBOLIC})


@dataclass(frozen=True)
class _FitPart:
    """A patch's merge-test sample (its points, rays and sigmas) with its centroid and centred scatter: the
    total-least-squares plane of a union of parts follows from these moments alone."""

    n: int
    XU: np.ndarray  # (n, 6): points and unit rays
    S: np.ndarray  # (n,) sigmas
    mean: np.ndarray
    scatter: np.ndarray

    @classmethod
    def of(cls, idx: np.ndarray, st: _State) -> _FitPart:
        X = st.X[idx]
        mean = X.mean(axis=0) if len(X) else np.zeros(3)
        d = X - mean
        return cls(len(X), np.hstack([X, st.U[idx]]), st.S[idx], mean, d.T @ d)

    @classmethod
    def batch(cls, subs: dict[int, np.ndarray], st: _State) -> dict[int, _FitPart]:
        """:meth:`of` for every (non-empty) sample of ``subs`` at once."""
        keys = list(subs)
        cnt = np.array([subs[k].size for k in keys])
        if cnt.size == 0 or cnt.min() == 0:
            return {k: cls.of(subs[k], st) for k in keys}
        ix = np.concatenate([subs[k] for k in keys])
        starts = np.concatenate([[0], np.cumsum(cnt)[:-1]])
        XU = np.hstack([st.X[ix], st.U[ix]])
        S = st.S[ix]
        mean = _group_sums(XU[:, :3], starts) / cnt[:, None]
        scatter = _group_grams(XU[:, :3] - np.repeat(mean, cnt, axis=0), starts, cnt)
        return {k: cls(int(c), XU[s:s + c], S[s:s + c], mean[g], scatter[g])
                for g, (k, s, c) in enumerate(zip(keys, starts.tolist(), cnt.tolist(), strict=True))}

    def chi2(self, normal: np.ndarray, offset: float) -> float:
        """Sum of squared ray z-residuals (as in :func:`_plane_fits`) to the plane ``normal . x = offset``."""
        f = self.XU[:, :3] @ normal
        g = self.XU[:, 3:] @ normal
        z = (f - offset) / (np.maximum(np.abs(g), MIN_GRAZING) * self.S)  # valid pixels: sigma > 0
        return float(z @ z)


def _plane_union_rms(pairs: list[tuple[_FitPart, _FitPart | None]]) -> list[tuple[float, float]]:
    """For each ``(large, small)``: the RMS ray z-residual (as in :func:`_plane_fits`) of the total-least-squares
    plane of both parts together, over all their points and over ``small``'s (``small`` None: ``large`` alone,
    both RMS over its points); inf for fewer than 3 points (NaN residuals, impossible for valid pixels, would
    make them NaN: never accepted). The planes' eigen-decompositions are done in one batch."""
    out = [(float("inf"), float("inf"))] * len(pairs)
    todo, means, scatters = [], [], []
    for i, (large, small) in enumerate(pairs):
        if small is None:
            if large.n >= 3:
                todo.append(i)
                means.append(large.mean)
                scatters.append(large.scatter)
            continue
        n = large.n + small.n
        if n < 3 or small.n == 0:
            continue
        d = large.mean - small.mean
        todo.append(i)
        means.append((large.n * large.mean + small.n * small.mean) / n)
        scatters.append(large.scatter + small.scatter + (large.n * small.n / n) * np.outer(d, d))
    if not todo:
        return out
    normals = np.linalg.eigh(np.array(scatters))[1][:, :, 0]
    for i, mean, normal in zip(todo, means, normals, strict=True):
        large, small = pairs[i]
        offset = float(mean @ normal)
        if small is None:
            c = large.chi2(normal, offset)
            out[i] = (float(np.sqrt(c / large.n)), float(np.sqrt(c / large.n)))
        else:
            c_small = small.chi2(normal, offset)
            out[i] = (float(np.sqrt((large.chi2(normal, offset) + c_small) / (large.n + small.n))),
                      float(np.sqrt(c_small / small.n)))
    return out


def _merge(labels: np.ndarray, st: _State, params: SegmentationParams, jump_h, jump_v) -> np.ndarray:
    """Greedy best-first merging of adjacent patches whose union fits one surface (returns new labels).

    A pair merges when the union's fit (plane when both patches are planar, by class or by fit; quadric
    otherwise) has an RMS range residual within ``merge_k`` sigma over the union and within ``1.5 merge_k``
    over the smaller part (a small fragment of another surface is not hidden by the larger patch's many good
    points). With ``curved_planar_merge`` a planar pair that no plane fits is tried as a quadric, which must
    not be a plane pair (:func:`_is_plane_pair`: two faces at a crease). Costs are computed in batches and
    re-evaluated lazily when a patch has changed since its pair was queued. With
    ``class_min_pixels`` set, two patches whose dominant curvature classes are cylindrical and doubly curved
    never merge (:func:`_class_boundary`): at a tangent join (a pipe and its elbow, a tank and its dome) the
    class change is the only cue.
    """
    groups = _groups(labels)
    if len(groups) < 2:
        return labels
    thr = params.merge_k
    nmax = params.merge_fit_points
    members = dict(groups)
    subs = {k: _subsample(v, nmax) for k, v in members.items()}
    counts = dict(zip(members, _class_counts(list(members.values()), st.hk),
                      strict=True))  # each patch's pixels per curvature class (5,)
    planar_class = {k: _is_planar_counts(c) for k, c in counts.items()}
    parts = _FitPart.batch(subs, st)

    flats: dict[int, bool] = {}  # whether a plane fits the patch, computed when needed

    def update_flats(keys) -> None:
        new = [k for k in keys if k not in flats]
        for k, (rms, _) in zip(new, _plane_union_rms([(parts[k], None) for k in new]), strict=True):
            flats[k] = rms <= thr

    update_flats(list(members))
    version = dict.fromkeys(members, 0)
    nbrs: dict[int, set[int]] = {k: set() for k in members}
    for a, b in _adjacency(labels, jump_h, jump_v):
        nbrs[a].add(b)
        nbrs[b].add(a)

    def costs(pairs: list[tuple[int, int]]) -> list[float]:
        """RMS residual of the union fit of each pair (inf when the smaller part does not fit it), all fitted
        in one batch."""
        out = [float("inf")] * len(pairs)
        update_flats(sorted({k for pair in pairs for k in pair}))
        todo, ordered, planar, n_large = [], [], [], []
        curved = []  # (index in todo) of the unions fitted by a quadric, in one batch
        flat_pairs = []  # (index in pairs, larger, smaller) of the unions fitted by a plane, in one batch
        for i, (a, b) in enumerate(pairs):
            if params.class_min_pixels is not None and \
                    _class_boundary(counts[a], counts[b], params.class_min_pixels):
                continue
            if subs[a].size < subs[b].size:
                a, b = b, a
            todo.append(i)
            ordered.append((a, b))
            n_large.append(subs[a].size)
            # two planes (by class, or by fit: crease pixels make a face look curved) merge only as one
            # plane, never as the plane pair a general quadric fits exactly
            planar.append((planar_class[a] and planar_class[b]) or (flats[a] and flats[b]))
            if planar[-1] or subs[a].size + subs[b].size < 10:  # (< 10 points: a plane, as in _quick_fits)
                flat_pairs.append((i, a, b))
            else:
                curved.append(len(todo) - 1)
        flat_rms = _plane_union_rms([(parts[a], parts[b]) for _, a, b in flat_pairs])
        for (i, _, _), (rms_all, rms_small) in zip(flat_pairs, flat_rms, strict=True):
            if rms_small <= 1.5 * thr:
                out[i] = rms_all
        # two planar-looking pieces of one gently curved surface (a large pipe close to a noisy sensor) that
        # no plane fits are retried as a quadric, which must not be the plane pair of two faces at a crease
        retry = [j for j in range(len(todo))
                 if params.curved_planar_merge and planar[j] and not out[todo[j]] <= thr]
        if curved or retry:
            # the unions' pixels (larger part first) are gathered only for the quadric fits
            unions = {j: np.concatenate([subs[ordered[j][0]], subs[ordered[j][1]]]) for j in curved + retry}
            Pq, zq = _quick_fits([unions[j] for j in curved + retry], np.zeros(len(curved) + len(retry), bool), st)
            for j, z in zip(curved, zq, strict=False):
                if _rms(z[n_large[j]:]) <= 1.5 * thr:
                    out[todo[j]] = _rms(z)
            for j, p, z in zip(retry, Pq[len(curved):], zq[len(curved):], strict=True):
                if _rms(z) <= thr and _rms(z[n_large[j]:]) <= 1.5 * thr and \
                        not _is_plane_pair(p, st.X[unions[j]], params.plane_pair_tol):
                    out[todo[j]] = _rms(z)
        return out

    heap: list[tuple[float, int, int, int, int]] = []

    def push(pairs: list[tuple[int, int]]) -> None:
        pairs = [(min(a, b), max(a, b)) for a, b in pairs]
        for (a, b), c in zip(pairs, costs(pairs), strict=True):
            if c <= thr:
                heapq.heappush(heap, (c, a, b, version[a], version[b]))

    push([(a, b) for a in nbrs for b in sorted(nbrs[a]) if a < b])
    parent = np.arange(max(members) + 1)
    while heap:
        _, a, b, va, vb = heapq.heappop(heap)
        if a not in members or b not in members:
            continue
        if va != version[a] or vb != version[b]:
            push([(a, b)])
            continue
        members[a] = np.concatenate([members[a], members.pop(b)])
        members[a].sort(kind="stable")  # two sorted runs: a linear merge
        subs[a] = _subsample(members[a], nmax)
        subs.pop(b)
        parts[a] = _FitPart.of(subs[a], st)
        parts.pop(b)
        counts[a] = counts[a] + counts.pop(b)
        planar_class[a] = _is_planar_counts(counts[a])
        planar_class.pop(b)
        flats.pop(b)
        flats.pop(a)
        version[a] += 1
        parent[b] = a
        old = nbrs[a]
        nb_b = nbrs.pop(b)
        nbrs[a] = (old | nb_b) - {a, b}
        for q in nb_b - {a}:
            nbrs[q].discard(b)
            nbrs[q].add(a)
        push([(a, q) for q in sorted(nb_b - {a}) if q not in old])
    while True:  # follow each label's chain of merges to the patch that absorbed it last
        nxt = parent[parent]
        if np.array_equal(nxt, parent):
            break
        parent = nxt
    out = labels.copy()
    m = out >= 0
    out[m] = parent[out[m]]
    return out


def _merge_enclosed(labels: np.ndarray, params: SegmentationParams, valid: np.ndarray, jump_h: np.ndarray,
                    jump_v: np.ndarray) -> np.ndarray:
    """Merge small patches lying wholly inside one other patch.

    A patch is enclosed by q when every pixel next to it (4-neighbours) is q, an unlabelled return, or on
    the far side of a jump; the image border and pixels without a return count as other neighbours. Small
    enclosed patches (fewer than ``min_patch_pixels``) join q.
    """
    for _ in range(10):
        if labels.size == 0 or labels.max() < 0:
            return labels
        remap = _enclosed_targets(labels, valid, jump_h, jump_v, int(labels.max()) + 1, params.min_patch_pixels)
        if np.array_equal(remap, np.arange(remap.size)):
            return labels
        m = labels >= 0
        labels = labels.copy()
        labels[m] = remap[labels[m]]
    return labels


def _enclosed_targets(labels: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                      n_labels: int, min_pixels: int) -> np.ndarray:
    """One round of :func:`_merge_enclosed`: the label each patch joins, itself when it stays (n_labels,); the
    compiled :func:`.kernels.enclosed_targets`, whose reference is :func:`_enclosed_targets_reference`.
    ``labels`` (H, W) < ``n_labels``, ``valid`` (H, W) the returns."""
    return kernels.enclosed_targets(_kernel_labels(labels), valid, jump_h, jump_v, int(n_labels), int(min_pixels))


def _enclosed_targets_reference(labels: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                                n_labels: int, min_pixels: int) -> np.ndarray:
    """:func:`_enclosed_targets` in numpy, by the unique (patch, neighbour) pairs of the four directions."""
    Hh, Ww = labels.shape
    # per direction: neighbour label, with -3 = transparent (unlabelled return or across a jump)
    across = []
    for dr, dc in ((0, -1), (0, 1), (-1, 0), (1, 0)):
        j = np.zeros((Hh, Ww), bool)
        if dc == -1:
            j[:, 1:] = jump_h
        elif dc == 1:
            j[:, :-1] = jump_h
        elif dr == -1:
            j[1:, :] = jump_v
        else:
            j[:-1, :] = jump_v
        across.append(j)
    remap = np.arange(n_labels)
    pad = np.full((Hh + 2, Ww + 2), -2, dtype=np.int64)  # -2: border or no return
    lab = np.where(valid, labels, -2).astype(np.int64)
    lab[lab == -1] = -3
    pad[1:-1, 1:-1] = lab
    centre = pad[1:-1, 1:-1]
    pairs = []
    for nb, j in zip((pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]), across, strict=True):
        m = (centre >= 0) & (nb != centre) & (nb != -3) & ~j
        pairs.append(np.stack([centre[m], nb[m]], axis=1))
    pairs = np.concatenate(pairs)
    if pairs.size == 0:
        return remap
    pairs = _unique_pairs(pairs)
    sizes = np.bincount(labels[labels >= 0], minlength=n_labels)
    owner, first, n_other = np.unique(pairs[:, 0], return_index=True, return_counts=True)
    for p, f, k in zip(owner, first, n_other, strict=True):
        q = int(pairs[f, 1])
        if k == 1 and q >= 0 and sizes[p] < min_pixels and sizes[q] > sizes[p] and remap[q] == q:
            remap[p] = q
    return remap


def _attach_isolated(labels: np.ndarray, st: _State, params: SegmentationParams, jump_h: np.ndarray,
                     jump_v: np.ndarray) -> np.ndarray:
    """Attach small patches cut off from everything by jumps to a patch across the jump whose surface fits.

    Grazing limb samples of a sphere or pipe are often separated from the rest of their surface by range
    steps larger than the jump allowance; they cannot grow back, but they lie on that surface (RMS range
    residual within ``grow_k`` sigma of its fit). A small object in front of a wall does not fit the wall
    and stays on its own.
    """
    pairs_j, pairs_n = [], []
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & (a != b)
        for dst, sel in ((pairs_j, m & j), (pairs_n, m & ~j)):
            dst.append(np.stack([a[sel], b[sel]], axis=1))
            dst.append(np.stack([b[sel], a[sel]], axis=1))
    across = _unique_pairs(np.concatenate(pairs_j))
    linked = np.unique(np.concatenate(pairs_n)[:, 0])
    if across.size == 0:
        return labels
    groups = _groups(labels)
    small = {k for k, v in groups.items() if v.size < params.min_patch_pixels}
    remap = np.arange(int(labels.max()) + 1)
    isolated = sorted(small - set(linked.tolist()))
    cands = {p: [int(q) for q in across[across[:, 0] == p, 1] if groups[int(q)].size > groups[p].size]
             for p in isolated}
    fits = _quick_fits_of(groups, sorted({q for c in cands.values() for q in c}), st, params)
    tests = [(p, q) for p in isolated for q in cands[p]]
    rms_of = {}
    if tests:  # the RMS residual of each isolated patch to each candidate's surface, in one pass
        P = np.array([fits[q] for _, q in tests])
        idx = np.concatenate([groups[p] for p, _ in tests])
        sizes = np.array([groups[p].size for p, _ in tests])
        z = _pixel_residuals(P, np.repeat(np.arange(len(tests)), sizes), st.X[idx], st.U[idx], st.S[idx])
        ms = np.add.reduceat(z * z, np.concatenate([[0], np.cumsum(sizes)[:-1]])) / sizes
        rms_of = dict(zip(tests, np.sqrt(ms).tolist(), strict=True))
    for p in isolated:
        best, best_rms = -1, params.grow_k
        for q in cands[p]:
            if rms_of[(p, q)] <= best_rms:
                best, best_rms = q, rms_of[(p, q)]
        if best >= 0 and remap[best] == best:
            remap[p] = best
    if np.all(remap == np.arange(remap.size)):
        return labels
    out = labels.copy()
    m = out >= 0
    out[m] = remap[out[m]]
    return out


def _absorb_fragments(labels: np.ndarray, st: _State, params: SegmentationParams, jump_h: np.ndarray,
                      jump_v: np.ndarray) -> np.ndarray:
    """Merge fragments (fewer than ``min_region_pixels``) into the bordering patch whose surface fits them best.

    A fragment joins a larger patch it touches without a jump when the RMS range residual of its pixels to
    that patch's fit is within ``absorb_k`` sigma (the neighbour with the longest common border among those
    that fit). Fragments that fit no neighbour (a small object, a transition band between two surfaces)
    stay as they are. Hoover's metric counts any fragment wholly inside a truth region as an
    over-segmentation of it, so the pieces of one surface cut out by misclassified curvature must go back.
    At most ``absorb_rounds`` rounds.
    """
    min_pixels, max_rms = params.min_region_pixels, params.absorb_k
    for _ in range(params.absorb_rounds):
        groups = _groups(labels)
        if len(groups) < 2:
            return labels
        sizes = np.zeros(max(groups) + 1, np.int64)
        for k, v in groups.items():
            sizes[k] = v.size
        pairs, blen = _border_pairs(labels, jump_h, jump_v)
        if pairs.size == 0:
            return labels
        sel = (sizes[pairs[:, 0]] < min_pixels) & (sizes[pairs[:, 1]] > sizes[pairs[:, 0]])
        pairs, blen = pairs[sel], blen[sel]
        if pairs.size == 0:
            return labels
        # the fits of every neighbour a fragment may join
        fits = _quick_fits_of(groups, [int(q) for q in np.unique(pairs[:, 1])], st, params)
        remap = np.arange(sizes.size)
        order = np.lexsort((-blen, pairs[:, 0]))
        pairs, blen = pairs[order], blen[order]
        starts = np.flatnonzero(np.r_[True, pairs[1:, 0] != pairs[:-1, 0]])
        ends = np.r_[starts[1:], len(pairs)]
        for s0, e0 in zip(starts, ends, strict=True):
            p = int(pairs[s0, 0])
            idx = groups[p]
            for q in pairs[s0:e0, 1]:
                q = int(q)
                if remap[q] != q:
                    continue
                _, _, z = ray_residuals(fits[q], st.X[idx], st.S[idx])
                if _rms(np.where(np.isfinite(z), z, np.inf)) <= max_rms:
                    remap[p] = q
                    break
        if np.all(remap == np.arange(remap.size)):
            return labels
        labels = labels.copy()
        m = labels >= 0
        labels[m] = remap[labels[m]]
    return labels
