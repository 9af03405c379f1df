"""H-K segmentation of organised range images into surface patches (section 3 of Fillatreau & Fisher).

The paper follows Besl & Jain ("Segmentation through variable-order surface fitting", IEEE PAMI 10(2),
1988, doi:10.1109/34.3881): a patch is a maximal connected set of pixels whose mean (H) and Gaussian (K)
curvature signs do not change; patches are grown and merged by surface fitting, and a plane or a quadric is
fitted to each. The steps here:

1. **Derivatives** of the parametric surface ``P(u, v)`` (the point image; ``u`` column, ``v`` row) by local
   quadratic fits whose windows exclude neighbours across depth jumps (:mod:`recognition.derivatives`:
   separable Savitzky-Golay kernels where the whole window is on one surface, batched masked 6x6 solves
   elsewhere).
2. **Curvatures** from the fundamental forms, valid for perspective images: ``E = Pu.Pu, F = Pu.Pv,
   G = Pv.Pv``, ``n = Pu x Pv / |Pu x Pv|`` oriented to **face the sensor** (``n . P < 0``),
   ``L = Puu.n, M = Puv.n, N = Pvv.n``, ``K = (LN - M²) / (EG - F²)``,
   ``H = (EN - 2FM + GL) / (2 (EG - F²))``. With this normal a surface bulging towards the sensor (the
   outside of a sphere or pipe) has ``H < 0``: a sphere of radius r gives ``H = -1/r, K = 1/r²``, a
   cylinder ``H = -1/(2r), K = 0``.
3. **Zero thresholds from the noise.** The derivative estimates are linear in the data; range noise of
   sigma along the ray moves ``L, M, N`` by ``(ray . n) sum_k c_k dr_k``, so their covariance is
   ``sigma² (ray . n)²`` times the filter's unit-noise covariance. ``sigma_H`` is its first-order
   propagation; ``sigma_K`` adds the second-order term ``(var_L var_N + 2 var_M²) / (EG - F²)²`` (on a plane
   the first-order term of K vanishes). ``H = 0`` when ``|H| <= k sigma_H``, the same for K.
4. **Classes**: planar (H=0, K=0), cylindrical (K=0, H!=0; cones too: they are developable), elliptic
   (K>0), hyperbolic (K<0, whatever H). K>0 with H=0 is impossible (K <= H²): treated as planar noise.
   **Edges**: jump pairs (range difference beyond :func:`recognition.derivatives.jump_threshold`) and crease
   pairs (normals of neighbours further apart than ``crease_k`` times their propagated angular sigma and
   ``crease_min_angle``).
5. **Patches**: seeds are the connected components of one class, edge pixels removed, that survive a
   morphological erosion of ``seed_erosion`` pixels (thin bands of transitional curvature along creases
   vanish) with at least ``min_seed_pixels`` left. Each seed gets a plane (planar seeds) or a quadric; seeds
   grow into adjacent unlabelled pixels (never across a jump) whose range residual to the patch's surface is
   within ``grow_k`` sigma, with refits between rounds. Leftover connected pixels with defined curvature
   become patches of their own (isolated pieces under ``min_leftover_pixels`` stay unlabelled).
   Adjacent patches are merged greedily, best first, while the fit of their
   union (plane for two planar patches, quadric otherwise) has an RMS range residual within ``merge_k``
   sigma; small fragments lying wholly inside one other patch are merged into it (the Hoover metric counts
   them as over-segmentation otherwise), and small pieces cut off by jumps (grazing limbs) join the patch
   across the jump whose surface fits them. Small and noisy patches are kept and flagged, never dropped.

The segmenter reads only the point image and the per-pixel sigma; never any ground truth.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
import scipy.ndimage as ndi
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from recognition.derivatives import jump_pairs, norm3, quadratic_derivatives
from recognition.surface_fit import (
    _MIN_GRAZING,
    PlaneFit,
    QuadricSurfaceFit,
    fit_plane,
    fit_quadric_lsq,
    normalisation_transform,
    plane_params,
    quadric_gradient,
    quadric_monomials,
    ray_residuals,
)

__all__ = [
    "SurfaceType",
    "EdgeType",
    "SegmentationParams",
    "Patch",
    "Segmentation",
    "CurvatureImages",
    "segment",
    "curvature_images",
    "classify_hk",
]


class SurfaceType(IntEnum):
    """H-K surface class of a pixel or patch."""

    NONE = 0
    PLANAR = 1
    CYLINDRICAL = 2
    ELLIPTIC = 3
    HYPERBOLIC = 4


class EdgeType(IntEnum):
    """Bits of :attr:`Segmentation.edges`."""

    JUMP = 1
    CREASE = 2


@dataclass(frozen=True)
class SegmentationParams:
    """Parameters of :func:`segment` (all thresholds in units of the propagated noise unless stated).

    Attributes
    ----------
    window : int
        Odd size of the square window of the local quadratic fits (>= 3). Larger: smoother curvature,
        wider transition bands at creases.
    zero_k : float
        ``H = 0`` when ``|H| <= zero_k * sigma_H`` (same for K).
    jump_k : float
        Range-noise allowance of the jump test, in sigma.
    jump_tan : float
        ``tan`` of the steepest incidence still considered one continuous surface: neighbours may differ in
        range by ``jump_tan * range * ray angle`` beyond the noise allowance (5.0 ~ 79 deg).
    crease_k : float
        Crease when the angle between neighbouring normals exceeds ``crease_k`` times its propagated sigma...
    crease_min_angle : float, radians
        ...and this angle.
    sigma_floor_m : float, metres
        Floor applied to the input sigma (quantisation level; keeps noise-free images usable).
    seed_erosion : int or None
        Erosion (pixels) that a class component must survive to seed a patch (None: ``window // 2``).
    min_seed_pixels : int
        Fewest pixels left after erosion for a seed.
    grow_k : float
        A pixel joins an adjacent patch when its range residual to the patch's surface is within
        ``grow_k`` sigma.
    grow_rounds : int
        Grow / refit rounds (>= 1).
    max_grow_iterations : int
        One-pixel growth steps per round at most.
    merge_k : float
        Adjacent patches merge when the RMS range residual of their union's fit is within ``merge_k`` sigma.
    min_patch_pixels : int
        Patches below this size are flagged ``small``; small fragments enclosed by one patch are merged.
    noisy_k : float
        Patches whose fit RMS range residual exceeds ``noisy_k`` sigma are flagged ``noisy``.
    min_leftover_pixels : int
        Leftover pieces (pixels that fit no neighbouring patch, linked without jumps) with fewer pixels
        stay unlabelled: isolated returns (flying pixels, grazing limb samples) are not patches. Larger
        pieces become patches of their own, flagged ``small`` / ``noisy`` as they deserve.
    max_fit_points : int
        Points used per fit while growing and merging (a deterministic stride subsample); final fits use all.
    connectivity : int
        4 or 8: pixel connectivity of class components.
    """

    window: int = 7
    zero_k: float = 3.0
    jump_k: float = 4.0
    jump_tan: float = 5.0
    crease_k: float = 4.0
    crease_min_angle: float = float(np.deg2rad(12.0))
    sigma_floor_m: float = 1e-5
    seed_erosion: int | None = None
    min_seed_pixels: int = 8
    grow_k: float = 3.0
    grow_rounds: int = 2
    max_grow_iterations: int = 100
    merge_k: float = 2.0
    min_patch_pixels: int = 50
    noisy_k: float = 3.0
    min_leftover_pixels: int = 3
    max_fit_points: int = 1500
    connectivity: int = 4

    def __post_init__(self) -> None:
        if not isinstance(self.window, int | np.integer) or self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"window must be an odd integer >= 3, got {self.window!r}")
        for name in ("zero_k", "jump_k", "crease_k", "grow_k", "merge_k", "noisy_k"):
            v = getattr(self, name)
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not np.isfinite(self.jump_tan) or self.jump_tan < 0:
            raise ValueError(f"jump_tan must be >= 0, got {self.jump_tan!r}")
        if not 0 <= self.crease_min_angle <= np.pi:
            raise ValueError(f"crease_min_angle must be in [0, pi] radians, got {self.crease_min_angle!r}")
        if not self.sigma_floor_m > 0:
            raise ValueError(f"sigma_floor_m must be > 0, got {self.sigma_floor_m!r}")
        if self.seed_erosion is not None and self.seed_erosion < 0:
            raise ValueError(f"seed_erosion must be >= 0 or None, got {self.seed_erosion!r}")
        for name in ("min_seed_pixels", "grow_rounds", "max_grow_iterations", "min_patch_pixels",
                     "min_leftover_pixels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if self.max_fit_points < 10:
            raise ValueError(f"max_fit_points must be >= 10, got {self.max_fit_points!r}")
        if self.connectivity not in (4, 8):
            raise ValueError(f"connectivity must be 4 or 8, got {self.connectivity!r}")

    @property
    def erosion(self) -> int:
        """Effective seed erosion in pixels."""
        return self.window // 2 if self.seed_erosion is None else self.seed_erosion


@dataclass(frozen=True)
class Patch:
    """One segmented surface patch.

    Attributes
    ----------
    id : int
        Its value in :attr:`Segmentation.labels`.
    pixels : ndarray of shape (N, 2), int
        (row, column) of its pixels, raster order.
    n_pixels : int
    surface_type : SurfaceType
        Dominant H-K class of its pixels (after growing and merging).
    fit : PlaneFit or QuadricSurfaceFit
        Plane ``n . x = d`` (n facing the sensor) for planar patches, a general quadric otherwise; with
        covariance and RMS residuals (``rms_sigma``: along the ray, in sigma units). A failed fit is falsy.
    small : bool
        Fewer than ``min_patch_pixels`` pixels.
    noisy : bool
        Fit RMS range residual above ``noisy_k`` sigma (or the fit failed).
    class_counts : tuple of int
        Pixels of each class (NONE, PLANAR, CYLINDRICAL, ELLIPTIC, HYPERBOLIC).
    """

    id: int
    pixels: np.ndarray
    n_pixels: int
    surface_type: SurfaceType
    fit: PlaneFit | QuadricSurfaceFit
    small: bool
    noisy: bool
    class_counts: tuple[int, ...] = field(default=(0, 0, 0, 0, 0))


@dataclass(frozen=True)
class Segmentation:
    """Result of :func:`segment`.

    Attributes
    ----------
    labels : ndarray of shape (H, W), int32
        Patch id per pixel, -1 for none.
    hk_class : ndarray of shape (H, W), int8
        :class:`SurfaceType` per pixel (0 where curvature is undefined).
    H, K : ndarray of shape (H, W), float64
        Mean curvature (1/m, normal facing the sensor) and Gaussian curvature (1/m²); NaN where undefined.
    sigma_H, sigma_K : ndarray of shape (H, W), float64
        Their propagated noise sigmas.
    normals : ndarray of shape (H, W, 3)
        Unit surface normals from the local fits, facing the sensor (NaN where undefined).
    edges : ndarray of shape (H, W), uint8
        Bitmask of :class:`EdgeType` (1 jump, 2 crease).
    patches : tuple of Patch
        Ordered by decreasing size; ``patches[i].id == i``.
    """

    labels: np.ndarray
    hk_class: np.ndarray
    H: np.ndarray
    K: np.ndarray
    sigma_H: np.ndarray
    sigma_K: np.ndarray
    normals: np.ndarray
    edges: np.ndarray
    patches: tuple[Patch, ...]

    @property
    def n_patches(self) -> int:
        """Number of patches."""
        return len(self.patches)


@dataclass(frozen=True)
class CurvatureImages:
    """Per-pixel curvature and its propagated noise (see :func:`curvature_images`)."""

    H: np.ndarray
    K: np.ndarray
    sigma_H: np.ndarray
    sigma_K: np.ndarray
    normals: np.ndarray
    sigma_normal: np.ndarray


# --------------------------------------------------------------------------------------------- validation


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


# --------------------------------------------------------------------------------------------- curvature


def curvature_images(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams) -> CurvatureImages:
    """Mean and Gaussian curvature of a perspective point image, with propagated noise.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame, NaN where no return
    sigma : ndarray of shape (H, W), metres, range sigma along the ray (already floored)
    params : SegmentationParams

    Returns
    -------
    CurvatureImages
        ``H`` (1/m) with the normal facing the sensor, ``K`` (1/m²), their sigmas, unit normals (H, W, 3),
        and ``sigma_normal`` (H, W), radians, the propagated angular sigma of the normal.
    """
    der = quadratic_derivatives(points, sigma, params.window, params.jump_k, params.jump_tan)
    Pu, Pv = der.Pu, der.Pv
    E = np.einsum("ijk,ijk->ij", Pu, Pu)
    F = np.einsum("ijk,ijk->ij", Pu, Pv)
    G = np.einsum("ijk,ijk->ij", Pv, Pv)
    cr = np.cross(Pu, Pv)
    with np.errstate(invalid="ignore", divide="ignore"):
        n = cr / norm3(cr)[..., None]
        flip = np.einsum("ijk,ijk->ij", n, points) > 0
        n[flip] *= -1.0
        L = np.einsum("ijk,ijk->ij", der.Puu, n)
        M = np.einsum("ijk,ijk->ij", der.Puv, n)
        N = np.einsum("ijk,ijk->ij", der.Pvv, n)
        det = E * G - F * F
        K = (L * N - M * M) / det
        Hc = (E * N - 2.0 * F * M + G * L) / (2.0 * det)
        rays = points / norm3(points)[..., None]
        cos2 = np.einsum("ijk,ijk->ij", rays, n) ** 2
        s2 = sigma**2 * cos2
        c = der.cov2  # (H, W, 6): LL, MM, NN, LM, LN, MN per unit variance
        cLL, cMM, cNN, cLM, cLN, cMN = (c[..., i] * s2 for i in range(6))
        hL, hM, hN = G / (2.0 * det), -F / det, E / (2.0 * det)
        var_H = (hL * hL * cLL + hM * hM * cMM + hN * hN * cNN
                 + 2.0 * (hL * hM * cLM + hL * hN * cLN + hM * hN * cMN))
        kL, kM, kN = N / det, -2.0 * M / det, L / det
        var_K = (kL * kL * cLL + kM * kM * cMM + kN * kN * cNN
                 + 2.0 * (kL * kM * cLM + kL * kN * cLN + kM * kN * cMN))
        var_K += (cLL * cNN + 2.0 * cMM * cMM) / det**2
        sig_n = np.sqrt(s2 * (der.var_u / E + der.var_v / G))
    return CurvatureImages(Hc, K, np.sqrt(var_H), np.sqrt(var_K), n, sig_n)


def classify_hk(H: np.ndarray, K: np.ndarray, sigma_H: np.ndarray, sigma_K: np.ndarray, k: float) -> np.ndarray:
    """H-K sign classes with noise-derived zero thresholds.

    Parameters
    ----------
    H, K, sigma_H, sigma_K : ndarray of shape (H, W)
    k : float
        A value is zero when within ``k`` of its sigma.

    Returns
    -------
    ndarray of shape (H, W), int8
        :class:`SurfaceType` values; NONE where H or K is undefined.
    """
    with np.errstate(invalid="ignore"):
        defined = np.isfinite(H) & np.isfinite(K) & np.isfinite(sigma_H) & np.isfinite(sigma_K)
        h0 = np.abs(H) <= k * sigma_H
        k0 = np.abs(K) <= k * sigma_K
        out = np.zeros(H.shape, dtype=np.int8)
        out[k0 & h0] = SurfaceType.PLANAR
        out[k0 & ~h0] = SurfaceType.CYLINDRICAL
        out[~k0 & (K > 0) & ~h0] = SurfaceType.ELLIPTIC
        out[~k0 & (K > 0) & h0] = SurfaceType.PLANAR  # K > 0 with H = 0 cannot happen (K <= H²): noise
        out[~k0 & (K < 0)] = SurfaceType.HYPERBOLIC
    out[~defined] = SurfaceType.NONE
    return out


def _crease_pairs(normals, sig_n, params) -> tuple[np.ndarray, np.ndarray]:
    out = []
    for sl_a, sl_b in (
        ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
        ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        dot = np.clip(np.einsum("ijk,ijk->ij", normals[sl_a], normals[sl_b]), -1.0, 1.0)
        with np.errstate(invalid="ignore"):
            ang = np.arccos(dot)
            thr = np.maximum(params.crease_k * np.hypot(sig_n[sl_a], sig_n[sl_b]), params.crease_min_angle)
            out.append(ang > thr)
    return out[0], out[1]


# --------------------------------------------------------------------------------------------- patches


def _structure(connectivity: int) -> np.ndarray:
    return ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)


def _seed_labels(hk: np.ndarray, edges: np.ndarray, params: SegmentationParams) -> np.ndarray:
    """Class components (edges removed) that survive the seed erosion, labelled 0..n-1 (-1 elsewhere)."""
    labels = np.full(hk.shape, -1, dtype=np.int32)
    struct = _structure(params.connectivity)
    nxt = 0
    for cls in (SurfaceType.PLANAR, SurfaceType.CYLINDRICAL, SurfaceType.ELLIPTIC, SurfaceType.HYPERBOLIC):
        m = (hk == cls) & (edges == 0)
        if not m.any():
            continue
        lab, n = ndi.label(m, structure=struct)
        er = ndi.binary_erosion(m, structure=np.ones((3, 3), bool), iterations=params.erosion) \
            if params.erosion > 0 else m
        counts = np.bincount(lab[er], minlength=n + 1)
        keep = counts >= params.min_seed_pixels
        keep[0] = False
        if not keep.any():
            continue
        remap = np.where(keep, np.cumsum(keep) - 1 + nxt, -1).astype(np.int32)
        sel = remap[lab]
        labels[sel >= 0] = sel[sel >= 0]
        nxt += int(keep.sum())
    return labels


def _groups(labels: np.ndarray) -> dict[int, np.ndarray]:
    """Flat pixel indices of each label >= 0."""
    flat = labels.ravel()
    idx = np.flatnonzero(flat >= 0)
    if idx.size == 0:
        return {}
    lab = flat[idx]
    order = np.argsort(lab, kind="stable")
    idx, lab = idx[order], lab[order]
    cuts = np.flatnonzero(np.diff(lab)) + 1
    starts = np.concatenate([[0], cuts])
    return {int(lab[s]): part for s, part in zip(starts, np.split(idx, cuts), strict=True)}


def _subsample(idx: np.ndarray, n_max: int) -> np.ndarray:
    if idx.size <= n_max:
        return idx
    return idx[np.linspace(0, idx.size - 1, n_max).astype(np.int64)]


def _quick_fit(x: np.ndarray, u: np.ndarray, s: np.ndarray, planar: bool,
               want_params: bool = True) -> tuple[np.ndarray | None, np.ndarray]:
    """Plane (TLS) or quadric (unit-norm LSQ) fit; its parameters (10,) in metres and the ray z-residuals.

    ``x`` points (N, 3), ``u`` their unit rays, ``s`` their sigmas. The residual of each point is the range
    change putting it on the surface to first order, in sigma units (the incidence cosine floored at 0.25).
    """
    if planar or len(x) < 10:
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
        mean = x.mean(axis=0)
        scale = float(np.sqrt(np.mean(np.sum((x - mean) ** 2, axis=1)))) or 1.0
        y = (x - mean) / scale
        D = quadric_monomials(y)
        _, V = np.linalg.eigh(D.T @ D)
        pn = V[:, 0]
        f = D @ pn
        g = quadric_gradient(pn, y)
        p = None
        if want_params:
            p = normalisation_transform(mean, scale) @ pn
            p /= np.linalg.norm(p)
    gr = np.sum(g * u, axis=1)
    floor = _MIN_GRAZING * norm3(g)
    gr = np.where(np.abs(gr) < floor, floor, np.abs(gr))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = scale * np.abs(f) / (gr * s)
    return p, np.where(np.isfinite(z), z, np.inf)


def _rms(z: np.ndarray) -> float:
    return float(np.sqrt(np.mean(z**2))) if z.size else float("inf")


@dataclass
class _State:
    """Working arrays of the region growing / merging (private)."""

    X: np.ndarray  # (H*W, 3) points
    U: np.ndarray  # (H*W, 3) unit rays
    S: np.ndarray  # (H*W,) sigma
    hk: np.ndarray  # (H*W,) class
    params: SegmentationParams


def _is_planar_counts(counts: np.ndarray) -> bool:
    cc = counts[1:]
    return bool(cc.sum() == 0 or np.argmax(cc) == 0)


def _fit_groups(groups: dict[int, np.ndarray], st: _State, n_labels: int) -> np.ndarray:
    P = np.full((max(n_labels, 1), 10), np.nan)
    for lab, idx in groups.items():
        sub = _subsample(idx, st.params.max_fit_points)
        planar = _is_planar_counts(np.bincount(st.hk[idx], minlength=5))
        P[lab], _ = _quick_fit(st.X[sub], st.U[sub], st.S[sub], planar)
    return P


def _neighbour_links(shape, valid, jump_h, jump_v):
    """For each direction (left, right, up, down): (row shift, col shift, link allowed (H, W) bool)."""
    H, W = shape
    links = []
    left = np.zeros(shape, bool)
    left[:, 1:] = valid[:, :-1] & ~jump_h
    right = np.zeros(shape, bool)
    right[:, :-1] = valid[:, 1:] & ~jump_h
    up = np.zeros(shape, bool)
    up[1:, :] = valid[:-1, :] & ~jump_v
    down = np.zeros(shape, bool)
    down[:-1, :] = valid[1:, :] & ~jump_v
    for (dr, dc), ok in (((0, -1), left), ((0, 1), right), ((-1, 0), up), ((1, 0), down)):
        links.append((dr, dc, ok & valid))
    return links


def _grow(labels: np.ndarray, P: np.ndarray, st: _State, links, max_iter: int, thr: float) -> None:
    """Grow labelled patches into unlabelled valid pixels whose residual fits (in place)."""
    H, W = labels.shape
    flat = labels.ravel()
    cand = np.flatnonzero((flat < 0) & np.isfinite(st.S))
    if cand.size == 0:
        return
    r, c = np.divmod(cand, W)
    nb = []
    for dr, dc, ok in links:
        allowed = ok[r, c]
        nidx = np.where(allowed, (r + dr) * W + (c + dc), -1)
        nb.append(nidx)
    nb = np.stack(nb)  # (4, n)
    x = st.X[cand]
    s = st.S[cand]
    active = np.ones(cand.size, bool)
    for _ in range(max_iter):
        nl = np.where(nb >= 0, flat[np.maximum(nb, 0)], -1)
        nl[:, ~active] = -1
        front = (nl >= 0).any(axis=0)
        fi = np.flatnonzero(front)
        if fi.size == 0:
            break
        z = np.full((4, fi.size), np.inf)
        for k in range(4):
            m = nl[k, fi] >= 0
            if m.any():
                pk = P[nl[k, fi[m]]]
                _, _, zz = ray_residuals(pk, x[fi[m]], s[fi[m]])
                z[k, m] = np.where(np.isfinite(zz), np.abs(zz), np.inf)
        best = np.argmin(z, axis=0)
        zb = z[best, np.arange(fi.size)]
        acc = zb <= thr
        if not acc.any():
            break
        sel = fi[acc]
        flat[cand[sel]] = nl[best[acc], sel]
        active[sel] = False


def _link_components(mask: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
    """4-connected components of ``mask`` whose links never cross a jump pair; labels 0..n-1, -1 elsewhere."""
    H, W = mask.shape
    idx = np.full(mask.shape, -1, dtype=np.int64)
    n = int(mask.sum())
    idx[mask] = np.arange(n)
    rows, cols = [], []
    for a, b, j in ((idx[:, :-1], idx[:, 1:], jump_h), (idx[:-1, :], idx[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & ~j
        rows.append(a[m])
        cols.append(b[m])
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    out = np.full(mask.shape, -1, dtype=np.int64)
    out[mask] = comp
    return out


def _adjacency(labels: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray) -> set[tuple[int, int]]:
    pairs = []
    for a, b, j in ((labels[:, :-1], labels[:, 1:], jump_h), (labels[:-1, :], labels[1:, :], jump_v)):
        m = (a >= 0) & (b >= 0) & (a != b) & ~j
        if m.any():
            pa, pb = a[m].astype(np.int64), b[m].astype(np.int64)
            pairs.append(np.stack([np.minimum(pa, pb), np.maximum(pa, pb)], axis=1))
    if not pairs:
        return set()
    u = np.unique(np.concatenate(pairs), axis=0)
    return {(int(p), int(q)) for p, q in u}


def _merge(labels: np.ndarray, st: _State, jump_h, jump_v) -> np.ndarray:
    """Greedy best-first merging of adjacent patches whose union fits one surface (returns new labels).

    A pair merges when the union's fit (plane when both patches are planar, quadric otherwise) has an RMS
    range residual within ``merge_k`` sigma over the union and within ``1.5 merge_k`` over the smaller
    part (a small fragment of another surface is not hidden by the larger patch's many good points).
    Costs are re-evaluated lazily when a patch has changed since its pair was queued.
    """
    groups = _groups(labels)
    if len(groups) < 2:
        return labels
    thr = st.params.merge_k
    nmax = st.params.max_fit_points
    members = dict(groups)
    subs = {k: _subsample(v, nmax) for k, v in members.items()}
    counts = {k: np.bincount(st.hk[v], minlength=5) for k, v in members.items()}
    version = dict.fromkeys(members, 0)
    nbrs: dict[int, set[int]] = {k: set() for k in members}
    for a, b in _adjacency(labels, jump_h, jump_v):
        nbrs[a].add(b)
        nbrs[b].add(a)

    def cost(a: int, b: int) -> float:
        sa, sb = subs[a], subs[b]
        if sa.size < sb.size:
            sa, sb = sb, sa
        sub = np.concatenate([sa, sb])
        planar = _is_planar_counts(counts[a]) and _is_planar_counts(counts[b])
        _, z = _quick_fit(st.X[sub], st.U[sub], st.S[sub], planar, want_params=False)
        rms_all, rms_small = _rms(z), _rms(z[sa.size:])
        return rms_all if rms_small <= 1.5 * thr else float("inf")

    heap: list[tuple[float, int, int, int, int]] = []

    def push(a: int, b: int) -> None:
        a, b = min(a, b), max(a, b)
        c = cost(a, b)
        if c <= thr:
            heapq.heappush(heap, (c, a, b, version[a], version[b]))

    for a in nbrs:
        for b in nbrs[a]:
            if a < b:
                push(a, b)
    parent = np.arange(max(members) + 1)
    while heap:
        _, a, b, va, vb = heapq.heappop(heap)
        if a not in members or b not in members:
            continue
        if va != version[a] or vb != version[b]:
            push(a, b)
            continue
        members[a] = np.concatenate([members[a], members.pop(b)])
        subs[a] = _subsample(np.sort(members[a]), nmax)
        subs.pop(b)
        counts[a] = counts[a] + counts.pop(b)
        version[a] += 1
        parent[parent == b] = a
        old = nbrs[a]
        nb_b = nbrs.pop(b)
        nbrs[a] = (old | nb_b) - {a, b}
        for q in nb_b - {a}:
            nbrs[q].discard(b)
            nbrs[q].add(a)
            if q not in old:
                push(a, q)
    out = labels.copy()
    m = out >= 0
    out[m] = parent[out[m]]
    return out


def _merge_enclosed(labels: np.ndarray, valid: np.ndarray, jump_h: np.ndarray, jump_v: np.ndarray,
                    min_pixels: int) -> np.ndarray:
    """Merge small patches lying wholly inside one other patch.

    A patch is enclosed by q when every pixel next to it (4-neighbours) is q, an unlabelled return, or on
    the far side of a jump; the image border and pixels without a return count as other neighbours. Small
    enclosed patches (fewer than ``min_pixels``) join q.
    """
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
    for _ in range(10):
        pad = np.full((Hh + 2, Ww + 2), -2, dtype=np.int64)  # -2: border or no return
        lab = np.where(valid, labels, -2).astype(np.int64)
        lab[lab == -1] = -3
        pad[1:-1, 1:-1] = lab
        centre = pad[1:-1, 1:-1]
        pairs = []
        for nb, j in zip((pad[1:-1, :-2], pad[1:-1, 2:], pad[:-2, 1:-1], pad[2:, 1:-1]), across, strict=True):
            m = (centre >= 0) & (nb != centre) & (nb != -3) & ~j
            pairs.append(np.stack([centre[m], nb[m]], axis=1))
        pairs = np.unique(np.concatenate(pairs), axis=0)
        if pairs.size == 0:
            return labels
        sizes = np.bincount(labels[labels >= 0])
        owner, first, n_other = np.unique(pairs[:, 0], return_index=True, return_counts=True)
        changed = False
        remap = np.arange(sizes.size)
        for p, f, k in zip(owner, first, n_other, strict=True):
            q = int(pairs[f, 1])
            if k == 1 and q >= 0 and sizes[p] < min_pixels and sizes[q] > sizes[p] and remap[q] == q:
                remap[p] = q
                changed = True
        if not changed:
            return labels
        m = labels >= 0
        labels = labels.copy()
        labels[m] = remap[labels[m]]
    return labels


def _attach_isolated(labels: np.ndarray, st: _State, jump_h: np.ndarray, jump_v: np.ndarray) -> np.ndarray:
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
    across = np.unique(np.concatenate(pairs_j), axis=0)
    linked = np.unique(np.concatenate(pairs_n)[:, 0])
    if across.size == 0:
        return labels
    groups = _groups(labels)
    small = {k for k, v in groups.items() if v.size < st.params.min_patch_pixels}
    remap = np.arange(int(labels.max()) + 1)
    fits: dict[int, np.ndarray] = {}
    for p in sorted(small - set(linked.tolist())):
        cands = [int(q) for q in across[across[:, 0] == p, 1] if groups[int(q)].size > groups[p].size]
        best, best_rms = -1, st.params.grow_k
        for q in cands:
            if q not in fits:
                sub = _subsample(groups[q], st.params.max_fit_points)
                planar = _is_planar_counts(np.bincount(st.hk[groups[q]], minlength=5))
                fits[q], _ = _quick_fit(st.X[sub], st.U[sub], st.S[sub], planar)
            idx = groups[p]
            _, _, z = ray_residuals(fits[q], st.X[idx], st.S[idx])
            rms = _rms(np.where(np.isfinite(z), z, np.inf))
            if rms <= best_rms:
                best, best_rms = q, rms
        if best >= 0 and remap[best] == best:
            remap[p] = best
    if np.all(remap == np.arange(remap.size)):
        return labels
    out = labels.copy()
    m = out >= 0
    out[m] = remap[out[m]]
    return out


# --------------------------------------------------------------------------------------------- main entry


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


def segment(points: np.ndarray, sigma: np.ndarray, params: SegmentationParams | None = None) -> Segmentation:
    """Segment an organised range image into H-K surface patches with plane / quadric fits.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), metres, sensor frame (x right, y down, z forward)
        NaN where there is no return.
    sigma : ndarray of shape (H, W), metres
        Range-noise sigma along the ray per pixel (NaN where no return); floored at ``sigma_floor_m``.
    params : SegmentationParams, optional

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
    pts, sig = _check_inputs(points, sigma)
    shape = sig.shape
    valid = np.isfinite(pts).all(axis=-1) & np.isfinite(sig) & np.any(pts != 0, axis=-1)
    if not valid.any():
        return _empty(shape)
    sig = np.where(valid, np.maximum(sig, params.sigma_floor_m), np.nan)
    pts = np.where(valid[..., None], pts, np.nan)

    cur = curvature_images(pts, sig, params)
    hk = classify_hk(cur.H, cur.K, cur.sigma_H, cur.sigma_K, params.zero_k)
    rng = norm3(pts)
    rays = pts / rng[..., None]
    jump_h, jump_v = jump_pairs(rng, sig, rays, params.jump_k, params.jump_tan)
    crease_h, crease_v = _crease_pairs(cur.normals, cur.sigma_normal, params)
    edges = np.zeros(shape, np.uint8)
    for bit, eh, ev in ((EdgeType.JUMP, jump_h, jump_v), (EdgeType.CREASE, crease_h, crease_v)):
        e = np.zeros(shape, bool)
        e[:, :-1] |= eh
        e[:, 1:] |= eh
        e[:-1, :] |= ev
        e[1:, :] |= ev
        edges[e] |= np.uint8(bit)
    if not (hk > 0).any():
        return _empty(shape, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges)

    st = _State(X=pts.reshape(-1, 3), U=rays.reshape(-1, 3), S=sig.ravel(), hk=hk.ravel().astype(np.int64),
                params=params)
    links = _neighbour_links(shape, valid, jump_h, jump_v)

    labels = _seed_labels(hk, edges, params)
    for _ in range(params.grow_rounds):
        n_lab = int(labels.max()) + 1
        if n_lab == 0:
            break
        P = _fit_groups(_groups(labels), st, n_lab)
        _grow(labels, P, st, links, params.max_grow_iterations, params.grow_k)
    if labels.max() >= 0:
        # last pass, relaxed: single returns beyond grow_k sigma of their own surface are expected in a
        # large patch (0.3 % at 3 sigma); only what fits no neighbour within 2 grow_k is left over
        _grow(labels, P, st, links, params.max_grow_iterations, 2.0 * params.grow_k)

    # leftover pixels with defined curvature: connected pieces of their own (never linked across a jump)
    left = valid & (labels < 0) & (hk > 0)
    if left.any():
        comp = _link_components(left, jump_h, jump_v)
        sizes = np.bincount(comp[comp >= 0])
        keep = sizes >= params.min_leftover_pixels
        remap = np.where(keep, np.cumsum(keep) - 1, -1)
        comp = np.where(comp >= 0, remap[np.maximum(comp, 0)], -1)
        base = int(labels.max()) + 1
        labels[comp >= 0] = (comp[comp >= 0] + base).astype(np.int32)
        P = _fit_groups(_groups(labels), st, int(labels.max()) + 1)
        _grow(labels, P, st, links, params.max_grow_iterations, params.grow_k)

    labels = _merge_enclosed(labels, valid, jump_h, jump_v, params.min_patch_pixels)
    labels = _merge(labels, st, jump_h, jump_v)
    labels = _merge_enclosed(labels, valid, jump_h, jump_v, params.min_patch_pixels)
    labels = _attach_isolated(labels, st, jump_h, jump_v)
    labels, patches = _finalise(labels, st, params)
    return Segmentation(labels, hk, cur.H, cur.K, cur.sigma_H, cur.sigma_K, cur.normals, edges, patches)


def _finalise(labels: np.ndarray, st: _State, params: SegmentationParams):
    """Relabel 0..n-1 by decreasing size and fit the final plane / quadric of every patch."""
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
        x, s = st.X[idx], st.S[idx]
        fit: PlaneFit | QuadricSurfaceFit
        if stype == SurfaceType.PLANAR or idx.size < 10:
            fit = fit_plane(x, s)
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
