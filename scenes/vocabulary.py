"""The words every layer shares, declared once and imported downward (DESIGN 2: ``harness -> reports ->
evaluation -> recognition -> sensors -> scenes``).

Both the core (``recognition``) and the scoring (``evaluation``, ``reports``) speak of a surface's class and of
a feature's change, so their names live here, at the bottom, in a module that holds no ground truth: the core
may import it (it must never import :mod:`scenes.perturb`, which draws the truth).

* :data:`CLASSES` - the paper's classes of a surface: PLAN, CYL, SPH, CONE, OTH (declared beside the feature
  types as :data:`scenes.features.TRUTH_CLASSES`; this is the same tuple).
* :data:`CHANGE_LABELS` - what happened to a feature or an object between the a priori model and the scene
  (DESIGN 10.7): unchanged, moved, missing, altered, new. A change map's pixel is an index into
  :data:`CHANGE_MAP_LABELS`, which adds :data:`UNOBSERVED` (the core could not see it: never scored).

Which labels a score averages (macro-F1 over the labels that name a change) is the evaluation's business:
:data:`evaluation.metrics.MACRO_LABELS`.
"""

from __future__ import annotations

from scenes.features import TRUTH_CLASSES

__all__ = ["CLASSES", "CHANGE_LABELS", "UNCHANGED", "MOVED", "MISSING", "ALTERED", "NEW", "UNOBSERVED",
           "CHANGE_MAP_LABELS"]

#: The paper's classes of a surface, in this order everywhere (probability vectors, confusion matrices).
CLASSES: tuple[str, ...] = TRUTH_CLASSES

#: The change labels of a feature or an object (DESIGN 10.7), in this order everywhere.
CHANGE_LABELS: tuple[str, ...] = ("unchanged", "moved", "missing", "altered", "new")
UNCHANGED, MOVED, MISSING, ALTERED, NEW = CHANGE_LABELS
#: What the core says of a feature it could not see; excluded from scoring.
UNOBSERVED = "unobserved"
#: The labels of a change map: a pixel's value is an index into this tuple (-1: no label).
CHANGE_MAP_LABELS: tuple[str, ...] = (*CHANGE_LABELS, UNOBSERVED)
