"""Classification: patches labelled PLAN, CYL, SPH, CONE or OTH (section 3 of Fillatreau & Fisher) behind one
interface, :func:`classify_patch`, with two classifiers: ``paper`` (:mod:`.paper`, the paper's rule made precise)
and ``select`` (:mod:`.select`, the core's model-selection classifier, with the trimmed rescue of :mod:`.rescue`);
and :func:`merge_test` (:mod:`.merge`), whether one primitive explains two patches.

Both methods fit on a regular-stride subsample of at most ``max_points`` points (the information criterion
then works with that N: the decision is that of a patch of ``max_points`` points), and the chosen primitive
is polished by a Gauss-Newton step on all points so its parameters, covariance and invariants use the
whole patch.

The invariants' visible length has a heuristic sigma: the point spacing ``sqrt(L W / N)`` (W the patch
width across the axis), since the length is set by the patch ends, not by the fit.

Degenerate patches (fewer than 10 points, NaNs, collinear or exactly coplanar points) give OTH with a
``reason`` (PLAN for coplanar points with ``planar_hint``), never an exception; wrong shapes raise
``ValueError``.
"""

from .classify import classify_patch
from .merge import merge_test
from .paper import paper_plausibilities
from .params import PaperParams, SelectParams
from .result import CLASSES, PatchClassification, Primitive

__all__ = [
    "CLASSES", "PaperParams", "SelectParams", "PatchClassification", "Primitive", "classify_patch",
    "paper_plausibilities", "merge_test",
]
