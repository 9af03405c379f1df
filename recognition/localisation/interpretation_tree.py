"""Interpretation-tree search of scene items against model elements (the paper's section 4).

The search (:func:`match`) assigns each item a model element or a wildcard (spurious, changed or
misclassified patch). It is an interpretation tree cut at the depth where the pose is fixed (DESIGN 6.3):

* unary constraints: type, invariants within tolerance (radius, half-angle), a visible length or extent
  no larger than the model's, an area no larger than the model face's; with a pose prior, the item moved
  by the prior must lie near the candidate;
* binary constraints against every earlier pair, tested for all candidates of a node at once on arrays:
  angles between normals/axes, distances between parallel planes, from axes and centres to planes,
  between axes, between centres, and between the two items' positions, which must both lie on their
  elements (a face, an axis segment: ``ModelElements.bound_centre`` and ``bound_radius``);
* items ordered by fewest candidates (tempered by size: small patches are the likeliest spurious); seeds
  of 2-3 items are enumerated by their last item - (0,1), (0,2), (1,2), (0,3), ... - so a spurious item
  costs a few seeds, never a whole subtree, and every item is tried early;
* as soon as a seed's pairs constrain 6 DOF (a cheap model-frame test, then the closed form of
  :mod:`.pose`), every other item is tested against that pose at once, on flat arrays of all
  (item, candidate) pairs, taking its best consistent element or a wildcard: a *leaf*. Leaves with more
  than ``max_wildcard_fraction * n + extra_wildcards`` wildcards are dropped; a pose seen before is not
  tested again;
* a node budget and a time budget (CPU, with a wall-clock cap): the search stops with what it has and says
  why (``MatchResult.stop_reason``); it also stops once a leaf explains ``stop_fraction`` of the items;
* the best leaves are then refined with all their pairs (weighted Gauss-Newton) and completed again.
  When no seed fixes 6 DOF, the largest partial assignments are returned as underconstrained hypotheses.

Hypotheses are deduplicated by pose and ranked by the summed ``log(pixels)`` of their matched items; the
list handed to the caller, who verifies them (:mod:`.verification`), holds the best half by that score
and, for every item, the best hypothesis that explains it (:func:`_diverse`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from recognition.describe import SceneDescription
from recognition.tuning import AUTO
from scenes.geometry import perpendicular_basis
from scenes.model import SceneModel

from .matching import (
    _DIMS,
    KINDS,
    MatchParams,
    ModelElements,
    SceneItem,
    _row_norms,
    binary_ok,
    make_pair,
    model_elements,
    scene_items,
    unary_candidates,
)
from .pose import PoseEstimate, estimate_pose, pose_hypotheses, sorted_with_ties

__all__ = ["Hypothesis", "MatchResult", "match", "given_match"]


@dataclass(frozen=True)
class Hypothesis:
    """A leaf of the tree.

    Attributes
    ----------
    pairs : tuple of (item index, element index or -1 for a wildcard), one per item in the tree.
    pose : the pose from all matched pairs.
    score : summed ``log(pixels)`` of the matched items.
    n_matched : int
    """

    pairs: tuple[tuple[int, int], ...]
    pose: PoseEstimate
    score: float
    n_matched: int


@dataclass(frozen=True)
class MatchResult:
    """Hypotheses (best score first), the items and elements they index, and search statistics
    (``stop_reason``: why the search stopped early - node or time budget - or "" when it completed).
    ``matchable``: the patch indices of every scene item, those without a candidate element included."""

    hypotheses: tuple[Hypothesis, ...]
    items: tuple[SceneItem, ...]
    elements: ModelElements
    n_nodes: int
    exhausted: bool
    candidates: tuple[int, ...] = field(default=())
    stop_reason: str = ""
    matchable: frozenset[int] = frozenset()


class _FlatPairs:
    """Every (item, candidate element) pair of the tree as flat arrays, so that a fixed pose is tested against
    all remaining items and all their candidates at once (DESIGN 6.3: no per-pair numpy calls)."""

    def __init__(self, items, el: ModelElements, cands):
        self.el = el
        self.n_items = len(items)
        self.groups = []
        for kind in KINDS:
            it_idx = [i for i, it in enumerate(items) if it.kind == kind and len(cands[i])]
            if not it_idx:
                continue
            ii = np.concatenate([np.full(len(cands[i]), i) for i in it_idx]).astype(np.intp)
            ee = np.concatenate([cands[i] for i in it_idx]).astype(np.intp)
            g = dict(kind=kind, item=ii, el=ee,
                     d=np.array([items[i].direction for i in ii]).reshape(-1, 3),
                     p=np.array([items[i].position for i in ii]).reshape(-1, 3),
                     half_len=np.array([0.5 * items[i].length if np.isfinite(items[i].length) else 0.0
                                        for i in ii]),
                     radius=np.array([items[i].radius for i in ii]),
                     ang_tol=np.array([items[i].angle_tol for i in ii]),
                     dist_tol=np.array([items[i].dist_tol for i in ii]),
                     dm=el.direction[ee], pm=el.position[ee], hs=el.half_size[ee], u=el.u_axis[ee],
                     length=el.length[ee], start=el.start[ee], half_angle=el.half_angle[ee])
            g["is_rect"] = np.isfinite(g["u"][:, 0])
            g["u0"] = np.where(g["is_rect"][:, None], g["u"], 0.0)
            g["v0"] = np.cross(g["dm"], g["u0"])
            self.groups.append(g)

    def best(self, T: np.ndarray, ang_scale: float, dist_scale: float, lever_sigma: float, centre: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray]:
        """For every item: the best consistent element under ``T`` (-1: none) and its misfit (inf: none).

        Tolerances are ``ang_scale`` x the item's angle tolerance and ``dist_scale`` x its distance tolerance
        plus ``lever_sigma`` x the item's distance from ``centre`` (sensor frame; the seed pose's rotation
        uncertainty moves far items more)."""
        R, t = T[:3, :3], T[:3, 3]
        best_e = np.full(self.n_items, -1, dtype=np.intp)
        best_m = np.full(self.n_items, np.inf)
        for g in self.groups:
            d_w = g["d"] @ R.T
            p_w = g["p"] @ R.T + t
            dm, pm = g["dm"], g["pm"]
            lever = _row_norms(g["p"] - centre)
            atol = ang_scale * g["ang_tol"] + lever_sigma
            dtol = dist_scale * g["dist_tol"] + lever_sigma * lever
            w = p_w - pm
            hl = g["half_len"]
            kind = g["kind"]
            if kind == "PLAN":
                ang = np.arccos(np.clip(np.sum(dm * d_w, axis=1), -1, 1))
                dist = np.abs(np.sum(dm * w, axis=1))
                eu = np.abs(np.sum(w * g["u0"], axis=1)) - g["hs"][:, 0]
                ev = np.abs(np.sum(w * g["v0"], axis=1)) - g["hs"][:, 1]
                rad = _row_norms(w - np.sum(w * dm, axis=1)[:, None] * dm) - g["hs"][:, 0]
                excess = np.where(g["is_rect"], np.maximum(eu, ev), rad)
                inside = excess <= hl + dtol
            elif kind in ("CYL", "CONE"):
                c = np.sum(dm * d_w, axis=1)
                ang = np.arccos(np.clip(np.abs(c) if kind == "CYL" else c, -1, 1))
                along = np.sum(w * dm, axis=1)
                dist = _row_norms(w - along[:, None] * dm)
                if kind == "CYL":
                    inside = np.abs(along) - 0.5 * g["length"] <= hl + dtol
                else:
                    lo, hi = g["start"], g["start"] + g["length"]
                    inside = (along >= lo - hl - dtol) & (along <= hi + hl + dtol)
                    dist = np.maximum(dist, np.abs(along * np.tan(g["half_angle"]) - g["radius"]))
            else:
                ang = np.zeros(len(dm))
                dist = _row_norms(w)
                inside = np.ones(len(dm), dtype=bool)
            mis = np.maximum(ang / atol, dist / dtol)
            mis = np.where((mis <= 1.0) & inside, mis, np.inf)
            order = np.lexsort((mis, g["item"]))
            ii = g["item"][order]
            first = np.flatnonzero(np.r_[True, ii[1:] != ii[:-1]])
            sel = order[first]
            best_m[g["item"][sel]] = mis[sel]
            best_e[g["item"][sel]] = np.where(np.isfinite(mis[sel]), g["el"][sel], -1)
        return best_e, best_m


def _seed_constrains(items, el: ModelElements, assigned: list[tuple[int, int]]) -> bool:
    """Cheap test, in the model frame, of whether the pairs can constrain all 6 DOF (the pose solver has the
    last word): two clearly non-parallel directions, or one direction family plus an off-axis lever (two
    separated parallel axes, an axis and a point, two points); translation rows of full rank."""
    dirs, rows, lines, pts = [], [], [], []
    for i, e in assigned:
        if e < 0:
            continue
        k = items[i].kind
        d, p = el.direction[e], el.position[e]
        if k == "PLAN":
            dirs.append(d)
            rows.append(d)
        elif k in ("CYL", "CONE"):
            dirs.append(d)
            rows.append(d) if k == "CONE" else None
            rows.extend(perpendicular_basis(d))
            lines.append((p, d))
            if k == "CONE":
                pts.append(p)
        else:
            rows.extend(np.eye(3))
            pts.append(p)
    if len(rows) < 3:
        return False
    if np.linalg.svd(np.array(rows), compute_uv=False)[2] < 0.25:
        return False
    D = np.array(dirs).reshape(-1, 3)
    if len(D) >= 2:
        c = np.abs(D @ D.T)
        if np.min(c) < math.cos(math.radians(14.0)):
            return True
    # a single direction family (or none): the roll needs a lever
    a = D[0] if len(D) else None
    levers = [q2 - q1 for (q1, _), (q2, _) in zip(lines, lines[1:], strict=False)]
    levers += [q - l[0] for l in lines for q in pts]
    levers += [q2 - q1 for q1, q2 in zip(pts, pts[1:], strict=False)]
    for v in levers:
        if a is not None:
            v = v - (v @ a) * a
        if np.linalg.norm(v) > 0.05:
            return True
    return False


class _Search:
    """Depth-limited interpretation tree: seeds of 2-4 consistent pairs that fix the pose (items taken in
    order of fewest candidates, item tuples enumerated by their last item so every item is tried early),
    each seed's closed-form pose tested against every other item at once (:class:`_FlatPairs`)."""

    def __init__(self, items, el, cands, params: MatchParams, length_m: float):
        self.items, self.el, self.cands, self.p = items, el, cands, params
        self.length_m = length_m
        self.n_nodes = 0
        self.leaves: list[Hypothesis] = []
        self.max_wild = int(params.max_wildcard_fraction * len(items)) + params.extra_wildcards
        self.total_weight = float(sum(it.weight for it in items))
        self.best_score = 0.0
        self._poses = np.zeros((64, 4, 4))
        self._n_poses = 0
        self.dedupe_angle = math.radians(params.same_pose_angle_deg)
        self.dedupe_dist = params.same_pose_rel * length_m
        # fewest candidates first, tempered by size: a small patch is the likeliest to be spurious or
        # misclassified, and a seed that starts with it wastes the budget
        self.order = sorted(range(len(items)), key=lambda i: (math.log(len(cands[i]) + 1.0)
                                                              - params.size_weight * math.log(items[i].n_pixels),
                                                              -items[i].n_pixels))
        self.flat = _FlatPairs(items, el, cands)
        self.stop_reason = ""
        self.t0 = time.perf_counter()
        self.c0 = time.process_time()
        self.partial: list[tuple[int, list[tuple[int, int]]]] = []  # (dims, pairs) when nothing fixes 6 DOF

    def out_of_budget(self) -> bool:
        if self.stop_reason:
            return True
        if self.n_nodes >= self.p.max_nodes:
            self.stop_reason = f"node budget ({self.p.max_nodes}) reached"
        elif time.process_time() - self.c0 > self.p.max_time_s:
            self.stop_reason = f"time budget ({self.p.max_time_s:g} s CPU) reached"
        elif time.perf_counter() - self.t0 > self.p.max_wall_s:
            self.stop_reason = f"time budget ({self.p.max_wall_s:g} s wall) reached"
        return bool(self.stop_reason)

    def pose(self, assigned: list[tuple[int, int]], T_init=None, iterations=None, assess=True,
             chi2_slack: float = 1.0) -> list[PoseEstimate]:
        pairs = [make_pair(self.items[i], self.el, e) for i, e in assigned if e >= 0]
        hyps = pose_hypotheses(pairs, length_m=self.length_m, max_sigma=self.p.max_free_sigma, T_init=T_init,
                               iterations=(1 if T_init is None else 3) if iterations is None else iterations,
                               max_signs=4, assess=assess)
        return [h for h in hyps if h.ok and h.cost <= chi2_slack * (self.p.pose_chi2_factor * h.n_residuals + 10.0)]

    def run(self):
        order = self.order
        n = len(order)
        max_depth = self.p.max_seed_size
        # item tuples (positions in ``order``) by their last position: (0,1), (0,2), (1,2), (0,3), ...
        for last in range(1, n):
            for first in range(last):
                self._seed([order[first], order[last]], [], max_depth, last)
                if self.out_of_budget():
                    return
            if self.best_score >= self.p.stop_fraction * self.total_weight and len(self.leaves) > 0 \
                    and last >= min(n - 1, 3):
                self.stop_reason = ""  # explained almost everything: done
                return

    def _seed(self, want: list[int], assigned: list[tuple[int, int]], max_depth: int, last: int) -> None:
        """Assign ``want[0]`` (then the rest) every consistent candidate; when the pairs fix 6 DOF, test the
        pose; otherwise extend with one more item positioned after ``last`` in the order (depth-limited)."""
        if self.out_of_budget():
            return
        if not want:
            if len(assigned) >= max_depth:
                return
            # add a third (fourth) item after the last one used
            for pos in range(last + 1, len(self.order)):
                self._seed([self.order[pos]], assigned, max_depth, pos)
                if self.out_of_budget():
                    return
            return
        i = want[0]
        item = self.items[i]
        cand = self.cands[i]
        for j, e in assigned:
            if len(cand) == 0:
                break
            cand = cand[binary_ok(self.items[j], e, item, cand, self.el, self.p.length_slack)]
        self.n_nodes += 1
        for e in cand:
            if self.out_of_budget():
                return
            new = assigned + [(i, int(e))]
            if len(want) > 1:
                self._seed(want[1:], new, max_depth, last)
                continue
            if _seed_constrains(self.items, self.el, new):
                self.n_nodes += 1
                hyps = self.pose(new, iterations=0, assess=False, chi2_slack=3.0)  # closed form; finish() assesses
                if hyps:
                    for h in hyps[:2]:
                        self._complete(new, h)
                    continue
            # pairs that fix fewer than 6 DOF are kept, at every depth, for when no seed fixes all 6: a floor and
            # a wall with nothing else consistent (the pipe patch a merge) still place the sensor but for a shift
            # along the wall, which the caller may find by agreement
            self.partial.append((sum(_DIMS[self.items[k].kind] for k, _ in new), new))
            if len(new) < max_depth:
                self._seed([], new, max_depth, last)

    def _complete(self, seed: list[tuple[int, int]], pose: PoseEstimate) -> None:
        """Every other item takes its best element consistent with the seed's pose, all at once."""
        T = pose.T_world_sensor
        if self._seen(T):
            return
        seed_items = [i for i, _ in seed]
        # rotation uncertainty of a seed pose: about the worst direction sigma of its items
        s_rot = max(self.items[i].sigma_angle for i in seed_items)
        centre = np.mean([self.items[i].position for i in seed_items], axis=0)
        best_e, _ = self.flat.best(T, 2.0, 2.0, 3.0 * s_rot, centre)
        for i, e in seed:
            best_e[i] = e
        n_w = int(np.sum(best_e < 0))
        if n_w > self.max_wild:
            self._remember(T)  # too many items unexplained: not a leaf, but do not test this pose again
            return
        out = [(i, int(best_e[i])) for i in range(len(self.items))]
        self._leaf(out, pose)

    def _remember(self, T: np.ndarray) -> None:
        if self._n_poses == len(self._poses):
            self._poses = np.concatenate([self._poses, np.zeros_like(self._poses)])
        self._poses[self._n_poses] = T
        self._n_poses += 1

    def _seen(self, T: np.ndarray) -> bool:
        """Whether a leaf with (nearly) the same pose exists (all leaves tested at once)."""
        if self._n_poses == 0:
            return False
        P = self._poses[: self._n_poses]
        cos = (np.einsum("nij,ij->n", P[:, :3, :3], T[:3, :3]) - 1.0) / 2.0
        close = (cos > math.cos(self.dedupe_angle)) & (
            _row_norms(P[:, :3, 3] - T[:3, 3]) < self.dedupe_dist)
        return bool(close.any())

    def _leaf(self, assigned, pose: PoseEstimate) -> None:
        matched = [i for i, e in assigned if e >= 0]
        score = float(sum(self.items[i].weight for i in matched))
        self.leaves.append(Hypothesis(tuple(sorted(assigned)), pose, score, len(matched)))
        self._remember(pose.T_world_sensor)
        if pose.free_dof == 0:
            self.best_score = max(self.best_score, score)

    def finish(self, max_hypotheses: int) -> list[Hypothesis]:
        """The best leaves refined with all their pairs (a second completion under the refined pose); when no
        seed fixed 6 DOF, the largest partial assignments as underconstrained hypotheses."""
        leaves = _diverse(sorted_with_ties(self.leaves, first=lambda h: -h.score, cost=lambda h: h.pose.cost,
                                           tiebreak=_tiebreak), self.order,
                          2 * max_hypotheses)
        out: list[Hypothesis] = []
        for h in leaves:
            T = h.pose.T_world_sensor
            ref = self.pose(list(h.pairs), T_init=T)
            if not ref:
                out.append(h)
                continue
            pose = ref[0]
            seed_items = [i for i, e in h.pairs if e >= 0]
            centre = np.mean([self.items[i].position for i in seed_items], axis=0)
            best_e, _ = self.flat.best(pose.T_world_sensor, 2.0, 2.0, 0.0, centre)
            pairs = [(i, int(best_e[i])) for i in range(len(self.items))]
            if pairs != list(h.pairs) and sum(e >= 0 for _, e in pairs) >= h.n_matched:
                ref2 = self.pose(pairs, T_init=pose.T_world_sensor)
                if ref2 and ref2[0].free_dof == 0:
                    pose = ref2[0]
                else:
                    pairs = list(h.pairs)
            else:
                pairs = list(h.pairs)
            matched = [i for i, e in pairs if e >= 0]
            out.append(Hypothesis(tuple(pairs), pose, float(sum(self.items[i].weight for i in matched)),
                                  len(matched)))
        if not out and self.partial:
            self.partial.sort(key=lambda x: -x[0])
            for _, pairs in self.partial[: max_hypotheses]:
                hyps = self.pose(pairs, iterations=3)
                paired = {k for k, _ in pairs}
                full = pairs + [(i, -1) for i in range(len(self.items)) if i not in paired]
                # every pose the pairs admit: a pipe's axis fixes the rotation only up to its sign, and which
                # of the two the solver lists first turns on the last bits of the fits
                for h in hyps:
                    out.append(Hypothesis(tuple(sorted(full)), h,
                                          float(sum(self.items[i].weight for i, _ in pairs)), len(pairs)))
        return out


def _tiebreak(h: Hypothesis) -> tuple:
    """The order of hypotheses that fit equally well (:func:`.pose.sorted_with_ties`): by pairs, signs, then the
    pose itself (to a micrometre and a microradian: the same pairs and signs can settle in mirror poses)."""
    T = h.pose.T_world_sensor
    return h.pairs, h.pose.signs, () if T is None else tuple(np.round(T[:3], 6).ravel().tolist())


def _ranked(hypotheses: list[Hypothesis]) -> list[Hypothesis]:
    """Best score first, then fewer free DOF, then lower pose cost (ties up to rounding by :func:`_tiebreak`)."""
    return sorted_with_ties(hypotheses, first=lambda h: (-h.score, h.pose.free_dof), cost=lambda h: h.pose.cost,
                            tiebreak=_tiebreak)


def _diverse(ranked: list[Hypothesis], order: list[int], n: int) -> list[Hypothesis]:
    """At most ``n`` of the ``ranked`` hypotheses: the best half by score, then the best one that matches each
    item (items in search ``order``: fewest candidates first), then the rest by score.

    The score counts matched pixels, not how telling the matches are: a new cabinet whose three faces fit
    some cabinet of the model outscores the one tank that fits a single element, and with enough such
    coincidences the right interpretation falls out of a list cut by score. Verification, not the score,
    decides; it must be shown, for every item, the best interpretation that explains it.
    """
    chosen = ranked[: n // 2]
    taken = {id(h) for h in chosen}
    for i in order:
        if len(chosen) >= n:
            break
        h = next((h for h in ranked if id(h) not in taken and any(k == i and e >= 0 for k, e in h.pairs)), None)
        if h is not None:
            chosen.append(h)
            taken.add(id(h))
    chosen += [h for h in ranked if id(h) not in taken][: n - len(chosen)]
    return chosen


def _same_pose(a: np.ndarray, b: np.ndarray, angle_rad: float, dist_m: float) -> bool:
    dR = a[:3, :3].T @ b[:3, :3]
    ang = math.acos(np.clip((np.trace(dR) - 1) / 2, -1, 1))
    return ang < angle_rad and float(np.linalg.norm(a[:3, 3] - b[:3, 3])) < dist_m


def _length_m(params: MatchParams, items) -> float:
    """``params.length_m``, or the items' median range when it is "auto"."""
    return float(np.median([it.range_m for it in items])) if params.length_m == AUTO else float(params.length_m)


def match(description: SceneDescription, model: SceneModel | ModelElements, pixel_pitch_rad: float,
          params: MatchParams = MatchParams(), prior: np.ndarray | None = None) -> MatchResult:
    """Interpretation-tree search (module docstring).

    Parameters
    ----------
    description : the scene description (patches in the sensor frame).
    model : the a priori model, or its :func:`model_elements` (precomputed once per model).
    pixel_pitch_rad : the sensor's angular pixel size (for patch areas).
    params : tolerances and limits.
    prior : optional ``T_world_sensor`` (4, 4) prior restricting the candidates (with
        ``params.prior_angle_rad`` and ``params.prior_dist_m``).

    Returns
    -------
    MatchResult with its hypotheses sorted by score (then fewer free DOF, then lower pose cost).
    """
    el = model if isinstance(model, ModelElements) else model_elements(model)
    items = scene_items(description, pixel_pitch_rad, params)
    matchable = frozenset(it.patch_index for it in items)
    cands = [unary_candidates(it, el, params, prior) for it in items]
    keep = [k for k in range(len(items)) if len(cands[k])]
    items = [items[k] for k in keep]
    cands = [cands[k] for k in keep]
    if not items:
        return MatchResult((), tuple(items), el, 0, True, (), matchable=matchable)
    length_m = _length_m(params, items)
    s = _Search(items, el, cands, params, length_m)
    s.run()
    leaves = _ranked(s.finish(params.max_hypotheses))
    uniq: list[Hypothesis] = []
    for h in leaves:
        T = h.pose.T_world_sensor
        if any(_same_pose(T, u.pose.T_world_sensor, math.radians(params.same_pose_angle_deg),
                          params.same_pose_rel * length_m) for u in uniq):
            continue
        uniq.append(h)
    uniq = _ranked(_diverse(uniq, s.order, params.max_hypotheses))
    return MatchResult(tuple(uniq), tuple(items), el, s.n_nodes, not s.stop_reason,
                       tuple(len(c) for c in cands), s.stop_reason, matchable)


def given_match(description: SceneDescription, model: SceneModel | ModelElements, pixel_pitch_rad: float,
                pairings: dict[int, tuple[str, str]], params: MatchParams = MatchParams()) -> MatchResult:
    """The match result of given correspondences (``{patch id: (feature id, part)}``) instead of a search:
    one hypothesis whose pose is computed from them in closed form. Used to isolate the pose stage from
    matching (the harness's ``pairing`` oracle); patches not in ``pairings`` are wildcards."""
    el = model if isinstance(model, ModelElements) else model_elements(model)
    items = tuple(scene_items(description, pixel_pitch_rad, params))
    index = {(str(f), str(p)): e for e, (f, p) in enumerate(zip(el.feature_id, el.part, strict=True))}
    pairs_idx = []
    for i, it in enumerate(items):
        e = index.get(pairings.get(it.patch_id, ("", "")), -1)
        if e >= 0 and el.kind[e] != it.kind:
            e = -1  # a pairing the item's kind cannot express (e.g. a patch labelled CYL on a plane)
        pairs_idx.append((i, e))
    pairs = [make_pair(items[i], el, e) for i, e in pairs_idx if e >= 0]
    hyps: tuple[Hypothesis, ...] = ()
    if pairs:
        pose = estimate_pose(pairs, length_m=_length_m(params, items), max_sigma=params.max_free_sigma)
        if pose.ok:
            score = float(sum(items[i].weight for i, e in pairs_idx if e >= 0))
            hyps = (Hypothesis(tuple(pairs_idx), pose, score, len(pairs)),)
    return MatchResult(hyps, items, el, 0, True, matchable=frozenset(it.patch_index for it in items))
