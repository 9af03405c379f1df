"""Localisation in one call, :func:`localise`: matching, pose, verification and ICP refinement (the paper's
section 4).

``localise(description, scan, model)`` estimates ``T_world_sensor`` from a scene description and the a
priori model only (plus ``scan.pose_prior`` when the suite gives one, DESIGN 10.1):

1. interpretation-tree matching of PLAN/CYL/CONE/SPH patches to model elements (:mod:`.matching`,
   :mod:`.interpretation_tree`), each hypothesis with a closed-form, refined pose (:mod:`.pose`);
2. verification: every hypothesis is screened by its agreement with the model's predicted range image on a
   coarse grid of the sensor's own rays (:mod:`.prediction`, :mod:`.verification`, a few ms each), the best
   few verified on a finer grid, with an allowance for a closed-form pose's error (``pre_icp_rel``);
3. the best few are refined by a quick ICP (:mod:`.icp`) and verified again: the agreement after
   ICP decides (this is what settles the 90/180 deg alternatives of symmetric walls and bays); another
   distinct pose agreeing within ``ambiguity_margin`` makes the result ambiguous (not ok). The winner gets
   the full ICP against the model surfaces predicted visible from it. ICP never uses the points of the
   matchable patches its hypothesis leaves unmatched (:func:`_explained`): they are changes;
4. the prediction at the final pose (full resolution), returned for change detection (DESIGN 10.11), and
   the final confidence (agreement at the final pose). OTH patches and the patches left to wildcards are
   then paired by overlap with the prediction (the paper's second, looser stage).

The result says why when it fails (``ok=False`` and ``reason``): no hypothesis, low confidence, pose left
underconstrained, ambiguous, search budget reached. Nothing here sees the truth.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.special import ndtr

from recognition.describe import SceneDescription
from recognition.tuning import tuned
from scenes.model import SceneModel
from sensors.range_image import Scan

from .icp import STABLE_KINDS, IcpParams, icp_fixed_directions, icp_refine
from .interpretation_tree import given_match, match
from .matching import MatchParams, make_pair, model_elements
from .pose import estimate_pose
from .precision import flattest_probe, separation_z
from .prediction import Prediction, predict
from .twins import twin_poses
from .verification import VerifyParams, agreement, soft_agreement

__all__ = ["LocaliseParams", "PoseAlternative", "PoseResult", "agreement_separation", "localise", "overlap_pairings"]


@dataclass(frozen=True)
class LocaliseParams:
    """Parameters of :func:`localise`.

    Attributes
    ----------
    match : interpretation-tree parameters.
    verify : verification parameters.
    icp : ICP parameters.
    max_screen, screen_stride : at most this many hypotheses (best tree score first) are screened by their
        agreement on a prediction at this pixel stride ...
    max_verify : ... and the best this many verified at ``verify.stride``.
    icp_screen : the quick ICP of the finalists (``icp`` is the winner's full ICP).
    max_icp : the best this many verified hypotheses (agreement at least ``icp_fraction`` of the best) are
        refined by the quick ICP and verified again; the agreement after it decides.
    accept_agreement, accept_margin : a first finalist agreeing at least ``accept_agreement`` after ICP,
        and ahead of a remaining finalist's (pre-ICP) agreement by ``accept_margin``, ends the refinement.
    ambiguity_margin : another distinct pose (not the same within ``match.same_pose_angle_deg`` and
        ``match.same_pose_rel``) agreeing within this margin of the best after ICP makes the result ambiguous
        (not ok: a symmetric scene the data cannot decide).
    pre_icp_rel : the agreement threshold's fraction of the range before ICP (screening and verification of
        closed-form poses; after ICP ``verify.rel`` applies).
    min_confidence : below this final agreement the result is not ok (set on the first phase's default
        suites, now ``classic``: right poses agreed 0.50-1.0, wrong ones up to 0.43).
    use_icp : run ICP (always, to tighten the pose; it also fixes the DOF the pairs leave free).
    prior_angle_deg, prior_dist_m : how far the true pose may be from ``scan.pose_prior`` (its noise);
        candidates are restricted accordingly. Ignored without a prior.
    second_stage_fraction : a patch left out of the tree is paired with the model feature that the
        prediction shows on at least this fraction of its agreeing pixels.
    slide_steps : without a pose prior and without a fully constrained hypothesis, each of the first
        ``max_verify`` hypotheses (best tree score first) whose pairs leave one translation free (a floor, a
        wall and pipes along that wall) is slid along it: the
        sensor positions within the model's extent along the free direction, in this many steps, then a
        quarter step around the best, each scored by its agreement on a coarse prediction (pixel stride
        ``slide_stride``, about 1 ms each on VGA); the best starts the verification and ICP (which cannot
        converge from metres away). 0: no slide (a count of places).
    max_twins, max_twin_candidates : the poses the model's repeated structure makes look like the winner
        (:mod:`.twins`: a twin of a matched feature where the winner puts that feature) and the other
        interpretations of the winner's patches, at most ``max_twin_candidates`` screened on a coarse prediction,
        the best ``max_twins`` refined by the quick ICP and verified as alternatives. 0: none.
    max_reinterpretations : the other interpretations of the patches the winner matched (the tree run again on
        them alone, no wildcard), at most this many hypotheses; their fully constrained poses join the twins.
        0: none.
    pin_angle_deg, pin_rel : the probes of the precision check (:mod:`.precision`): the final pose turned by
        this angle about each world axis through the sensor and moved by this fraction of the median measured
        range along each world axis - the evaluation's success tolerance, which an ok pose claims to meet.
    pin_z : an ok pose must be separated from every probe by at least this (``d / se`` of
        :func:`agreement_separation`): otherwise the data do not fix it within the tolerance (``not pinned``).
    separation_z : ... and from every materially different alternative by at least this (``ambiguous``).
    separation_leave_out : the separation from an alternative leaves out this many patches that favour the
        winner most (:func:`agreement_separation`): a preference one patch carries may be a change.
    max_free_without_one : an ok pose leaves at most this many DOF free when the ICP's correspondences on any one
        movable model object (kinds other than :data:`.icp.STABLE_KINDS`) are left out: in a partially correct
        model any one of them may have moved, and a pose that rests on it alone is as wrong as it. A move is
        seen against the rest of the view in the directions the rest fixes, and goes unseen in the others:
        there, the pose with the object moved explains the data exactly as well. 6: no such check.
    rest_within_tolerance : without one movable object, a direction also counts as free when the rest fixes it
        no better than the success tolerance an ok pose claims (``pin_angle_deg``, ``pin_rel``), not only
        beyond 0.1 rad or 0.1 median ranges (:func:`.icp.icp_refine`'s ``tolerance``); such a pose is
        conditional on the object (it stays usable for change detection: only ``max_free_without_one``'s count
        decides that, as before).
    conditional_max_free : a pose that passes every other check but rests on one object is not ok but
        *conditional* on it (``PoseResult.conditional_on``) while the rest of the view leaves at most this many
        DOF free without it: usable for change detection, which then judges the rest of the view against it.
        Beyond it, the pose is not used at all.
    disagree_fraction : the patches of which fewer than this fraction of pixels agree with the final pose are
        registered on their own (:func:`_disagreeing_alternative`): the pose they ask for is an alternative that
        the final pose must be separated from. 0: no such alternative.
    disagree_reach : ... by an ICP whose first correspondences reach this fraction of the median range (the held
        poses are a few percent of the range off, beyond the final ICP's first reach, ``icp.max_corr_rel``).
    stable_reach : the same reach for those of them that see a floor or a wall, registered moving the pose only
        in the directions they fix, then by the final ICP on the whole view (:func:`_stable_alternative`).
    object_share : a patch sees an object when the model predicts it over at least this share of the patch's
        pixels; the separation from the stable alternative leaves out the patches of the one movable object (or
        lone patch) that most favours each side.

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    match: MatchParams = tuned(default_factory=lambda: MatchParams(max_hypotheses=20), unit="-",
                               chosen="20 hypotheses for the verification to screen (af4da75), else MatchParams'")
    verify: VerifyParams = tuned(default_factory=VerifyParams, unit="-", chosen="VerifyParams' own defaults")
    icp: IcpParams = tuned(default_factory=IcpParams, unit="-", chosen="IcpParams' own defaults")
    max_screen: int = tuned(20, unit="count", chosen="the first phase's default (now classic): verifying 100 let an "
                            "89 deg pose pass the confidence bar at 0.56 (docs/notebook.md)")
    screen_stride: int = tuned(8, unit="px", chosen="not tuned: a speed setting, set in af4da75")
    max_verify: int = tuned(6, unit="count", chosen="not tuned: set in c9baa1a")
    icp_screen: IcpParams = tuned(
        default_factory=lambda: IcpParams(max_source_points=1500, n_passes=2, max_iterations=10), unit="-",
        chosen="not tuned: a quick ICP for the finalists, set in af4da75")
    max_icp: int = tuned(4, unit="count", chosen="not tuned: set in af4da75")
    icp_fraction: float = tuned(0.5, unit="fraction", chosen="not tuned: set in af4da75")
    accept_agreement: float = tuned(0.6, unit="agreement", chosen="not tuned: set in af4da75")
    accept_margin: float = tuned(0.15, unit="agreement", chosen="not tuned: set in af4da75")
    ambiguity_margin: float = tuned(0.05, unit="agreement", chosen="not tuned: set in af4da75")
    pre_icp_rel: float = tuned(0.012, unit="fraction of range", chosen="not tuned: set in af4da75")
    min_confidence: float = tuned(
        0.45, unit="agreement", chosen="the first phase's default suites (now classic): right poses agreed "
        "0.50-1.0, wrong ones up to 0.43 (af4da75); not re-checked on calibration")
    use_icp: bool = tuned(True, unit="-", chosen="on since c9baa1a (it also fixes the DOF the pairs leave free)")
    prior_angle_deg: float = tuned(5.0, unit="deg", chosen="not tuned: set in c9baa1a")
    prior_dist_m: float = tuned(0.3, unit="m", chosen="not tuned: set in c9baa1a")
    second_stage_fraction: float = tuned(0.5, unit="fraction", chosen="not tuned: set in c9baa1a")
    slide_steps: int = tuned(
        32, unit="count", chosen="set with the slide in 72aa03b (Kinect-like constrained pose success 4 -> 5 of 9 on "
        "the first phase's default, now classic); the count not varied")
    slide_stride: int = tuned(
        16, unit="px", chosen="the first phase's default (now classic): the same peak as stride 8 on the Kinect-like "
        "trial, matching median 0.37 -> 0.22 s (740502b)")

    max_twins: int = tuned(2, unit="count", chosen="not tuned: a speed bound (each costs a quick ICP)")
    max_reinterpretations: int = tuned(
        128, unit="count", chosen="not tuned: a speed bound on the search of the winner's patches alone (the corner "
        "of calibration's factory-s2005-p10-v0-factory_scanner-n0, ok at 90 deg off, needs one)")
    max_twin_candidates: int = tuned(
        160, unit="count", chosen="not tuned: a speed bound on the coarse screening (64 before the reinterpretations "
        "joined the twins)")
    pin_angle_deg: float = tuned(
        1.0, unit="deg", chosen="the evaluation's success tolerance (DESIGN 10.6): an ok pose claims to be within it")
    pin_rel: float = tuned(
        0.01, unit="fraction of the median range", chosen="the evaluation's success tolerance (DESIGN 10.6)")
    pin_z: float = tuned(
        1.0, unit="separation (d / se)", chosen="not tuned: one standard error; checked on calibration (an in-process "
        "collection of 93 trials at 9dc872f's parent): ok-but-wrong poses 6 -> 2 with separation_z")
    separation_z: float = tuned(
        1.0, unit="separation (d / se)", chosen="not tuned: one standard error; checked on calibration with pin_z")
    separation_leave_out: int = tuned(
        1, unit="patches", chosen="not tuned: one patch, so that one changed object cannot carry the verdict alone; "
        "checked on calibration with the tie rule (c8864fb, same draws): ok-but-wrong poses 4 -> 3, constrained pose "
        "success 0.892 -> 0.919")
    max_free_without_one: int = tuned(
        0, unit="DOF", chosen="issue 34's rule (a pose is trustworthy only if no materially different pose explains "
        "the data nearly as well; one object moved along a direction only it fixes does): checked on calibration "
        "at 6ad664a, ok but wrong 1 -> 0 (a Kinect-like pose 180 deg off resting on one pipe run), 11 right poses "
        "conditional instead of ok (10 Kinect-like); 3 before (445e44a), when not ok also meant no change detection")
    rest_within_tolerance: bool = tuned(
        True, unit="-", chosen="issue 34's rule with its own measure of 'materially different' (the success tolerance "
        "an ok pose claims): calibration, 1 right pose of 41 ok conditional instead (a mock-up pose resting on one "
        "pipe), ok but wrong 0 -> 0, change macro-F1 the same; 72 trials on scenes no suite holds (seeds "
        "7000-7111): ok but wrong 1 -> 0 (a Kinect-like pose 5.3 deg and 298 mm off at confidence 0.91 on a moved "
        "pipe run that the rest of its view fixed to about 5 deg)")
    conditional_max_free: int = tuned(
        3, unit="DOF", chosen="max_free_without_one's value before the conditional verdict (calibration at 445e44a: "
        "the wrong poses that rested on one object left 6, 6 and 1 DOF free without it, the right ones 1-3): the "
        "poses change detection used then, it uses now (calibration at 6ad664a: 6 instead gave change macro-F1 "
        "0.906 -> 0.886 with 3 more poses, all wrong)")
    disagree_fraction: float = tuned(
        0.5, unit="fraction", chosen="not tuned: a patch mostly unexplained by the pose (under half its pixels agree)")
    disagree_reach: float = tuned(
        0.1, unit="fraction of range", chosen="not tuned: five times the materially different distance (2 %)")
    stable_reach: float = tuned(
        0.2, unit="fraction of range", chosen="set, not swept: ten times the materially different distance (2 %); "
        "0.1 missed a wall 0.25 m off at a scale of 1.4 m (factory-s3003-p20-v1 of full's factory group)")
    object_share: float = tuned(0.3, unit="fraction", chosen="set, not swept: the overlap_share of change "
                                "detection")

    def __post_init__(self):
        if not 0 < self.object_share <= 1:
            raise ValueError(f"object_share must be in (0, 1], got {self.object_share}")
        if not self.stable_reach > 0:
            raise ValueError(f"stable_reach must be > 0, got {self.stable_reach}")
        if not 0 <= self.disagree_fraction <= 1 or self.disagree_reach <= 0:
            raise ValueError(f"disagree_fraction must be in [0, 1] and disagree_reach > 0, got "
                             f"{self.disagree_fraction}, {self.disagree_reach}")
        if self.max_twins < 0 or self.max_twin_candidates < 0 or self.max_reinterpretations < 0:
            raise ValueError(f"max_twins, max_twin_candidates and max_reinterpretations must be >= 0, got "
                             f"{self.max_twins}, {self.max_twin_candidates}, {self.max_reinterpretations}")
        if self.pin_angle_deg <= 0 or self.pin_rel <= 0:
            raise ValueError(f"pin_angle_deg and pin_rel must be > 0, got {self.pin_angle_deg}, {self.pin_rel}")
        if not 0 <= self.max_free_without_one <= 6 or not 0 <= self.conditional_max_free <= 6:
            raise ValueError(f"max_free_without_one and conditional_max_free must be in 0..6, got "
                             f"{self.max_free_without_one}, {self.conditional_max_free}")
        if self.separation_leave_out < 0:
            raise ValueError(f"separation_leave_out must be >= 0, got {self.separation_leave_out}")
        if self.max_verify < 1:
            raise ValueError(f"max_verify must be >= 1, got {self.max_verify}")
        if not 0 <= self.min_confidence <= 1:
            raise ValueError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if self.prior_angle_deg <= 0 or self.prior_dist_m <= 0:
            raise ValueError("prior_angle_deg and prior_dist_m must be > 0")
        if not 0 < self.second_stage_fraction <= 1:
            raise ValueError(f"second_stage_fraction must be in (0, 1], got {self.second_stage_fraction}")
        if self.slide_steps < 0 or self.slide_stride < 1:
            raise ValueError(f"slide_steps must be >= 0 and slide_stride >= 1, got {self.slide_steps}, "
                             f"{self.slide_stride}")


@dataclass(frozen=True)
class PoseAlternative:
    """A pose materially different from the winner's (not the same within ``match.same_pose_angle_deg`` and
    ``match.same_pose_rel``) and how well the data separate the winner from it.

    Attributes
    ----------
    T_world_sensor : ndarray of shape (4, 4), the alternative pose (after its quick ICP when it had one).
    agreement : float in [0, 1], its agreement with the data (:func:`recognition.localisation.agreement`).
    separation : the winner's agreement minus this one's over the standard error of that difference
        (:func:`agreement_separation`, :func:`.precision.separation_z`).
    """

    T_world_sensor: np.ndarray
    agreement: float
    separation: float


@dataclass(frozen=True)
class PoseResult:
    """Result of :func:`localise`.

    Attributes
    ----------
    ok : bool; reason : why not ok ("" when ok).
    conditional_on : the movable model object the pose rests on alone (``LocaliseParams.max_free_without_one``)
        when it passed every other check and the rest of the view fixes enough (``conditional_max_free``): not
        ok, since that object may have moved, but the pose to use if it did not ("" otherwise; then ``usable``
        is ``ok``).
    T_world_sensor : ndarray of shape (4, 4) or None, the final pose (after ICP).
    T_world_sensor_initial : ndarray of shape (4, 4) or None, closed form + weighted refinement (before ICP).
    cov_T_world_sensor : ndarray of shape (6, 6) or None, over (rotation vector rad, translation m), left
        perturbation in the world frame (ICP's when it ran, else the pairs').
    free_dof : int, degrees of freedom left unconstrained (0 when fully constrained).
    confidence : float in [0, 1], the probability the core gives its pose: ``Phi(z)`` of the least separation
        ``z`` of the final pose from a probe at the success tolerance and from a materially different
        alternative (:func:`agreement_separation`).
    pairings : tuple of (patch id, model feature id or None = wildcard).
    n_hypotheses : int, hypotheses from the tree; n_nodes : int, nodes it visited.
    predicted : :class:`recognition.localisation.Prediction` at the final pose (full resolution) or None.
    timing_s : dict, seconds per stage (matching, pose, verification, icp, predict).
    agreement : float in [0, 1] or None, agreement of the data with the model predicted at the final pose.
    alternatives : tuple of :class:`PoseAlternative`, the best of each other distinct pose the verification
        refined, best first (empty when only one was).
    """

    ok: bool
    reason: str
    T_world_sensor: np.ndarray | None
    T_world_sensor_initial: np.ndarray | None
    cov_T_world_sensor: np.ndarray | None
    free_dof: int
    confidence: float
    pairings: tuple[tuple[int, str | None], ...]
    n_hypotheses: int
    n_nodes: int
    predicted: object | None
    timing_s: dict[str, float]
    alternatives: tuple[PoseAlternative, ...] = ()
    agreement: float | None = None
    conditional_on: str = ""

    @property
    def usable(self) -> bool:
        """Whether the pose is one to run change detection against: ok, or conditional on one object."""
        return self.T_world_sensor is not None and (self.ok or bool(self.conditional_on))


def _check_T(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"expected {name} of shape (4, 4), got {T.shape}")
    return T


def overlap_pairings(description: SceneDescription, prediction: Prediction, exclude: set[int],
                     min_fraction: float, params: VerifyParams, scan: Scan) -> dict[int, str]:
    """Second stage: pair patches (not in ``exclude``) with the model feature the prediction shows on most
    of their agreeing pixels (at least ``min_fraction`` of the patch's pixels on the prediction's grid)."""
    s, o = prediction.stride, prediction.offset
    h, w = prediction.range.shape
    labels = description.labels[o::s, o::s][:h, :w]
    meas = scan.range[o::s, o::s][:h, :w]
    sig = description.sigma[o::s, o::s][:h, :w]
    thr = params.k_sigma * np.nan_to_num(sig, nan=0.0) + params.abs_m + params.rel * np.nan_to_num(meas, nan=0.0)
    with np.errstate(invalid="ignore"):
        good = (np.abs(meas - prediction.range) <= thr) & (prediction.surface_id >= 0)
    fid_of_surface = np.array([sf.feature_id for sf in prediction.surfaces], dtype=object)
    out: dict[int, str] = {}
    lab = labels.ravel()
    gd = good.ravel()
    sid = prediction.surface_id.ravel()
    for p in description.patches:
        if p.id in exclude or p.n_pixels < params.min_pixels:
            continue
        on = lab == p.id
        n_on = int(on.sum())
        if n_on == 0:
            continue
        hit = sid[on & gd]
        if len(hit) == 0:
            continue
        fids = fid_of_surface[hit]
        vals, counts = np.unique(fids.astype(str), return_counts=True)
        k = int(np.argmax(counts))
        if counts[k] >= min_fraction * n_on:
            out[p.id] = str(vals[k])
    return out


def _explained(description: SceneDescription, matchable: frozenset[int], items, h) -> np.ndarray:
    """Bool (H, W): the pixels ICP may use under hypothesis ``h`` - all but those of the ``matchable`` patches
    (indices of patches with a primitive fit that the tree could match) that ``h`` leaves unmatched. Such a
    patch contradicts the model where it is (a new cabinet, a sphere of another radius): it is a change, and
    its points would pull the pose towards the nearest model surface."""
    unmatched = matchable - {items[i].patch_index for i, e in h.pairs if e >= 0}
    return ~_pixels_of(description, [description.patches[k] for k in unmatched])


def _pixels_of(description: SceneDescription, patches) -> np.ndarray:
    """Bool (H, W): the pixels of ``patches`` (scene patches of ``description``)."""
    mask = np.zeros(description.labels.shape, dtype=bool)
    flat = mask.reshape(-1)
    for p in patches:
        flat[p.pixels] = True
    return mask


def _pose_scale(description: SceneDescription) -> float:
    """The scene's median range (m): the median distance of the patches' centroids from the sensor (1 without
    patches), the length that ``same_pose_rel`` and ``pin_rel`` are fractions of in :func:`_close`."""
    rng = [float(np.linalg.norm(np.mean(p.points, axis=0))) for p in description.patches if len(p.points)]
    return float(np.median(rng)) if rng else 1.0


def _close(A: np.ndarray, B: np.ndarray, scale: float, angle_deg: float, rel: float) -> bool:
    """Whether two poses are the same up to ``angle_deg`` and ``rel`` x ``scale`` (:func:`_pose_scale`)."""
    c = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    return bool(c > math.cos(math.radians(angle_deg)) and np.linalg.norm(A[:3, 3] - B[:3, 3]) < rel * scale)


def agreement_separation(description: SceneDescription, fractions_a: dict[int, float],
                         fractions_b: dict[int, float], leave_out: int = 0, leave_out_b: int = 0,
                         objects: dict[int, frozenset[str]] | None = None) -> tuple[float, float]:
    """How far the data prefer pose A to pose B: ``(d, se)``, the difference of their agreements over the
    patches both score and its standard error, after leaving out the ``leave_out`` patches that favour A most
    (and the ``leave_out_b`` that favour B most).

    ``d`` is the ``log(pixels)``-weighted mean of the per-patch differences ``f_A - f_B`` (the weights of
    :func:`recognition.localisation.agreement`); the patches are the independent units (neighbouring pixels of
    one patch share its pose error and its surface, so they are not), and ``se`` is the weighted mean's
    standard error over them, ``sqrt(n / (n - 1) sum w² (δ - d)²) / sum w``. With fewer than two shared
    patches nothing measures the spread: ``se = inf``.

    Parameters
    ----------
    description : the scene description (patch sizes).
    fractions_a, fractions_b : ``{patch id: fraction of agreeing pixels}`` of the two poses.
    leave_out : how many of the patches with the largest ``f_A - f_B`` are left out (ties: the larger, then the
        lower patch id first); leaving out such a patch never raises ``d``. A preference that one patch carries
        may be a change, not the pose: an altered pipe that the wrong pose fits, a moved cabinet where the wrong
        pose puts its twin.
    leave_out_b : the same for the patches with the smallest ``f_A - f_B`` (ties: the larger, then the lower patch
        id first); leaving out such a patch never lowers ``d``. For an alternative built from the patches that
        favour it (:func:`_disagreeing_alternative`).
    objects : ``{patch id: the movable model objects the patch sees}`` (:func:`_patch_objects`); with it, the
        patches that favour A of the one unit - a movable object, or a patch that sees none - whose favour to A
        is the largest (``log(pixels)``-weighted) are left out too, and so for B. A moved object carries all of
        its patches and those it hid at its old place, not one.
    """
    size = {p.id: p.n_pixels for p in description.patches}
    common = sorted(set(fractions_a) & set(fractions_b))
    if leave_out > 0 and common:
        favour = sorted(common, key=lambda k: (-(fractions_a[k] - fractions_b[k]), -size[k], k))
        common = sorted(favour[leave_out:])
    if leave_out_b > 0 and common:
        favour_b = sorted(common, key=lambda k: (fractions_a[k] - fractions_b[k], -size[k], k))
        common = sorted(favour_b[leave_out_b:])
    if objects:  # and the patches of the one movable object (or lone patch) that most favours each side
        for sign in (1.0, -1.0):
            common = _without_object(common, objects, {k: sign * (fractions_a[k] - fractions_b[k]) for k in common},
                                     size)
    if len(common) < 2:
        return 0.0, math.inf
    w = np.array([math.log(size[k]) for k in common])
    delta = np.array([fractions_a[k] - fractions_b[k] for k in common])
    d = float(w @ delta / w.sum())
    n = len(common)
    se = float(math.sqrt(n / (n - 1) * float(np.sum(w**2 * (delta - d) ** 2))) / w.sum())
    return d, se


def _without_object(common: list[int], objects: dict[int, frozenset[str]], favour: dict[int, float],
                    size: dict[int, int]) -> list[int]:
    """``common`` without the patches favouring a side (``favour`` > 0) of the one unit whose weighted favour to
    that side is the largest: a movable object (``objects``: all the patches that see it) or a patch that sees
    none (ties: objects by name, then lone patches by id)."""
    total: dict[str, float] = {}
    for k in common:
        if favour[k] > 0:
            for unit in objects.get(k) or (f"#{k:09d}",):
                total[unit] = total.get(unit, 0.0) + math.log(size[k]) * favour[k]
    if not total:
        return common
    top = min(total, key=lambda u: (-total[u], u))
    return [k for k in common if not (favour[k] > 0 and top in (objects.get(k) or (f"#{k:09d}",)))]


def _patch_objects(description: SceneDescription, model: SceneModel, pred: Prediction,
                   share: float) -> dict[int, frozenset[str]]:
    """The model objects each patch sees from ``pred``'s pose: those the model predicts over at least ``share``
    of the patch's pixels (on the prediction's grid) - the object at the patch's place, or in front of it."""
    s, o = pred.stride, pred.offset
    h, w = pred.range.shape
    lab = description.labels[o::s, o::s][:h, :w].ravel()
    names = sorted({model.object_of(sf.feature_id) for sf in pred.surfaces})
    index = {n: i for i, n in enumerate(names)}
    obj = np.array([index[model.object_of(sf.feature_id)] for sf in pred.surfaces] + [-1])[pred.surface_id.ravel()]
    sel = (lab >= 0) & (obj >= 0)
    if not sel.any():
        return {}
    total = np.bincount(lab[lab >= 0])
    pairs, counts = np.unique(np.stack([lab[sel], obj[sel]]), axis=1, return_counts=True)
    out: dict[int, set[str]] = {}
    for (k, i), c in zip(pairs.T.tolist(), counts.tolist(), strict=True):
        if c >= share * total[k]:
            out.setdefault(k, set()).add(names[i])
    return {k: frozenset(v) for k, v in out.items()}


def _movable(model: SceneModel, objects: frozenset[str]) -> frozenset[str]:
    """The movable ones (kinds other than :data:`.icp.STABLE_KINDS`) of model ``objects``."""
    return frozenset(o for o in objects if model.object(o).kind not in STABLE_KINDS)


def free_translation(free_dof: int, free_basis: np.ndarray) -> np.ndarray | None:
    """The unit world direction (3,) of a pose's one free DOF when it is a pure translation, else None.

    ``free_basis`` (6, free_dof) over (rotation vector, translation), as in
    :class:`recognition.localisation.PoseEstimate`."""
    if free_dof != 1:
        return None
    b = np.asarray(free_basis, float)[:, 0]
    t = float(np.linalg.norm(b[3:]))
    if t < 0.5 or np.linalg.norm(b[:3]) > 1e-6 * max(t, 1.0):
        return None
    return b[3:] / t


def slide_along(T: np.ndarray, direction: np.ndarray, points: np.ndarray, score, steps: int) -> np.ndarray:
    """``T`` (4, 4) translated along the unit world ``direction`` to the best-scoring place.

    The sensor is kept within the extent of ``points`` (N, 3, world) along ``direction``: ``steps`` evenly
    spaced places there, then nine at a quarter step around the best; ``score(T)`` -> float (higher is
    better); ties keep the earliest (the unslid pose is tried first).
    """
    pos = float(T[:3, 3] @ direction)
    proj = points @ direction
    lo, hi = float(proj.min()) - pos, float(proj.max()) - pos
    step = (hi - lo) / max(steps, 1)

    def moved(s: float) -> np.ndarray:
        out = T.copy()
        out[:3, 3] = T[:3, 3] + s * direction
        return out

    best_s, best = 0.0, score(T)

    def visit(places: np.ndarray) -> None:
        nonlocal best_s, best
        for s in places:
            if s == best_s:
                continue
            v = score(moved(float(s)))
            if v > best:
                best_s, best = float(s), v

    visit(np.linspace(lo, hi, steps + 1))
    visit(best_s + np.linspace(-step, step, 9))  # about the best coarse place
    return moved(best_s)


PROBE_NAMES = tuple([f"turned {d} about {a}" for a in "xyz" for d in ("-", "+")]
                    + [f"moved {d} along {a}" for a in "xyz" for d in ("-", "+")])


def _twin_outcomes(description, scan, model, model_simulator, el, best, T_best, best_agreement,
                   screen_v: VerifyParams, params: LocaliseParams, timing: dict[str, float], scale: float,
                   others: list[np.ndarray] = ()) -> list[tuple]:
    """The poses the model's repeated structure makes look like ``T_best`` (:func:`.twins.twin_poses` of the
    features ``best`` pairs, then ``others``: the :func:`_reinterpretations`), screened on a coarse prediction;
    the best ``max_twins`` of them (agreeing at least ``icp_fraction`` of the winner) refined by the quick ICP
    and verified, as outcome tuples ``(agreement, None, T_initial, T_refined, prediction, fractions)`` sorted
    best first. They can only be alternatives: without a hypothesis of their own they have no pairs to stand
    on. ``scale``: :func:`_pose_scale` of ``description``."""
    if params.max_twins == 0:
        return []
    t0 = time.perf_counter()
    matched = {str(el.feature_id[e]) for _, e in best.pairs if e >= 0}
    same = (params.match.same_pose_angle_deg, params.match.same_pose_rel)
    kept: list[np.ndarray] = []
    for T in [*twin_poses(T_best, matched, model), *others]:
        if len(kept) >= params.max_twin_candidates:
            break
        if not any(_close(T, K, scale, *same) for K in [T_best, *kept]):
            kept.append(T)
    screened = sorted(((agreement(description, scan, predict(model_simulator, scan.sensor, T, screen_v.stride),
                                  screen_v)[0], k, T) for k, T in enumerate(kept)), key=lambda x: (-x[0], x[1]))
    timing["verification"] += time.perf_counter() - t0
    out = []
    for sc, _, T in screened[: params.max_twins]:
        if sc < params.icp_fraction * best_agreement:
            break
        pred = predict(model_simulator, scan.sensor, T, params.verify.stride)
        after, T_f, pred_f, frac = _quick_refine(description, scan, model, model_simulator, pred, None, params,
                                                 timing)
        out.append((after, None, T, T_f, pred_f, frac))
    return sorted(out, key=lambda x: -x[0])


def _reinterpretations(description: SceneDescription, res, best, el, pixel_pitch_rad: float,
                       params: LocaliseParams, timing: dict[str, float]) -> list[np.ndarray]:
    """The fully constrained poses of every interpretation of the patches the winner ``best`` matched: the
    interpretation tree run again on those patches alone, with no wildcard, at most ``max_reinterpretations``
    hypotheses (best tree score first); :func:`_twin_outcomes` leaves out the winner's own pose among them.
    Empty when there are no twins to screen them with (``max_twins`` 0).

    The main search spends its hypothesis budget on the interpretations of all the patches, so in a bay whose
    corners look alike (a floor and two walls seen away from their ends) the one that puts the sensor in the
    right corner may never be made; on the winner's own patches the search is small and complete. Nothing
    here prefers one corner to another: the verification does, or finds it cannot (``ambiguous``)."""
    if params.max_reinterpretations == 0 or params.max_twins == 0:
        return []
    t0 = time.perf_counter()
    used = {res.items[i].patch_index for i, e in best.pairs if e >= 0}
    sub = replace(description, patches=tuple(description.patches[k] for k in sorted(used)))
    mp = replace(params.match, max_wildcard_fraction=0.0, extra_wildcards=0,
                 max_hypotheses=params.max_reinterpretations)
    found = match(sub, el, pixel_pitch_rad, mp)
    out = [h.pose.T_world_sensor for h in found.hypotheses if h.pose.free_dof == 0]
    timing["matching"] += time.perf_counter() - t0
    return out


def _quick_refine(description, scan, model, model_simulator, pred: Prediction, mask: np.ndarray | None,
                  params: LocaliseParams, timing: dict[str, float]) -> tuple[float, np.ndarray, Prediction, dict]:
    """The quick ICP (``params.icp_screen``) of the pose of ``pred`` with the source pixels ``mask``, and the
    agreement after it: ``(agreement, T after, its prediction, per-patch fractions)`` (the pose of ``pred`` when
    ICP is off or fails)."""
    T_f, pred_f = pred.T_world_sensor, pred
    if params.use_icp:
        t0 = time.perf_counter()
        ir = icp_refine(scan, pred, model, pred.T_world_sensor, params.icp_screen, mask)
        timing["icp"] += time.perf_counter() - t0
        if ir.ok:
            t0 = time.perf_counter()
            T_f = ir.T_world_sensor
            pred_f = predict(model_simulator, scan.sensor, T_f, params.verify.stride)
            timing["verification"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    after, frac = agreement(description, scan, pred_f, params.verify)
    timing["verification"] += time.perf_counter() - t0
    return after, T_f, pred_f, frac


def _pinned(description: SceneDescription, scan: Scan, model_simulator, T: np.ndarray,
            params: LocaliseParams) -> tuple[float, int]:
    """The precision check (:func:`.precision.flattest_probe`) of ``T`` at the verification's stride: the least
    separation from a probe at the success tolerance, and which probe."""
    valid = scan.range[np.isfinite(scan.range)]
    step_m = params.pin_rel * (float(np.median(valid)) if len(valid) else 1.0)

    def score(T_p):
        return soft_agreement(description, scan, predict(model_simulator, scan.sensor, T_p, params.verify.stride),
                              params.verify)

    _, fractions = score(T)
    return flattest_probe(T, fractions, score, math.radians(params.pin_angle_deg), step_m,
                          lambda a, b: agreement_separation(description, a, b))


def _verified(description: SceneDescription, scan: Scan, model_simulator, T: np.ndarray, params: LocaliseParams,
              timing: dict[str, float]) -> tuple[Prediction, float, dict[int, float]]:
    """The model predicted from ``T`` on the verification's grid (``params.verify.stride``) and the data's
    :func:`agreement` with it (score, per-patch fractions); the time counts as verification."""
    t0 = time.perf_counter()
    pred = predict(model_simulator, scan.sensor, T, params.verify.stride)
    score, fractions = agreement(description, scan, pred, params.verify)
    timing["verification"] += time.perf_counter() - t0
    return pred, float(score), fractions


def _materially_different(A: np.ndarray, B: np.ndarray, scale: float, params: LocaliseParams) -> bool:
    """Whether two poses are farther apart than twice the success tolerance an ok pose claims (``pin_angle_deg``,
    ``pin_rel``; ``scale``: :func:`_pose_scale`), so that they cannot both be within it of the truth."""
    return not _close(A, B, scale, 2 * params.pin_angle_deg, 2 * params.pin_rel)


def _start_alternative(description: SceneDescription, scan: Scan, model_simulator, T_start: np.ndarray,
                       T_final: np.ndarray, f_final: dict[int, float], params: LocaliseParams,
                       timing: dict[str, float], scale: float) -> PoseAlternative | None:
    """The pose the winning hypothesis started from (its pairs' closed form, before ICP) as an alternative to
    the final pose, when ICP carried the pose materially away from it: beyond twice the success tolerance an ok
    pose claims (``pin_angle_deg``, ``pin_rel``), so that the two cannot both be within it of the truth; None
    otherwise. (At once the tolerance, a right final pose whose start was 12 mm off at 1 m, which the data
    preferred by a little, was called ambiguous: tests/harness/test_plugins.py's mock-up trial.)

    ICP follows the model surfaces nearest the points, and a change can hold them (a new object beside a model
    surface, a pipe of another radius): it can then leave the pose the pairs gave for one a few degrees off
    that the agreement, counting the changed parts too, prefers by a little. Only the data can say whether the
    move was for the better, so the final pose must be separated from its start like from any other
    alternative (``separation_z``). Both are scored on the verification's grid (``params.verify``; ``f_final``:
    the final pose's per-patch fractions, :func:`_verified`). ``scale``: :func:`_pose_scale` of ``description``."""
    if not _materially_different(T_start, T_final, scale, params):
        return None
    _, a_start, f_start = _verified(description, scan, model_simulator, T_start, params, timing)
    return PoseAlternative(T_start, a_start, separation_z(
        *agreement_separation(description, f_final, f_start, params.separation_leave_out)))


def _disagreeing_alternative(description: SceneDescription, scan: Scan, model: SceneModel, model_simulator,
                             final: tuple[Prediction, float, dict[int, float]], params: LocaliseParams,
                             timing: dict[str, float], scale: float) -> PoseAlternative | None:
    """The pose that the patches the final pose leaves unexplained ask for, as an alternative to it.

    In a partially correct model a pose can be held by a moved object: ICP then fits that object, and the
    unchanged surfaces around it are the ones left unexplained. The reverse reading of the same data is the
    pose that fits those surfaces, with the object moved. This registers the patches of which fewer than
    ``params.disagree_fraction`` of pixels agree with ``T_final`` (on the verification's grid) alone, by ICP from
    ``T_final`` against the model predicted there (first reach ``params.disagree_reach`` of the range); their
    pose is returned with its separation from the final pose, as :func:`_start_alternative` does, when it is
    materially different (beyond twice the success tolerance). When the disagreeing patches are the change (the
    final pose right), their pose misplaces the rest of the view and the data separate the two; when they are
    the unchanged rest, they do not. The alternative is built from the patches that favour it, so the separation
    leaves out as many of them as of those that favour the final pose (``separation_leave_out`` each way): one
    moved object carries neither side.
    None without such patches, when their ICP fails, or when their pose is the final one. ``final``: the final
    pose's :func:`_verified`.
    """
    pred, _, f_final = final
    T_final = pred.T_world_sensor
    by_id = {p.id: p for p in description.patches}
    asking = [by_id[k] for k, fr in sorted(f_final.items()) if fr < params.disagree_fraction and k in by_id]
    if not asking:
        return None
    t0 = time.perf_counter()
    ir = icp_refine(scan, pred, model, T_final, replace(params.icp, max_corr_rel=params.disagree_reach),
                    _pixels_of(description, asking))
    timing["icp"] += time.perf_counter() - t0
    if not ir.ok or not _materially_different(ir.T_world_sensor, T_final, scale, params):
        return None
    _, a_alt, f_alt = _verified(description, scan, model_simulator, ir.T_world_sensor, params, timing)
    return PoseAlternative(ir.T_world_sensor, a_alt, separation_z(*agreement_separation(
        description, f_final, f_alt, params.separation_leave_out, params.separation_leave_out)))


def _stable_alternative(description: SceneDescription, scan: Scan, model: SceneModel, model_simulator,
                        final: tuple[Prediction, float, dict[int, float]], params: LocaliseParams,
                        timing: dict[str, float], scale: float) -> PoseAlternative | None:
    """The pose that the stable structure the final pose leaves unexplained asks for, as an alternative to it.

    :func:`_disagreeing_alternative` for the disagreeing patches that see a floor or a wall (the model predicts
    one of :data:`.icp.STABLE_KINDS` over at least ``params.object_share`` of their pixels at the final pose)
    and no movable object (whose old place, moved away, would leave them unexplained at the right pose), which
    no perturbation moves: a wall left unexplained while a moved tank holds the pose. They are registered
    alone by ICP from ``T_final`` against the model predicted there (first reach ``params.stable_reach`` of the
    range), moving the pose only in the directions they fix (:func:`.icp.icp_fixed_directions`: a wall alone
    fixes three), then the whole view by the final ICP from there; that pose is returned with its separation
    from the final pose when it is materially different. When the wall is the change seen wrongly (the final
    pose right), the whole view brings the pose back or misplaces the rest and the data separate the two. One
    moved object carries neither side: the separation leaves out, on each side, the patches of the one movable
    object (all the patches that see it at either pose: its own, and those its old place hides) or the one lone
    patch that favours that side most.
    None without such patches, when their ICP fails, or when their pose is the final one. ``final``: the final
    pose's :func:`_verified`.
    """
    pred, _, f_final = final
    T_final = pred.T_world_sensor
    by_id = {p.id: p for p in description.patches}
    seen = _patch_objects(description, model, pred, params.object_share)
    asking = [by_id[k] for k, fr in sorted(f_final.items()) if fr < params.disagree_fraction and k in by_id
              and seen.get(k) and not _movable(model, seen[k])]
    if not asking:
        return None
    t0 = time.perf_counter()
    ir = icp_fixed_directions(scan, pred, model, T_final, _pixels_of(description, asking),
                              params.stable_reach * scale, params.icp)
    if ir.ok:  # then the whole view from there, as the final pose was refined: the rest follows if it can
        whole = icp_refine(scan, predict(model_simulator, scan.sensor, ir.T_world_sensor, params.verify.stride),
                           model, ir.T_world_sensor, params.icp)
        ir = whole if whole.ok else ir
    timing["icp"] += time.perf_counter() - t0
    if not ir.ok or not _materially_different(ir.T_world_sensor, T_final, scale, params):
        return None
    pred_alt, a_alt, f_alt = _verified(description, scan, model_simulator, ir.T_world_sensor, params, timing)
    seen_alt = _patch_objects(description, model, pred_alt, params.object_share)
    objects = {}  # the movable objects each patch sees at either pose
    for k in seen.keys() | seen_alt.keys():
        if movable := _movable(model, seen.get(k, frozenset()) | seen_alt.get(k, frozenset())):
            objects[k] = movable
    return PoseAlternative(ir.T_world_sensor, a_alt, separation_z(*agreement_separation(
        description, f_final, f_alt, objects=objects)))


def _confidence(z: float) -> float:
    """The confidence of a pose verdict from its least separation ``z`` (from a probe at the tolerance or an
    alternative): ``Phi(z)``, the probability that a difference measured ``z`` standard errors above 0 is
    above 0."""
    return float(ndtr(min(z, 8.0))) if not math.isnan(z) else 0.0


def _model_points(model: SceneModel) -> np.ndarray:
    """Points on every feature of ``model`` (64 each, a fixed draw): its extent, world frame."""
    rng = np.random.default_rng(0)
    return np.concatenate([f.sample(64, rng)[0] for f in model.features])


def localise(description: SceneDescription, scan: Scan, model: SceneModel,
             params: LocaliseParams = LocaliseParams(), model_simulator=None,
             pairings: dict[int, tuple[str, str]] | None = None) -> PoseResult:
    """Estimate ``T_world_sensor`` of ``scan`` against the a priori ``model``.

    Parameters
    ----------
    description : :func:`recognition.describe.describe` of the scan.
    scan : the scan (sensor model, points; ``pose_prior`` (4, 4) restricts the search when present).
    model : the a priori model.
    params : :class:`LocaliseParams`.
    model_simulator : ``sensors.simulate.Simulator.from_scene(model)``, built once per model and reused
        (compiling costs 0.3-1 s); built here when None.
    pairings : given correspondences ``{patch id: (model feature id, part)}`` replacing the tree search
        (the pose is then computed from them in closed form, verified and refined as usual).

    Returns
    -------
    PoseResult (never raises on a degenerate scene: ``ok=False`` and ``reason``).
    """
    timing = {"matching": 0.0, "pose": 0.0, "verification": 0.0, "icp": 0.0, "predict": 0.0}
    prior = None if scan.pose_prior is None else _check_T(scan.pose_prior, "scan.pose_prior")
    if model_simulator is None:
        from sensors.simulate import Simulator

        model_simulator = Simulator.from_scene(model)
    mp = params.match
    if prior is not None:
        mp = replace(mp, prior_angle_rad=math.radians(params.prior_angle_deg), prior_dist_m=params.prior_dist_m)
    t0 = time.perf_counter()
    el = model_elements(model)
    if pairings is None:
        res = match(description, el, scan.sensor.pixel_pitch_rad, mp, prior)
    else:
        res = given_match(description, el, scan.sensor.pixel_pitch_rad, pairings, mp)
    timing["matching"] = time.perf_counter() - t0
    patch_ids = [description.patches[it.patch_index].id for it in res.items]

    def failed(reason: str, **kw) -> PoseResult:
        base = dict(ok=False, reason=reason, T_world_sensor=None, T_world_sensor_initial=None,
                    cov_T_world_sensor=None, free_dof=6, confidence=0.0, pairings=(),
                    n_hypotheses=len(res.hypotheses), n_nodes=res.n_nodes, predicted=None, timing_s=timing)
        base.update(kw)
        return PoseResult(**base)

    if not res.hypotheses:
        why = "no matchable patches" if not res.items else "no consistent hypothesis"
        return failed(f"{why} ({len(res.items)} items, {res.n_nodes} nodes)")
    # verification of the best hypotheses (fully constrained ones first)
    t0 = time.perf_counter()
    hyps = sorted(res.hypotheses, key=lambda h: (h.pose.free_dof > 0, -h.score))[: params.max_screen]

    # the tree's score hardly tells a symmetric alternative from the right pose (DESIGN 6.3): every
    # hypothesis is screened on a coarse prediction (a few ms each), the best few verified finer
    screen_stride = max(params.screen_stride, params.verify.stride)
    # before ICP the pose may be a fraction of a degree off: the agreement allows for it (``pre_icp_rel``)
    pre_v = replace(params.verify, rel=max(params.verify.rel, params.pre_icp_rel))
    screen_v = replace(pre_v, stride=screen_stride)
    slide = prior is None and params.slide_steps > 0 and all(h.pose.free_dof > 0 for h in hyps)
    extent = _model_points(model) if slide else None
    slid: set[int] = set()  # ids of the hypotheses placed along their free direction by agreement
    slide_v = replace(pre_v, stride=params.slide_stride)

    def start_pose(h):
        T = h.pose.T_world_sensor
        if h.pose.free_dof > 0 and prior is not None:
            pairs = [make_pair(res.items[i], el, e) for i, e in h.pairs if e >= 0]
            T = estimate_pose(pairs, T_init=prior, length_m=1.0).T_world_sensor
        elif slide and len(slid) < params.max_verify:
            direction = free_translation(h.pose.free_dof, h.pose.free_basis)
            if direction is not None:
                def score(T_s):
                    return agreement(description, scan, predict(model_simulator, scan.sensor, T_s,
                                                                params.slide_stride), slide_v)[0]
                T = slide_along(T, direction, extent, score, params.slide_steps)
                slid.add(id(h))
        return T
    screened = []
    for h in hyps:
        T = start_pose(h)
        if screen_stride != params.verify.stride and len(hyps) > params.max_verify:
            sc, _ = agreement(description, scan, predict(model_simulator, scan.sensor, T, screen_stride), screen_v)
        else:
            sc = 0.0
        screened.append((sc, h, T))
    screened.sort(key=lambda x: (-x[0], x[1].pose.free_dof > 0, -x[1].score))
    scored = []
    for _, h, T in screened[: params.max_verify]:
        pred = predict(model_simulator, scan.sensor, T, params.verify.stride)
        score, _ = agreement(description, scan, pred, pre_v)
        scored.append((score, h, pred))
    timing["verification"] = time.perf_counter() - t0
    scored.sort(key=lambda x: (-x[0], x[1].pose.free_dof))
    # ICP on the best few (a closed-form pose from a few pairs can be a degree off: its agreement is then
    # low although it is the right interpretation, DESIGN 6.3); the agreement after ICP decides, which also
    # settles symmetric alternatives (90/180 deg turns of a wall or bay) on the whole predicted image
    finalists = [x for x in scored[: params.max_icp] if x[0] >= params.icp_fraction * scored[0][0]]
    outcomes = []  # (score after a quick ICP, hypothesis, T_init, T after the quick ICP, its prediction)
    for k, (score, h, pred_h) in enumerate(finalists):
        if k > 0 and outcomes[0][0] >= params.accept_agreement and \
                outcomes[0][0] - score >= params.accept_margin:
            break  # far ahead of every remaining hypothesis even after their ICP could help them
        T_i = pred_h.T_world_sensor
        after, T_f, pred_f, frac = _quick_refine(description, scan, model, model_simulator, pred_h,
                                                 _explained(description, res.matchable, res.items, h), params, timing)
        outcomes.append((after, h, T_i, T_f, pred_f, frac))
    outcomes.sort(key=lambda x: (-x[0], x[1].pose.free_dof))
    after0, best, T_init, T_quick, pred_quick, frac0 = outcomes[0]
    scale = _pose_scale(description)
    others = _reinterpretations(description, res, best, el, scan.sensor.pixel_pitch_rad, params, timing)
    twins = _twin_outcomes(description, scan, model, model_simulator, el, best, T_quick, after0, screen_v, params,
                           timing, scale, others)
    alternatives: list[PoseAlternative] = []

    def distinct(T: np.ndarray, seen: list[np.ndarray]) -> bool:
        """Whether ``T`` is not the same pose (``match.same_pose_*``) as any of ``seen`` nor as an alternative."""
        return not any(_close(T, K, scale, params.match.same_pose_angle_deg, params.match.same_pose_rel)
                       for K in [*seen, *(a.T_world_sensor for a in alternatives)])

    for other in [*outcomes[1:], *twins]:
        if not distinct(other[3], [T_quick]):
            continue
        alternatives.append(PoseAlternative(
            other[3], float(other[0]),
            separation_z(*agreement_separation(description, frac0, other[5], params.separation_leave_out))))
    ambiguous = ""
    for alt in alternatives:
        if alt.agreement >= after0 - params.ambiguity_margin:
            ambiguous = f"ambiguous: another pose agrees {alt.agreement:.2f} vs {after0:.2f}"
            break
    # the winner's full ICP, against the model predicted visible from its quickly refined pose
    T_final, cov, free = T_quick, best.pose.cov_T_world_sensor, best.pose.free_dof
    icp_note, rests_on, resting_on = "", "", ""
    if params.use_icp:
        t0 = time.perf_counter()
        ir = icp_refine(scan, pred_quick, model, T_quick, params.icp,
                        _explained(description, res.matchable, res.items, best),
                        (params.pin_angle_deg, params.pin_rel) if params.rest_within_tolerance else None)
        timing["icp"] += time.perf_counter() - t0
        if ir.ok:
            T_final, cov = ir.T_world_sensor, ir.cov_T_world_sensor
            # a slid pose keeps its pairs' free DOF: agreement placed it, no pairing fixes it, and in a
            # repetitive bay a wrong interpretation finds a well-agreeing place too
            free = free if id(best) in slid else min(free, ir.free_dof)
            if ir.free_dof_without_one > params.max_free_without_one:
                rests_on = (f"pose rests on {ir.resting_on} alone: {ir.free_dof_without_one} DOF free without it "
                            "(had it moved, it would have carried the pose)")
                resting_on = ir.resting_on if ir.free_dof_without_one <= params.conditional_max_free else ""
            elif ir.loose_without_one > params.max_free_without_one:
                rests_on = (f"pose rests on {ir.loose_on} alone: without it the rest fixes {ir.loose_without_one} "
                            f"DOF no better than {params.pin_angle_deg:g} deg / {100 * params.pin_rel:g} % of range "
                            "(had it moved, it would have carried the pose)")
                resting_on = ir.loose_on
        else:
            icp_note = f"; ICP not applied: {ir.reason}"
    final_v = _verified(description, scan, model_simulator, T_final, params, timing)  # (for both alternatives)
    start = _start_alternative(description, scan, model_simulator, T_init, T_final, final_v[2], params, timing, scale)
    if start is not None and distinct(start.T_world_sensor, []):
        alternatives.append(start)
    if params.use_icp and params.disagree_fraction > 0:
        for ask in (_disagreeing_alternative, _stable_alternative):
            asked = ask(description, scan, model, model_simulator, final_v, params, timing, scale)
            if asked is not None and distinct(asked.T_world_sensor, []):
                alternatives.append(asked)
    pairs = {patch_ids[i]: (str(el.feature_id[e]) if e >= 0 else None) for i, e in best.pairs}
    # prediction at the final pose (shared with change detection) and the final confidence
    t0 = time.perf_counter()
    pred = predict(model_simulator, scan.sensor, T_final, 1)
    timing["predict"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    conf, _ = agreement(description, scan, pred, params.verify)
    second = overlap_pairings(description, pred, {p for p, f in pairs.items() if f is not None},
                              params.second_stage_fraction, params.verify, scan)
    timing["verification"] += time.perf_counter() - t0
    for pid, fid in second.items():
        pairs[pid] = fid
    pairings = tuple(sorted(pairs.items(), key=lambda kv: kv[0]))
    t0 = time.perf_counter()
    pin_z, pin_probe = _pinned(description, scan, model_simulator, T_final, params)
    timing["verification"] += time.perf_counter() - t0
    alt_z = min((a.separation for a in alternatives), default=math.inf)
    if not ambiguous and alt_z < params.separation_z:
        ambiguous = f"ambiguous: another pose is separated by {alt_z:.2f} < {params.separation_z} standard errors"
    not_pinned = "" if pin_z >= params.pin_z else (
        f"pose not pinned within {params.pin_angle_deg:g} deg / {100 * params.pin_rel:g} % of range: the probe "
        f"{PROBE_NAMES[pin_probe]} is separated by {pin_z:.2f} < {params.pin_z} standard errors")
    verdict_conf = _confidence(min(pin_z, alt_z))
    checked = conf >= params.min_confidence and free == 0 and not ambiguous and not icp_note and not not_pinned
    ok = checked and not rests_on
    reason = ""
    if icp_note:
        reason = "pose not refined"
    elif free > 0:
        reason = f"pose underconstrained: {free} free DOF"
        if id(best) in slid:
            reason += " (placed along it by agreement)"
    elif conf < params.min_confidence:
        reason = f"low confidence {conf:.2f} < {params.min_confidence}"
    elif ambiguous:
        reason = ambiguous
    elif not_pinned:
        reason = not_pinned
    elif rests_on:
        reason = rests_on
    if res.stop_reason and not ok:
        reason += f"; search stopped: {res.stop_reason}"
    return PoseResult(ok, reason + icp_note if not ok else "", T_final, T_init, cov, int(free), verdict_conf,
                      pairings, len(res.hypotheses), res.n_nodes, pred, timing, tuple(alternatives), float(conf),
                      resting_on if checked else "")
