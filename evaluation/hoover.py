"""Region-segmentation metrics of Hoover et al. (1996) against a ground-truth region image.

A. Hoover, G. Jean-Baptiste, X. Jiang, P. J. Flynn, H. Bunke, D. B. Goldgof, K. Bowyer, D. W. Eggert,
A. Fitzgibbon and R. B. Fisher, "An experimental comparison of range image segmentation algorithms",
IEEE PAMI 18(7), 673-689, 1996, doi:10.1109/34.506791. The reference implementation is USF's ``compare``
tool (``compare.c``); its default tolerance is 0.51, the project's default is 0.8.

Definitions (``O[m, g]`` the number of pixels shared by machine region m and truth region g, ``T`` the
tolerance, ``0.5 < T <= 1``):

- **correct detection** of (m, g): ``O >= T |g|`` and ``O >= T |m|``; score ``(O/|g| + O/|m|) / 2``;
- **over-segmentation** of g into m1..mk (k >= 2): every ``O[mi, g] >= T |mi|`` and ``sum_i O[mi, g] >=
  T |g|``; score: the mean of (the mean of ``O[mi, g]/|mi|``) and ``sum_i O[mi, g] / |g|``;
- **under-segmentation** of m into g1..gk (k >= 2): the mirror case;
- a truth region left unclassified is **missed**, a machine region left unclassified is **noise**.

Conflicts (a region in more than one candidate classification) are resolved greedily by decreasing score,
a correct detection winning ties, so an over- or under-segmentation replaces a correct detection only when
its score is strictly larger; a candidate is accepted only if none of its regions is already classified.
Taken literally, small fragments wholly inside a truth region turn its correct detection into an
over-segmentation: the metric stays literal (the segmenter merges such fragments).

Bookkeeping choices (documented because the original leaves them to its input format):

- pixels whose truth label is -1 (no truth surface) are ignored entirely: they count neither in ``|m|`` nor
  in any overlap; a machine region with no pixel on a truth region is not scored (not noise);
- machine label -1 means "no region": such pixels count in ``|g|`` (they lower the overlap ratios) but form
  no region;
- ``min_truth_pixels``: a truth region smaller than this is **no truth**, exactly like label -1, on both
  sides: its pixels count in no ``|m|`` and in no overlap, it takes no part in the classification and is not
  counted in the truth rates (class ``unscored``); a machine region left with no pixel on a scored truth
  region is not scored either (not noise).

Why small truth regions are no truth (issue 35, "The metric itself"): Hoover et al.'s ground truth has no
"small region" category. Its operator outlined the regions worth scoring and left everything else (shadow and
no return, areas too small or too ambiguous to outline) with the no-region label, and the comparison counts
``O``, ``|m|`` and ``|g|`` over the outlined pixels only: a machine pixel over no-region truth is neither right
nor wrong. The ``min_truth_pixels`` floor (200 pixels, ``evaluation.metrics.MIN_SCORED_PIXELS``) stands for that
operator's decision on our synthetic truth, which outlines every visible surface piece however small; what it
rejects must therefore be what the operator would not have outlined. Letting such regions take part while
leaving them out of the rates (this module until issue 35) put pixels that no rate counts into ``|m|``: a
machine region covering a scored region and a few small neighbours could fail ``O >= T |m|`` (or turn into an
under-segmentation of the scored region with them) because of pixels of unscored surfaces, and a machine region
lying mostly on small ones was dropped from the noise rate. An independent implementation that treats them as
no truth agreed on the mean but not frame by frame; that treatment is the one adopted here. Source: the
paper's definitions above and its ground-truth convention. The original ``compare`` program could not be
read: searches of public code, documentation and web pages for it (USF range segmentation comparison,
``compare.c``) found only the paper's abstract and later re-implementations (e.g. the Orfeo
Toolbox's ``HooverCompareSegmentation``, which excludes a background label from both images and has no size
floor), so this follows the paper, not a reading of ``compare.c``. The hand-made cases of
``tests/evaluation/test_hoover.py`` pin it, one per kind with and without a small truth region.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi

from evaluation.metrics import HOOVER_RATES

__all__ = [
    "CORRECT",
    "OVER",
    "UNDER",
    "MISSED",
    "NOISE",
    "UNSCORED",
    "HooverScore",
    "overlap_table",
    "hoover_score",
    "hoover_sweep",
    "MISSED_CAUSES",
    "missed_causes",
    "connected_truth_regions",
    "mean_scores",
    "DEFAULT_SWEEP",
]

DEFAULT_SWEEP: tuple[float, ...] = tuple(float(t) for t in np.linspace(0.51, 0.95, 12))
"""Tolerances of the default sweep: 12 values from 0.51 (``compare``'s default) to 0.95."""

CORRECT = "correct"
OVER = "over"
UNDER = "under"
MISSED = "missed"
NOISE = "noise"
UNSCORED = "unscored"


@dataclass(frozen=True)
class HooverScore:
    """Hoover metrics of one machine segmentation against one truth image at one tolerance.

    Attributes
    ----------
    tolerance : float
    n_truth : int
        Scored truth regions (at least ``min_truth_pixels`` pixels).
    n_machine : int
        Scored machine regions (see the module notes).
    n_correct, n_over, n_under, n_missed : int
        Scored truth regions in each category (they sum to ``n_truth``).
    n_noise : int
        Scored machine regions classified as noise.
    n_over_instances, n_under_instances : int
        Over-segmentation instances (truth regions split) and under-segmentation instances (machine regions
        covering several truth regions), as ``compare.c`` counts them.
    correct_detection_rate, over_rate, under_rate, missed_rate : float
        The counts divided by ``n_truth`` (NaN when ``n_truth == 0``).
    noise_rate : float
        ``n_noise / n_machine`` (NaN when ``n_machine == 0``).
    truth_ids, machine_ids : tuple of int
        Region labels, ascending (all regions present, scored or not).
    truth_class, machine_class : tuple of str
        Category of each region: correct, over, under, missed (truth) or noise (machine), or unscored.
    truth_partners : tuple of tuple of int
        For each truth region, the machine regions of its classification (empty when missed).
    min_truth_pixels : int
        The scoring floor the score was made with: smaller truth regions were no truth (module notes).
    """

    tolerance: float
    n_truth: int
    n_machine: int
    n_correct: int
    n_over: int
    n_under: int
    n_missed: int
    n_noise: int
    n_over_instances: int
    n_under_instances: int
    correct_detection_rate: float
    over_rate: float
    under_rate: float
    missed_rate: float
    noise_rate: float
    truth_ids: tuple[int, ...]
    machine_ids: tuple[int, ...]
    truth_class: tuple[str, ...]
    machine_class: tuple[str, ...]
    truth_partners: tuple[tuple[int, ...], ...]
    min_truth_pixels: int = 0

    def as_dict(self) -> dict[str, float]:
        """The summary keys of the results contract (DESIGN section 8)."""
        return {
            "correct_detection_rate": self.correct_detection_rate,
            "over_rate": self.over_rate,
            "under_rate": self.under_rate,
            "missed_rate": self.missed_rate,
            "noise_rate": self.noise_rate,
            "tolerance": self.tolerance,
        }


def _check_labels(machine_labels: np.ndarray, truth_labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    m = np.asanyarray(machine_labels)
    g = np.asanyarray(truth_labels)
    if m.ndim != 2 or g.ndim != 2:
        raise ValueError(f"expected 2D label images (H, W), got {m.shape} and {g.shape}")
    if m.shape != g.shape:
        raise ValueError(f"machine and truth label images differ in shape: {m.shape} vs {g.shape}")
    for name, a in (("machine_labels", m), ("truth_labels", g)):
        if not np.issubdtype(a.dtype, np.integer):
            if not np.all(np.isfinite(a)) or not np.all(a == np.round(a)):
                raise ValueError(f"{name} must hold integer labels")
    return m.astype(np.int64), g.astype(np.int64)


def overlap_table(machine_labels: np.ndarray, truth_labels: np.ndarray) -> tuple[np.ndarray, ...]:
    """Pixel overlaps of machine and truth regions (vectorised, sparse).

    Parameters
    ----------
    machine_labels, truth_labels : ndarray of shape (H, W), int
        -1 (any negative) = no region. Pixels with negative truth are ignored.

    Returns
    -------
    machine_ids : ndarray of shape (M,)
        Machine regions with at least one pixel on a truth region.
    truth_ids : ndarray of shape (G,)
        All truth regions.
    machine_sizes, truth_sizes : ndarray of shape (M,), (G,)
        ``|m|`` (pixels on truth regions only) and ``|g|``.
    pairs : ndarray of shape (P, 3)
        Rows ``(machine index, truth index, overlap)`` for every overlapping pair.
    """
    m, g = _check_labels(machine_labels, truth_labels)
    keep = g >= 0
    mv, gv = m[keep], g[keep]
    truth_ids, gi, truth_sizes = np.unique(gv, return_inverse=True, return_counts=True)
    has = mv >= 0
    machine_ids, mi, machine_sizes = np.unique(mv[has], return_inverse=True, return_counts=True)
    if machine_ids.size:
        code = mi.astype(np.int64) * max(truth_ids.size, 1) + gi[has]
        codes, counts = np.unique(code, return_counts=True)
        pairs = np.stack([codes // max(truth_ids.size, 1), codes % max(truth_ids.size, 1), counts], axis=1)
    else:
        pairs = np.zeros((0, 3), dtype=np.int64)
    return machine_ids, truth_ids, machine_sizes, truth_sizes, pairs


def hoover_score(
    machine_labels: np.ndarray,
    truth_labels: np.ndarray,
    tolerance: float = 0.8,
    min_truth_pixels: int = 0,
) -> HooverScore:
    """Classify every truth and machine region (Hoover et al. 1996) and report counts and rates.

    Parameters
    ----------
    machine_labels : ndarray of shape (H, W), int
        Machine segmentation, -1 = no region.
    truth_labels : ndarray of shape (H, W), int
        Ground-truth regions (connected pieces, see :func:`connected_truth_regions`), -1 = no truth.
    tolerance : float
        ``T`` in (0.5, 1].
    min_truth_pixels : int
        Truth regions smaller than this are no truth: their pixels count on neither side (module notes).

    Returns
    -------
    HooverScore

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.array([[0, 0, 1, 1]] * 4)
    >>> hoover_score(truth, truth).correct_detection_rate
    1.0
    """
    return score_table(overlap_table(machine_labels, truth_labels), tolerance, min_truth_pixels)


def score_table(table: tuple[np.ndarray, ...], tolerance: float = 0.8, min_truth_pixels: int = 0) -> HooverScore:
    """:func:`hoover_score` from the overlap table of :func:`overlap_table` (which does not depend on the
    tolerance: a sweep computes it once)."""
    if not 0.5 < float(tolerance) <= 1.0:
        raise ValueError(f"tolerance must be in (0.5, 1], got {tolerance!r}")
    if min_truth_pixels < 0:
        raise ValueError(f"min_truth_pixels must be >= 0, got {min_truth_pixels!r}")
    T = float(tolerance)
    machine_ids, truth_ids, msize, gsize, pairs = _without_small_truth(table, min_truth_pixels)
    nM, nG = machine_ids.size, truth_ids.size
    pm, pg, po = pairs[:, 0], pairs[:, 1], pairs[:, 2].astype(np.float64)
    # candidates: (score, kind priority, truth indices, machine indices, kind)
    cands: list[tuple[float, int, tuple[int, ...], tuple[int, ...], str]] = []
    ok_m = po >= T * msize[pm]  # m mostly inside g
    ok_g = po >= T * gsize[pg]  # g mostly inside m
    for k in np.flatnonzero(ok_m & ok_g):
        score = 0.5 * (po[k] / gsize[pg[k]] + po[k] / msize[pm[k]])
        cands.append((score, 0, (int(pg[k]),), (int(pm[k]),), CORRECT))
    # over-segmentation: per truth region, the machine regions mostly inside it
    for g_idx in np.unique(pg[ok_m]):
        sel = ok_m & (pg == g_idx)
        if sel.sum() >= 2 and po[sel].sum() >= T * gsize[g_idx]:
            score = 0.5 * (np.mean(po[sel] / msize[pm[sel]]) + po[sel].sum() / gsize[g_idx])
            cands.append((float(score), 1, (int(g_idx),), tuple(int(v) for v in pm[sel]), OVER))
    # under-segmentation: per machine region, the truth regions mostly inside it
    for m_idx in np.unique(pm[ok_g]):
        sel = ok_g & (pm == m_idx)
        if sel.sum() >= 2 and po[sel].sum() >= T * msize[m_idx]:
            score = 0.5 * (np.mean(po[sel] / gsize[pg[sel]]) + po[sel].sum() / msize[m_idx])
            cands.append((float(score), 1, tuple(int(v) for v in pg[sel]), (int(m_idx),), UNDER))
    # greedy: highest score first; on equal scores the correct detection (priority 0) wins
    cands.sort(key=lambda c: (-c[0], c[1], c[2], c[3]))
    t_class = [MISSED] * nG
    m_class = [NOISE] * nM
    t_partners: list[tuple[int, ...]] = [()] * nG
    t_done = np.zeros(nG, bool)
    m_done = np.zeros(nM, bool)
    n_over_inst = n_under_inst = 0
    for _, _, gs, ms, kind in cands:
        if t_done[list(gs)].any() or m_done[list(ms)].any():
            continue
        t_done[list(gs)] = True
        m_done[list(ms)] = True
        for gi in gs:
            t_class[gi] = kind
            t_partners[gi] = tuple(int(machine_ids[j]) for j in ms)
        for mj in ms:
            m_class[mj] = kind
        n_over_inst += kind == OVER
        n_under_inst += kind == UNDER

    scored_t = gsize >= min_truth_pixels
    scored_m = msize > 0  # a machine region with no pixel on a scored truth region is not scored
    t_final = tuple(c if s else UNSCORED for c, s in zip(t_class, scored_t, strict=True))
    m_final = tuple(c if s else UNSCORED for c, s in zip(m_class, scored_m, strict=True))
    n_truth = int(scored_t.sum())
    n_machine = int(scored_m.sum())
    counts = {k: sum(c == k for c in t_final) for k in (CORRECT, OVER, UNDER, MISSED)}
    n_noise = sum(c == NOISE for c in m_final)

    def rate(n: int, d: int) -> float:
        return n / d if d else float("nan")

    return HooverScore(
        tolerance=T,
        n_truth=n_truth,
        n_machine=n_machine,
        n_correct=counts[CORRECT],
        n_over=counts[OVER],
        n_under=counts[UNDER],
        n_missed=counts[MISSED],
        n_noise=n_noise,
        n_over_instances=int(n_over_inst),
        n_under_instances=int(n_under_inst),
        correct_detection_rate=rate(counts[CORRECT], n_truth),
        over_rate=rate(counts[OVER], n_truth),
        under_rate=rate(counts[UNDER], n_truth),
        missed_rate=rate(counts[MISSED], n_truth),
        noise_rate=rate(n_noise, n_machine),
        truth_ids=tuple(int(v) for v in truth_ids),
        machine_ids=tuple(int(v) for v in machine_ids),
        truth_class=t_final,
        machine_class=m_final,
        truth_partners=tuple(t_partners),
        min_truth_pixels=int(min_truth_pixels),
    )


def _without_small_truth(table: tuple[np.ndarray, ...], min_truth_pixels: int) -> tuple[np.ndarray, ...]:
    """The overlap table with the pixels of truth regions under ``min_truth_pixels`` made no truth: their
    overlaps dropped and ``|m|`` counted again without them (the regions stay listed, with no overlap)."""
    machine_ids, truth_ids, msize, gsize, pairs = table
    small = gsize < min_truth_pixels
    if not small.any():
        return table
    pairs = pairs[~small[pairs[:, 1]]]
    msize = np.bincount(pairs[:, 0], weights=pairs[:, 2], minlength=machine_ids.size).astype(np.int64)
    return machine_ids, truth_ids, msize, gsize, pairs


MISSED_CAUSES: tuple[str, ...] = ("unlabelled", "split", "merged")
"""Why a truth region was missed (:func:`missed_causes`)."""


def missed_causes(machine_labels: np.ndarray, truth_labels: np.ndarray, score: HooverScore,
                  table: tuple[np.ndarray, ...] | None = None) -> dict[str, int]:
    """Count the scored truth regions that ``score`` classifies as missed, by cause.

    The cause comes from the machine region ``m`` with the largest overlap ``O`` with the missed region
    ``g``. Both labels and ``score`` must come from the same images (``score = hoover_score(machine_labels,
    truth_labels, ...)``). With ``T`` the score's tolerance:

    - **merged**: ``O < T |m|``, so ``m`` also covers other surfaces;
    - **unlabelled**: ``O`` plus the pixels of ``g`` that no machine region labels reach ``T |g|``. Labelling
      them would have been enough;
    - **split**: otherwise. ``g`` is spread over several machine regions that are not all inside it.

    A region that no machine region touches is unlabelled. ``table``: the images' :func:`overlap_table`, when
    the caller has it already.

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.zeros((10, 10), int)
    >>> machine = np.where(np.arange(10)[None, :] < 7, 0, -1) * np.ones((10, 1), int)
    >>> missed_causes(machine, truth, hoover_score(machine, truth))
    {'unlabelled': 1, 'split': 0, 'merged': 0}
    """
    out = dict.fromkeys(MISSED_CAUSES, 0)
    missed = [g for g, c in zip(score.truth_ids, score.truth_class, strict=True) if c == MISSED]
    if not missed:
        return out
    m, g = _check_labels(machine_labels, truth_labels)
    machine_ids, truth_ids, msize, gsize, pairs = _without_small_truth(
        table if table is not None else overlap_table(m, g), score.min_truth_pixels)
    unlabelled = np.bincount(np.searchsorted(truth_ids, g[(g >= 0) & (m < 0)]), minlength=truth_ids.size)
    T = score.tolerance
    for gid in missed:
        k = int(np.searchsorted(truth_ids, gid))
        rows = pairs[pairs[:, 1] == k]
        if rows.size == 0:
            out["unlabelled"] += 1
            continue
        best = rows[np.argmax(rows[:, 2])]
        overlap = float(best[2])
        if overlap < T * msize[best[0]]:
            out["merged"] += 1
        elif overlap + unlabelled[k] >= T * gsize[k]:
            out["unlabelled"] += 1
        else:
            out["split"] += 1
    return out


def hoover_sweep(
    machine_labels: np.ndarray,
    truth_labels: np.ndarray,
    tolerances: Sequence[float] | np.ndarray = DEFAULT_SWEEP,
    min_truth_pixels: int = 0,
) -> list[HooverScore]:
    """:func:`hoover_score` at each tolerance (default 12 values from 0.51 to 0.95)."""
    table = overlap_table(machine_labels, truth_labels)
    return [score_table(table, float(t), min_truth_pixels) for t in tolerances]


def connected_truth_regions(surface_id_image: np.ndarray, connectivity: int = 4) -> np.ndarray:
    """Split every surface id into its connected pieces: the truth regions of the Hoover metric.

    Parameters
    ----------
    surface_id_image : ndarray of shape (H, W), int
        Per-pixel surface id, negative = none.
    connectivity : int
        4 or 8.

    Returns
    -------
    ndarray of shape (H, W), int64
        Region labels 0..n-1 (numbered in raster order of their first pixel), -1 where the input is < 0.

    Examples
    --------
    >>> import numpy as np
    >>> connected_truth_regions(np.array([[5, 7, 5]])).tolist()
    [[0, 1, 2]]
    """
    ids = np.asanyarray(surface_id_image)
    if ids.ndim != 2:
        raise ValueError(f"expected a surface id image of shape (H, W), got {ids.shape}")
    if connectivity not in (4, 8):
        raise ValueError(f"connectivity must be 4 or 8, got {connectivity!r}")
    ids = ids.astype(np.int64)
    out = np.full(ids.shape, -1, dtype=np.int64)
    struct = ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)
    offset = 0
    for sid in np.unique(ids[ids >= 0]):
        lab, n = ndi.label(ids == sid, structure=struct)
        m = lab > 0
        out[m] = lab[m] - 1 + offset
        offset += n
    if offset == 0:
        return out
    # renumber in raster order of first pixel (deterministic, independent of id values)
    flat = out.ravel()
    valid = np.flatnonzero(flat >= 0)
    _, first = np.unique(flat[valid], return_index=True)
    order = np.argsort(first)
    remap = np.empty(offset, dtype=np.int64)
    remap[order] = np.arange(offset)
    out[out >= 0] = remap[out[out >= 0]]
    return out


def mean_scores(scores: Sequence[HooverScore]) -> dict[str, float]:
    """Rates averaged over images (NaN rates skipped), as the summary reports them."""
    out: dict[str, float] = {}
    for k in HOOVER_RATES:
        v = np.array([getattr(s, k) for s in scores], dtype=np.float64)
        v = v[np.isfinite(v)]
        out[k] = float(v.mean()) if v.size else float("nan")
    tol = {s.tolerance for s in scores}
    out["tolerance"] = tol.pop() if len(tol) == 1 else float("nan")
    return out
