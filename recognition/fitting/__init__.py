"""Fitting: one home for the plane, quadric, cylinder, sphere, cone and torus fits and their shared algebra.

The paper fits planes or quadrics to the segmented patches (section 3 of Fillatreau & Fisher), classifies them
through a quadric's canonical form and verifies the class a posteriori with a dedicated fit. Here:

- :mod:`~recognition.fitting.algebra`: the quadric's parameters, monomial basis, gradient and normalisation;
- :mod:`~recognition.fitting.plane`: :class:`PlaneFit` from the dedicated :func:`fit_plane` or the
  segmenter's :func:`fit_plane_lsq`;
- :mod:`~recognition.fitting.quadric`: :func:`fit_quadric` (Taubin + Levenberg-Marquardt, with covariance) and
  its canonical form (:func:`canonicalise`), and the segmenter's :func:`fit_quadric_lsq`;
- :mod:`~recognition.fitting.sphere`, :mod:`~recognition.fitting.cylinder` (cylinders and cones),
  :mod:`~recognition.fitting.torus`: the dedicated fits, and :mod:`~recognition.fitting.range_refit`.

About the dedicated fits:

Every fit minimises the (Huber-robustified) sum of squared sigma-normalised orthogonal distances with a
small Levenberg-Marquardt solver on a manifold (axes are updated by a rotation in the plane orthogonal to
them, axis points slide in that plane), using vectorised residuals and analytic Jacobians, and stops on a
relative cost decrease below ``tol``. Initial values come from closed forms (weighted PCA for the plane, an
algebraic sphere fit) or from the axis of the Taubin quadric (or of the normals when given) followed by an
algebraic circle fit, so a few iterations suffice.

Large patches are subsampled on a regular stride (deterministic) to ``max_points`` for the iterations:
the start of lowest cost is chosen and iterated on a coarse subset of 400 points, refined by a few
iterations on the ``max_points`` subsample and polished by Gauss-Newton steps on all points; the residual
statistics and the covariance are computed on all points (so they reflect the whole patch).

The covariance is the sandwich ``H^-1 (J' W diag(r²) W J) H^-1 n / (n - k)`` with ``H = J' W J`` over the
minimal local parameters (``W``: Huber weights, ``r``: sigma-normalised residuals), then mapped to the
reported parameters. It equals ``s² H^-1`` (``s² = chi² / (n - k)``) when the normalised residuals are
homoscedastic, and stays right when they are not: range noise is along the ray while the fitted distance is
along the normal, so grazing points have smaller residuals than their sigma says (the plain form
over-predicted radius and half-angle sigmas 1.3-1.5x in Monte Carlo checks; the sandwich matched within
the 20 % tolerance of the tests).

Radius bias (measured against truth by ``python -m harness.bench.classification``): on one-sided patches the
geometric fit is within 0.1 % at mock-up and factory noise (median -0.02 %), but biased low under
Kinect-like noise where sigma/r reaches 0.2-0.5 (median about -2.7 %, p10 -19 %): the likelihood of
points displaced along the ray is not the orthogonal-distance one once the noise is a sizeable fraction of
the radius. Weighting each point by its incidence (``origin=``, ``sigma |cos|``) did not remove it and made
the predicted sigmas worse, so it is off by default. On real simulated scans (beam footprint of 4
sub-rays, noise along the ray) the geometric fit was much further off: 2.1 % low (median) on the factory
scanner's pipes, far outside its sigma. :func:`refit_along_rays` removes it, given each point's sub-ray
directions: a range-space refit whose predicted return is the mean over the sub-rays of their distance to
the model (measured on the default suite's groups with the truth segmentation: median error +0.02 %, median
|error| 0.24 %, 88 % of radii within 2 predicted sigmas on the factory scanner; on the mock-up 0.00 % /
0.03 % / 96 %).

A degenerate fit (too few points, non-finite input, collinear or coplanar points where a curved primitive
is needed, a diverging radius) is a result with ``ok=False`` and a ``reason``; only misuse raises.

The cone is parameterised by a point on its axis near the data, the radius there and the slope
``t = tan(half-angle)``, so it is continuous through ``t = 0`` (the cylinder) and nests it.
"""

from __future__ import annotations

import numpy as np

from ._solver import TRIM_SIGMA, huber_weights, trimmed_chi2
from .algebra import (
    MIN_GRAZING,
    MONOMIAL_GRADIENT,
    check_patch,
    evaluate,
    gradient,
    monomials,
    normalisation_map,
    plane_params,
    quadric_matrices,
    quadric_params,
    ray_residuals,
    taubin_fit,
)
from .cylinder import ConeFit, CylinderFit, axis_candidates, cone_residuals, cylinder_residuals, fit_cone, fit_cylinder
from .plane import PlaneFit, fit_plane, fit_plane_lsq
from .quadric import (
    CanonicalQuadric,
    QuadricFit,
    QuadricSurfaceFit,
    canonical_quantities,
    canonicalise,
    fit_quadric,
    fit_quadric_lsq,
)
from .range_refit import refit_along_rays
from .sphere import SphereFit, fit_sphere
from .torus import TorusFit, bend_test, fit_torus

__all__ = [
    "MIN_GRAZING",
    "MONOMIAL_GRADIENT",
    "TRIM_SIGMA",
    "CanonicalQuadric",
    "ConeFit",
    "CylinderFit",
    "PlaneFit",
    "QuadricFit",
    "QuadricSurfaceFit",
    "SphereFit",
    "TorusFit",
    "axis_candidates",
    "bend_test",
    "canonical_quantities",
    "canonicalise",
    "check_patch",
    "cone_residuals",
    "cylinder_residuals",
    "evaluate",
    "fit_cone",
    "fit_cylinder",
    "fit_plane",
    "fit_plane_lsq",
    "fit_primitive",
    "fit_quadric",
    "fit_quadric_lsq",
    "fit_sphere",
    "fit_torus",
    "gradient",
    "huber_weights",
    "monomials",
    "normalisation_map",
    "plane_params",
    "quadric_matrices",
    "quadric_params",
    "ray_residuals",
    "refit_along_rays",
    "taubin_fit",
    "trimmed_chi2",
]


def fit_primitive(label: str, points: np.ndarray, sigma: np.ndarray | float,
                  normals: np.ndarray | None = None) -> PlaneFit | CylinderFit | SphereFit | ConeFit | None:
    """The dedicated fit of class ``label`` (PLAN, CYL, SPH, CONE) with default settings; None for OTH."""
    fit = {"PLAN": fit_plane, "CYL": fit_cylinder, "SPH": fit_sphere, "CONE": fit_cone}.get(label)
    return None if fit is None else fit(points, sigma, normals)
