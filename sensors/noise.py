"""The range sensor noise model: its parameters and the per-pixel range sigma.

A :class:`NoiseModel` is the preset's noise description. The simulator (:mod:`sensors.simulate`)
applies it; the recognition core receives it with the scan and calls :meth:`NoiseModel.sigma` on its
own range and normal estimates (it never sees the true per-pixel sigma, DESIGN 10.1).

Terms, each switched off by its neutral value (``NoiseModel.without(term)`` does that for you):

``range``
    Gaussian noise along the ray. ``range_model="ray"``:
    ``sigma(r, i) = (s0 + s2 r^2) / max(cos i, cos i_max)`` (metres; ``r`` range, ``i`` incidence angle,
    clipped at ``i_max`` so that sigma stays finite at grazing angles).
    ``range_model="kinect_axial"`` (Nguyen, Izadi & Lovell 2012, doi:10.1109/3DIMPVT.2012.84), axial
    ``sigma_z(z, i) = s0 + s2 (z - z0)^2 + b / sqrt(z) * i^2 / (pi/2 - i)^2`` with ``i`` clipped at
    ``i_max``, converted to the ray (DESIGN 10.2): a depth error ``dz`` along a fixed ray of direction
    ``d`` is a range error ``dz / d_z``, so ``sigma_r = sigma_z / d_z``.
    With ``matching_window_px`` ``w > 1`` the errors are spatially correlated as a stereo or structured-light
    matcher makes them: white noise averaged over a ``w x w`` window and rescaled to unit variance (the
    per-pixel sigma is unchanged), so ``w²`` pixels carry one independent error (:attr:`NoiseModel.correlation_area`).
``quantisation``
    Rounding of the measured range to a step in metres (``quantisation_mode="range"``), or of inverse
    depth to a step in 1/m (``"inverse_depth"``: disparity-based sensors, depth step ~ ``step z^2``).
``grazing``
    Dropout probability ramping linearly from 0 at ``grazing_start`` to 1 at ``grazing_end`` (radians).
``footprint``
    The beam is ``footprint_rays`` sub-rays: the centre ray plus ``k - 1`` rays on a circle of
    ``footprint_radius_px`` pixels. Their ranges are averaged (equal weights); a beam straddling a
    depth edge returns a blend between the surfaces ("mixed pixel"). A return needs the centre ray and
    at least ``min_return_fraction`` of all sub-rays to hit within the range limits.
``specular``
    Per-material dropout probability (``specular_dropout``: pairs ``(material, p)``).
``outliers``
    A fraction ``outlier_rate`` of the returns is replaced by a range uniform in the sensor's limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

RANGE_MODELS = ("ray", "kinect_axial")
QUANTISATION_MODES = ("range", "inverse_depth")
TERMS = ("range", "quantisation", "grazing", "footprint", "specular", "outliers")


@dataclass(frozen=True)
class NoiseModel:
    """Parameters of the range noise (metres and radians; see the module docstring for each term).

    Attributes
    ----------
    enabled : master switch; ``False`` gives the exact range (within the sensor's range limits).
    range_model : ``"ray"`` or ``"kinect_axial"``.
    s0_m : constant sigma term (metres).
    s2_per_m : coefficient of ``r^2`` (``(z - z0)^2`` for ``kinect_axial``), 1/m.
    z0_m : ``kinect_axial`` only: depth of the quadratic's minimum (metres).
    incidence_coeff_m : ``kinect_axial`` only: ``b`` of the incidence term (metres * sqrt(metres)).
    max_incidence : incidence angle (radians) beyond which sigma stops growing.
    matching_window_px : side of the window over which the range errors are correlated (1 = independent).
    quantisation_step : 0 = off; metres (``range`` mode) or 1/m (``inverse_depth`` mode).
    quantisation_mode : ``"range"`` or ``"inverse_depth"``.
    grazing_start, grazing_end : radians, ``grazing_start <= grazing_end``; ``pi/2`` = off.
    footprint_rays : sub-rays per pixel (1 = off).
    footprint_radius_px : radius of the sub-ray circle, pixels (grid cells for a scanning laser).
    min_return_fraction : fraction of sub-rays that must hit for a return (0-1].
    specular_dropout : ``((material, probability), ...)``.
    outlier_rate : probability that a return is an outlier.
    mixed_threshold_sigma : a footprint blend farther than this many sigma (or 0.1 mm per metre) from the
        centre ray's exact range is flagged as a mixed pixel.
    """

    enabled: bool = True
    range_model: str = "ray"
    s0_m: float = 0.0
    s2_per_m: float = 0.0
    z0_m: float = 0.0
    incidence_coeff_m: float = 0.0
    max_incidence: float = math.radians(80.0)
    matching_window_px: int = 1
    quantisation_step: float = 0.0
    quantisation_mode: str = "range"
    grazing_start: float = math.pi / 2
    grazing_end: float = math.pi / 2
    footprint_rays: int = 1
    footprint_radius_px: float = 0.5
    min_return_fraction: float = 0.5
    specular_dropout: tuple[tuple[str, float], ...] = ()
    outlier_rate: float = 0.0
    mixed_threshold_sigma: float = 3.0

    def __post_init__(self):
        if self.range_model not in RANGE_MODELS:
            raise ValueError(f"range_model must be one of {', '.join(RANGE_MODELS)}, got {self.range_model!r}")
        if self.quantisation_mode not in QUANTISATION_MODES:
            raise ValueError(f"quantisation_mode must be one of {', '.join(QUANTISATION_MODES)}, "
                             f"got {self.quantisation_mode!r}")
        for name in ("s0_m", "s2_per_m", "z0_m", "incidence_coeff_m", "quantisation_step", "footprint_radius_px",
                     "outlier_rate", "mixed_threshold_sigma"):
            value = float(getattr(self, name))
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
            object.__setattr__(self, name, value)
        for name in ("max_incidence", "grazing_start", "grazing_end"):
            value = float(getattr(self, name))
            if not 0.0 <= value <= math.pi / 2 + 1e-12:
                raise ValueError(f"{name} must be in [0, 90] degrees, got {math.degrees(value):g}")
            object.__setattr__(self, name, value)
        if self.max_incidence >= math.pi / 2:
            raise ValueError("max_incidence must be < 90 degrees")
        if self.grazing_end < self.grazing_start:
            raise ValueError(f"grazing_end ({math.degrees(self.grazing_end):g} deg) must be >= grazing_start "
                             f"({math.degrees(self.grazing_start):g} deg)")
        for name in ("footprint_rays", "matching_window_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))
        if not 0.0 < self.min_return_fraction <= 1.0:
            raise ValueError(f"min_return_fraction must be in (0, 1], got {self.min_return_fraction}")
        if self.outlier_rate > 1:
            raise ValueError(f"outlier_rate must be <= 1, got {self.outlier_rate}")
        spec = tuple((str(m), float(p)) for m, p in dict(self.specular_dropout).items())
        for m, p in spec:
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"specular_dropout[{m}] must be in [0, 1], got {p}")
        object.__setattr__(self, "specular_dropout", spec)

    # -- which terms are active ------------------------------------------------------------------
    @property
    def has_range_noise(self) -> bool:
        return self.enabled and (self.s0_m > 0 or self.s2_per_m > 0 or self.incidence_coeff_m > 0)

    @property
    def correlation_area(self) -> float:
        """Pixels per independent range error: ``matching_window_px²`` (1 for independent errors)."""
        return float(self.matching_window_px**2)

    @property
    def has_quantisation(self) -> bool:
        return self.enabled and self.quantisation_step > 0

    @property
    def has_grazing(self) -> bool:
        return self.enabled and self.grazing_start < math.pi / 2

    @property
    def footprint(self) -> int:
        """Sub-rays actually cast per pixel (1 when the term or the model is off)."""
        return self.footprint_rays if self.enabled else 1

    @property
    def has_specular(self) -> bool:
        return self.enabled and any(p > 0 for _, p in self.specular_dropout)

    @property
    def has_outliers(self) -> bool:
        return self.enabled and self.outlier_rate > 0

    def active_terms(self) -> tuple[str, ...]:
        flags = (self.has_range_noise, self.has_quantisation, self.has_grazing, self.footprint > 1,
                 self.has_specular, self.has_outliers)
        return tuple(t for t, on in zip(TERMS, flags, strict=True) if on)

    def without(self, *terms: str) -> NoiseModel:
        """A copy with the named terms (from ``TERMS``) switched off."""
        unknown = [t for t in terms if t not in TERMS]
        if unknown:
            raise ValueError(f"unknown noise term(s) {', '.join(unknown)} (known: {', '.join(TERMS)})")
        changes: dict = {}
        if "range" in terms:
            changes |= {"s0_m": 0.0, "s2_per_m": 0.0, "incidence_coeff_m": 0.0}
        if "quantisation" in terms:
            changes["quantisation_step"] = 0.0
        if "grazing" in terms:
            changes |= {"grazing_start": math.pi / 2, "grazing_end": math.pi / 2}
        if "footprint" in terms:
            changes["footprint_rays"] = 1
        if "specular" in terms:
            changes["specular_dropout"] = ()
        if "outliers" in terms:
            changes["outlier_rate"] = 0.0
        return replace(self, **changes)

    def scaled(self, k: float) -> NoiseModel:
        """A copy whose range sigma is ``k`` times this one's at every range and incidence (the terms of
        :meth:`sigma` scaled; quantisation, grazing, footprint, dropout and outliers unchanged)."""
        if not (math.isfinite(k) and k > 0):
            raise ValueError(f"noise scale must be a finite number > 0, got {k}")
        return replace(self, s0_m=self.s0_m * k, s2_per_m=self.s2_per_m * k,
                       incidence_coeff_m=self.incidence_coeff_m * k)

    def with_footprint(self, rays: int) -> NoiseModel:
        """A copy casting ``rays`` sub-rays per pixel (1 = off)."""
        return replace(self, footprint_rays=rays)

    def off(self) -> NoiseModel:
        """The same parameters with the master switch off (exact ranges)."""
        return replace(self, enabled=False)

    def specular_probability(self, material: str) -> float:
        return dict(self.specular_dropout).get(material, 0.0)

    # -- the model ---------------------------------------------------------------------------------
    def sigma(self, range_m: np.ndarray, cos_incidence: np.ndarray | float = 1.0,
              ray_z: np.ndarray | float = 1.0) -> np.ndarray:
        """Standard deviation of the range noise along the ray (metres).

        Parameters
        ----------
        range_m : ndarray of any shape, metres along the ray (NaN propagates).
        cos_incidence : cosine of the angle between the ray and the surface normal, broadcastable to
            ``range_m`` (absolute value is used; 1 = head-on).
        ray_z : z component of the unit ray direction in the sensor frame (``kinect_axial`` only: converts
            the axial sigma to the ray; 1 on the optical axis).

        Returns
        -------
        ndarray of the broadcast shape, metres; zeros when range noise is off.
        """
        r = np.asarray(range_m, dtype=np.float64)
        c = np.maximum(np.abs(np.asarray(cos_incidence, dtype=np.float64)), math.cos(self.max_incidence))
        if not self.has_range_noise:
            return np.zeros(np.broadcast_shapes(r.shape, c.shape, np.shape(ray_z)))
        if self.range_model == "ray":
            return (self.s0_m + self.s2_per_m * r * r) / c
        dz = np.asarray(ray_z, dtype=np.float64)
        z = r * dz
        theta = np.arccos(np.minimum(c, 1.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            sigma_z = self.s0_m + self.s2_per_m * (z - self.z0_m) ** 2 \
                + self.incidence_coeff_m / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2
            return sigma_z / dz

    def grazing_probability(self, cos_incidence: np.ndarray) -> np.ndarray:
        """Dropout probability at grazing incidence, same shape as ``cos_incidence`` (0 when off)."""
        c = np.asarray(cos_incidence, dtype=np.float64)
        if not self.has_grazing:
            return np.zeros(c.shape)
        theta = np.arccos(np.minimum(np.abs(c), 1.0))
        if self.grazing_end <= self.grazing_start:
            return (theta >= self.grazing_start).astype(np.float64)
        return np.minimum(np.maximum((theta - self.grazing_start) / (self.grazing_end - self.grazing_start), 0.0), 1.0)

    def quantise(self, range_m: np.ndarray, ray_z: np.ndarray | float = 1.0) -> np.ndarray:
        """Quantised ranges (same shape); unchanged when quantisation is off."""
        r = np.asarray(range_m, dtype=np.float64)
        if not self.has_quantisation:
            return r
        q = self.quantisation_step
        if self.quantisation_mode == "range":
            return np.round(r / q) * q
        dz = np.asarray(ray_z, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = np.round(1.0 / (r * dz) / q) * q
            return 1.0 / inv / dz

    def footprint_offsets(self) -> np.ndarray:
        """Sub-ray offsets in pixels, shape (k, 2): the centre first, then a circle (k = ``footprint``)."""
        k = self.footprint
        if k == 1:
            return np.zeros((1, 2))
        a = 2 * np.pi * np.arange(k - 1) / (k - 1)
        ring = self.footprint_radius_px * np.stack([np.cos(a), np.sin(a)], axis=1)
        return np.concatenate([np.zeros((1, 2)), ring])


__all__ = ["NoiseModel", "RANGE_MODELS", "QUANTISATION_MODES", "TERMS"]
