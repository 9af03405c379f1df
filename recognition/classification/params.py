"""Parameters of the two classifiers of section 3 of Fillatreau & Fisher: :class:`PaperParams` (the paper's
plausibility rule) and :class:`SelectParams` (the core's model selection); every tuned value says on which
suite and figure it was chosen (its metadata, :func:`recognition.tuning.tuned`; all of them: ``docs/tuning.md``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recognition.tuning import tuned


@dataclass(frozen=True)
class PaperParams:
    """Parameters of the paper's plausibility classifier.

    Section 3 of the paper fixes the rule (plausibilities from the propagated Gaussians of the canonical
    parameters, the 0.2 margin, the a posteriori check) but leaves open the choices below; each is an option
    here, its default today's reading (the ``paper`` baseline), and the ``paper_reproduction`` suite runs the
    alternatives side by side (``docs/paper_reproduction.md``).

    Attributes
    ----------
    zero_rule : {"literal", "soft"}
        Plausibility of ``x = 0``. The paper: "heuristic functions involving the probabilities that the
        corresponding parameter is greater or lower than the required value (zero)", no function given.
        ``"literal"``: ``2 min(P(x>0), P(x<0))`` (1 at ``x = 0``, 0.317 at one sigma, 0.046 at two: for an exact
        primitive it is uniform on [0, 1]); ``"soft"``: ``exp(-z²/8)`` with ``z = x / sigma`` (0.88 at one sigma,
        0.61 at two).
    sigma_mode : {"bauer_fike", "first_order"}
        Eigenvalue sigmas (see :func:`recognition.fitting.canonicalise`). The paper: "we used an upper bound
        provided by the Bauer-Fike theorem", without saying how the size of the perturbation of ``A`` is taken
        from the fit's covariance, nor whether the eigenvalues' correlations (with each other and with
        ``C_cano``) are kept. ``"bauer_fike"``: ``sigma_l = sqrt(E ||dA||_F²)`` for every eigenvalue,
        uncorrelated; ``"first_order"``: ``dl_i = v_i' dA v_i`` with the full covariance (smaller sigmas: the
        "= 0" tests are stricter).
    margin : float
        The winning plausibility must beat the others by more than this (paper: 0.2).
    verify_factor : float
        A posteriori check: the dedicated fit's RMS distance must be <= ``verify_factor * RMS(sigma)``. The
        paper: "if lower than a given threshold"; the threshold is not given.
    max_points : int
        How many of the patch's points the fits use (the quadric's, hence the sigmas of the canonical
        parameters, which shrink as ``1 / sqrt(max_points)``; and the dedicated fits'). The paper fits each
        patch whole (least squares, then an Extended Kalman Filter) and does not say how many measured points
        its patches had, only that the OTH ones were "small patches containing a small number of noisy measure
        points": with fewer points the same biases (beam footprint, range-dependent noise) are fewer sigmas
        away from zero, and every "= 0" plausibility rises.
    subsample : {"stride", "random"}
        How the quadric fit's ``max_points`` points are chosen when the patch has more (not said by the paper,
        which used them all; the dedicated fits keep their own regular stride): ``"stride"``, evenly spaced in the
        patch's pixel order (row-major: every k-th pixel, a regular grid over the patch); ``"random"``, a uniform
        draw without replacement, seeded by the patch's point count (the same patch gives the same points).
    huber : float or None
        Huber threshold (sigma units) of the dedicated fits.
    """

    zero_rule: str = tuned("literal", unit="-", chosen="the paper's rule, read literally (the baseline)")
    sigma_mode: str = tuned("bauer_fike", unit="-", chosen="the paper's eigenvalue bound (the baseline)")
    margin: float = tuned(0.2, unit="probability", chosen="the paper's value")
    verify_factor: float = tuned(1.5, unit="ratio", chosen="not tuned: set with the baseline in 1a61ec8")
    max_points: int = tuned(2000, unit="points", chosen="not tuned: a speed bound, set in 1a61ec8")
    subsample: str = tuned("stride", unit="-", chosen="not tuned: the regular stride of 1a61ec8 (the baseline)")
    huber: float | None = tuned(3.0, unit="sigma", chosen="not tuned: set in 1a61ec8")

    def __post_init__(self) -> None:
        choices = {"zero_rule": ("literal", "soft"), "sigma_mode": ("bauer_fike", "first_order"),
                   "subsample": SUBSAMPLES}
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {getattr(self, name)!r}")
        if self.max_points < 10:
            raise ValueError(f"max_points must be >= 10 (a quadric has 9 degrees of freedom), got {self.max_points!r}")


#: How :class:`PaperParams` chooses a patch's ``max_points`` points (its ``subsample``).
SUBSAMPLES = ("stride", "random")


@dataclass(frozen=True)
class SelectParams:
    """Parameters of the model-selection classifier.

    Attributes
    ----------
    criterion : {"bic", "aic"}
        ``chi² + k ln N`` or ``chi² + 2 k``.
    gof_factor : float
        Tolerance for model error: the best model's reduced chi² (orthogonal distances over the given
        sigma) may reach this before the patch is OTH. With sigma along the ray the expected value for a
        correct model is ~E[cos² incidence] < 1.
    gof_z : float
        Statistical allowance ``gof_z * sqrt(2 / dof)`` added to ``gof_factor``.
    gof_width : float
        Relative width of the smooth goodness-of-fit plausibility around the threshold.
    quadric_as_other : bool
        Let a general quadric (k = 9) compete as the model of OTH.
    other_penalty : float
        Added to the quadric's criterion (a prior against OTH): at Kinect-like noise the range-dependent
        bias of one-sided fits makes true primitives slightly non-primitive, and the 9-parameter quadric
        then wins some of them.
    planar_hint_odds : float
        Prior odds multiplying the plane's posterior weight when the segmenter says the patch is planar.
    temperature : float
        Posterior weights ``exp(-delta / (2 T))``: T = 1 is the plain criterion; T > 1 tempers the
        over-confidence that unmodelled errors (range-dependent bias, non-Gaussian noise) give large N.
        Fit it on a calibration suite, never on the evaluation suite (DESIGN 10.8): T = 1 was best on the
        ``calibration`` suite (see ``prob_floor``).
    max_points : int
        Subsample size for the fits and the criterion.
    max_iter : int
        Iteration limit of each candidate fit. Correct models converge in 3-6 iterations from their starts
        at low noise but may crawl for 15-20 at Kinect-like noise (a cylinder cut off at 10 lost to the
        cone nested in it); models that are clearly losing stop early (``stop_above``).
    huber : float or None
        Huber threshold (sigma units) of the fits.
    cone_score_skip : float or None
        The cone is fitted only when a score test at the cylinder's solution (the decrease of the cost that
        one Gauss-Newton step of the cone predicts) reaches this fraction of the criterion's price of one
        parameter (``ln N`` for BIC); otherwise its criterion is the cylinder's plus that price minus the
        predicted decrease. None: no score test (always fit it).
    prob_floor : float
        Mixed with the uniform distribution: ``p = (1 - f) p + f / 5`` (bounds the Brier cost of a confident
        error). Fitted with ``temperature`` and ``gof_width`` on the ``calibration`` suite
        (``harness/suites/calibration.yaml``, seed 4242, never on ``default``; DESIGN 10.8): grid search of the
        multi-class Brier score over the 199 patches of >= 200 pixels of its 24 scans, end to end (real
        segmenter), with T in {1, 2, 4, ..., 32}, f in {0, 0.05, 0.1, 0.2, 0.3}, gof_width in {0.1, ..., 1.6}:
        best T = 1, f = 0.1, gof_width = 0.1 (Brier 0.240 -> 0.227 at accuracy 0.879). The remaining Brier
        is that of confident errors on patches the segmenter merged across two surfaces, which no
        re-weighting of the posterior fixes. The floor of the labels reached by the criterion, the plane gate
        and the elbow test (see ``rescue_floor`` and ``unexplained_floor`` for the other two decision paths).
    rescue_floor : float
        The floor (as ``prob_floor``) of a label the trimmed rescue gives (``min_inliers``; decision path
        ``"rescue"``, :func:`recognition.classification.select.decision_path`): such a patch is a mixture by
        construction, and its label, the primitive of its majority, is right less often than its inlier
        fraction says. At least ``prob_floor``. Fitted on the ``calibration`` suite with
        ``python -m harness.bench.confidence`` (the floor that minimises the Brier score of the path's patches).
    unexplained_floor : float
        The floor of OTH when no primitive fits within noise and no torus explains the points (decision path
        ``"unexplained"``): mostly patches the segmenter merged across surfaces, whose majority (the truth the
        evaluation scores) is a primitive. At least ``prob_floor``, below 1 (at 1 every class is equal). On the
        ``calibration`` suite OTH was right on 3 of these 21 patches: the Brier-optimal floor is 1, and 0.75
        gives a certain OTH the probabilities of a patch not better than noise
        (:data:`recognition.describe.NOISE_PROBABILITIES`: OTH 0.4, each primitive 0.15).
    range_refit : bool
        With sub-ray directions (``rays`` of :func:`classify_patch`), refit a chosen cylinder or sphere in
        range space (:func:`recognition.fitting.refit_along_rays`), which removes the radius bias of the
        geometric fit (beam footprint, noise along the ray).
    refit_points : int
        Subsample size of that refit's iterations.
    outlier_k : float or None
        Gross outliers (see :func:`_gross_outliers`) are removed before fitting when they are at most 20 %
        of the patch; None: keep all points.
    min_inliers : float or None
        A patch that would be OTH (no primitive fits all its points within noise, or a general quadric fits
        them better) gets the label of a primitive (plane, cylinder or sphere; not the cone, the most
        flexible) when, after three least-trimmed-squares refits on this fraction of its points, at least
        this fraction lies within ``trim_sigma`` of it and those pass the goodness-of-fit test; probability:
        that fraction. For patches the segmenter merged across two surfaces. None: no trimmed rescue. A pipe
        elbow also has most of its points near a cylinder (91 % within 3.5 sigma on a low-noise synthetic
        one), so an elbow that a torus explains (``torus``) is never rescued. Chosen on the first phase's
        ``calibration`` suite (seed 4242, never ``default``), end to end with the torus: 0.6, 0.7, 0.8 and 0.9
        gave the same labels there, accuracy 0.895 -> 0.917 (factory scanner 0.924 -> 0.958, mock-up 0.983 ->
        1.0, Kinect-like unchanged) and Brier 0.190 -> 0.151; 0.8, the middle, is the default.
    torus : bool
        Fit a ring torus (a pipe elbow, :func:`recognition.fitting.fit_torus`) when a curved primitive
        leads the criterion and the bend test passes (``torus_score_skip``). It competes as a model of OTH
        (k = 7): an elbow that it explains wins as OTH with its bend and pipe radii as invariants, where a
        cylinder or sphere would otherwise take its points at Kinect-like noise; and a torus that fits within
        noise and beats every primitive vetoes the trimmed rescue (``min_inliers``). The points must be in the
        sensor frame (the tube's normals are turned to face the origin).
    max_bend_ratio : float
        A torus competes only when its bend radius is at most this many pipe radii (pipe elbows are bent at
        1-5 pipe diameters): a torus of a much larger bend radius is a cylinder bent by the residuals of an
        impure patch or by range bias, not an elbow.
    torus_score_skip : float
        When the best primitive fits within noise, the torus is fitted only if bending the cylinder's axis
        (:func:`recognition.fitting.bend_test`, one linear least-squares step) predicts a decrease of
        the chi² of at least this fraction of the criterion's price of the torus's two extra parameters, with
        a bend radius of at most ``3 max_bend_ratio`` cylinder radii. On the ``calibration`` suite the torus
        took accuracy from 0.890 to 0.895 without the trimmed rescue (mock-up 0.967 -> 0.983).
    min_torus_points : int
        Patches of fewer points (after the gross outliers) get neither the torus nor the trimmed rescue:
        too few points to pin a torus's 7 parameters or to tell a majority from a merged neighbour; the size
        below which the evaluation does not score patches either. On the ``calibration`` suite 200 and 0 gave
        the same accuracy, Brier and correct detection; on ``default`` the 15-20 small patches of a
        factory-scanner frame took half its classification time with them.
    plane_gate : float or None
        Cylinders, cones and spheres are not fitted when the plane passes the goodness-of-fit test and a
        quadratic height field over it lowers the trimmed chi² by less than this fraction of their price
        (``2 ln N`` for two more parameters, plus the planar hint's log odds): at this scale they are such
        height fields, so they cannot win (large planar patches were 70 % of a frame's time). None: no gate
        (always fit them).
    invariant_sigma_scale : float
        Multiplies the sigmas of the reported invariants (radius, half-angle, length; the fits' own
        covariances are left alone). The fits' sandwich covariances miss errors shared by neighbouring points
        (beam footprint, incidence-dependent range bias): on the ``calibration`` suite (seed 4242, never
        ``default``; DESIGN 10.8) the radius errors of the 77 patches labelled CYL or SPH on a true cylinder or
        sphere had a median of 0.95 predicted sigmas where a Gaussian has 0.674: scale 1.415, rounded to 1.4.
    trim_sigma : float
        The trimmed chi² of the criterion and the goodness of fit: residuals beyond this many sigmas count as
        ``trim_sigma²`` (mixed pixels, outliers and bits of a neighbouring surface at a patch's border add at
        most that much each); the trimmed rescue's inliers are the points within it.
    single_sheet_fraction : float
        The general quadric competes as OTH only when the sign of its gradient along the plane's normal is the
        same for this fraction of the points (a noisy plane is fitted better by two parallel sheets, which are
        not a surface: :func:`_single_sheet`).
    merge_points : int
        Points (regular-stride subsample) of the union fit of :func:`recognition.classification.merge_test`.
    refit_trim : float
        Hard trimming threshold (sigma units) of the range refit (``range_refit``): points beyond get weight 0.
    refit_iter : int
        Iterations of the range refit at most.
    refit_final_points : int
        Points of the range refit's last two iterations, statistics and covariance.

    Every field's unit and where its value was chosen: :func:`recognition.tuning.tuned` (``docs/tuning.md``).
    """

    criterion: str = tuned("bic", unit="-", chosen="not tuned: BIC since 1a61ec8")
    gof_factor: float = tuned(1.5, unit="reduced chi²", chosen="not tuned: set in 1a61ec8")
    gof_z: float = tuned(3.0, unit="sigma", chosen="not tuned: set in 1a61ec8")
    gof_width: float = tuned(
        0.1, unit="relative", chosen="calibration (phase 1): grid search with temperature and prob_floor, Brier "
        "0.240 -> 0.227 at accuracy 0.879 (83bb055)")
    quadric_as_other: bool = tuned(True, unit="-", chosen="on since 1a61ec8: the general quadric is the model of OTH")
    other_penalty: float = tuned(0.0, unit="criterion", chosen="not tuned: no prior against OTH (1a61ec8)")
    planar_hint_odds: float = tuned(100.0, unit="odds", chosen="not tuned: set in 1a61ec8")
    temperature: float = tuned(
        1.0, unit="-", chosen="calibration (phase 1): T = 1 best of {1, 2, 4, ..., 32} by the Brier score (83bb055)")
    max_points: int = tuned(1500, unit="points", chosen="not tuned: a speed bound, set in 1a61ec8")
    max_iter: int = tuned(25, unit="count", chosen="not tuned: set in 1a61ec8 (a cylinder cut off at 10 lost to "
                          "the cone nested in it at Kinect-like noise)")
    huber: float | None = tuned(3.0, unit="sigma", chosen="not tuned: set in 1a61ec8")
    cone_score_skip: float | None = tuned(
        0.7, unit="fraction", chosen="not tuned: a speed gate, set in 83bb055 (accuracy unchanged there)")
    prob_floor: float = tuned(
        0.1, unit="probability", chosen="calibration (phase 1): f = 0.1 best of {0, 0.05, 0.1, 0.2, 0.3} by the "
        "Brier score, with temperature and gof_width (83bb055)")
    rescue_floor: float = tuned(
        0.37, unit="probability", chosen="calibration: the Brier-optimal floor of the 38 rescued patches of >= 200 "
        "pixels, 0.366 (python -m harness.bench.confidence on its run; their accuracy 0.684 at stated 0.880)")
    unexplained_floor: float = tuned(
        0.75, unit="probability", chosen="calibration: Brier-optimal at the bound 1 (3 of its 21 patches right at "
        "stated 0.919; python -m harness.bench.confidence); 0.75 gives a certain OTH the probabilities of a patch "
        "not better than noise (OTH 0.4, each primitive 0.15)")
    range_refit: bool = tuned(
        True, unit="-", chosen="on since 83bb055: the factory scanner's cylinder radii, 2.1 % low (median) from the "
        "geometric fit, within 0.02 % (the first phase's default, now classic)")
    refit_points: int = tuned(600, unit="points", chosen="not tuned: a speed bound, set in 83bb055")
    outlier_k: float | None = tuned(8.0, unit="robust sigma", chosen="not tuned: set in 83bb055")
    min_inliers: float | None = tuned(
        0.8, unit="fraction", chosen="calibration (phase 1), with the torus: accuracy 0.895 -> 0.917, Brier 0.190 "
        "-> 0.151; 0.6-0.9 gave the same labels, 0.8 the middle (1777436)")
    torus: bool = tuned(True, unit="-", chosen="calibration (phase 1): accuracy 0.890 -> 0.895 without the rescue "
                        "(1777436)")
    max_bend_ratio: float = tuned(10.0, unit="pipe radii", chosen="not tuned: elbows are bent at 1-5 pipe diameters "
                                  "(1777436)")
    torus_score_skip: float = tuned(0.7, unit="fraction", chosen="not tuned: a speed gate, set in 1777436")
    min_torus_points: int = tuned(
        200, unit="points", chosen="calibration (phase 1): 200 and 0 gave the same accuracy, Brier and correct "
        "detection; chosen for speed (325e52e)")
    plane_gate: float | None = tuned(
        0.5, unit="fraction", chosen="not tuned: a speed gate, set in 83bb055 (large planes were 70 % of a "
        "frame's time)")
    invariant_sigma_scale: float = tuned(
        1.4, unit="ratio", chosen="calibration (phase 1): median radius error 0.95 predicted sigmas against "
        "0.674 for a Gaussian (77 patches): 1.415, rounded (0b428fc)")
    trim_sigma: float = tuned(
        3.5, unit="sigma", chosen="not tuned: set with the robust goodness of fit in 83bb055 (a low-noise "
        "synthetic elbow has 91 % of its points within 3.5 sigma of a cylinder)")
    single_sheet_fraction: float = tuned(0.9, unit="fraction", chosen="not tuned: set in 1a61ec8")
    merge_points: int = tuned(1500, unit="points", chosen="not tuned: a speed bound, set with the merge test in "
                              "97ec30f")
    refit_trim: float = tuned(4.0, unit="sigma", chosen="not tuned: set with the range refit in 83bb055")
    refit_iter: int = tuned(5, unit="count", chosen="not tuned: set with the range refit in 83bb055")
    refit_final_points: int = tuned(6000, unit="points", chosen="not tuned: a speed bound, set with the range "
                                    "refit in 83bb055")

    def __post_init__(self) -> None:
        if self.criterion not in ("bic", "aic"):
            raise ValueError(f"criterion must be 'bic' or 'aic', got {self.criterion!r}")
        for name in ("cone_score_skip", "outlier_k", "plane_gate"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number or None (off), got {v!r}")
        if self.min_inliers is not None and not 0 < self.min_inliers < 1:
            raise ValueError(f"min_inliers must be in (0, 1) or None (off), got {self.min_inliers!r}")
        for name in ("trim_sigma", "refit_trim"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        if not 0.5 <= self.single_sheet_fraction <= 1:
            raise ValueError(f"single_sheet_fraction must be in [0.5, 1], got {self.single_sheet_fraction!r}")
        for name in ("merge_points", "refit_final_points"):
            if getattr(self, name) < 10:
                raise ValueError(f"{name} must be >= 10, got {getattr(self, name)!r}")
        if self.refit_iter < 1:
            raise ValueError(f"refit_iter must be >= 1, got {self.refit_iter!r}")
        if not 0 <= self.prob_floor < 1:
            raise ValueError(f"prob_floor must be in [0, 1), got {self.prob_floor!r}")
        for name in ("rescue_floor", "unexplained_floor"):
            v = getattr(self, name)
            if not self.prob_floor <= v < 1:
                raise ValueError(f"{name} must be in [prob_floor = {self.prob_floor:g}, 1), got {v!r}")

    def floor(self, path: str) -> float:
        """The probability floor of a label reached by decision path ``path`` (one of :data:`DECISION_PATHS`)."""
        if path not in DECISION_PATHS:
            raise ValueError(f"decision path must be one of {', '.join(map(repr, DECISION_PATHS))}, got {path!r}")
        return {"rescue": self.rescue_floor, "unexplained": self.unexplained_floor}.get(path, self.prob_floor)


#: How the model-selection classifier reaches a label (:func:`recognition.classification.select.decision_path`).
DECISION_PATHS = ("criterion", "plane_gate", "elbow", "rescue", "unexplained")
