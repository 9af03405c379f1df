"""Synthetic one-sided noisy patches of planes, cylinders, spheres, cones and tori (tests, benchmarks).

A patch is what a range sensor at the origin (looking along +z) would see of one surface: points on the
side facing the sensor, sampled with the density of an image grid of a given angular pixel size (pixels per
area ~ cos(incidence) / (range * pixel_angle)²), dropouts at grazing incidence, and Gaussian noise *along
the ray* with a sigma that grows with range and, mildly, with 1/cos(incidence). Ground truth parameters
travel in :class:`SyntheticPatch`. This module is test support, not part of the recognition core's inputs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "NoisePreset", "PRESETS", "SyntheticPatch", "sample_patch", "KINDS", "TRUE_CLASS", "random_rotation",
]

KINDS = ("plane", "cylinder", "sphere", "cone", "torus")
TRUE_CLASS = {"plane": "PLAN", "cylinder": "CYL", "sphere": "SPH", "cone": "CONE", "torus": "OTH"}


@dataclass(frozen=True)
class NoisePreset:
    """Sensor noise and scene scale of a benchmark level.

    Attributes
    ----------
    name : str
    range_m : (float, float)
        Range of the patch centre from the sensor, metres.
    radius_m : (float, float)
        Pipe radius range, metres (spheres: 1-3x, planes: half-sizes 2-6x).
    pixel_rad : float
        Angular pixel size, radians.
    model : str
        ``"quadratic"``: sigma = s0 (range / r0)²; ``"linear"``: sigma = s0 range / r0; ``"kinect"``:
        Nguyen's axial sigma 0.0012 + 0.0019 (z - 0.4)² converted to the ray.
    s0, r0 : float
        Sigma (m) at the reference range r0 (m).
    """

    name: str
    range_m: tuple[float, float]
    radius_m: tuple[float, float]
    pixel_rad: float
    model: str
    s0: float = 0.0
    r0: float = 1.0

    def sigma(self, ranges: np.ndarray, z: np.ndarray, cos_inc: np.ndarray) -> np.ndarray:
        """Sigma along the ray (N,) in metres for ranges (N,), depths z (N,) and incidence cosines (N,)."""
        if self.model == "quadratic":
            s = self.s0 * (ranges / self.r0) ** 2
        elif self.model == "linear":
            s = self.s0 * ranges / self.r0
        else:
            s = (0.0012 + 0.0019 * (z - 0.4) ** 2) * ranges / z
        return s * (1.0 + 0.5 * (1.0 / np.maximum(cos_inc, 0.15) - 1.0))


PRESETS: dict[str, NoisePreset] = {
    "mockup_laser": NoisePreset("mockup_laser", (0.5, 1.5), (0.02, 0.10), 1.0e-3, "quadratic", 2e-4, 1.0),
    "factory_scanner": NoisePreset(
        "factory_scanner", (2.0, 8.0), (0.05, 0.50), 1.5e-3, "linear", 1.5e-3, 5.0
    ),
    "kinect_like": NoisePreset("kinect_like", (0.6, 4.0), (0.03, 0.30), 1.6e-3, "kinect"),
}


@dataclass(frozen=True)
class SyntheticPatch:
    """A noisy one-sided patch and its truth.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    points : ndarray of shape (N, 3), metres (sensor frame, sensor at the origin)
    sigma : ndarray of shape (N,), metres, the true sigma along the ray
    normals : ndarray of shape (N, 3), true unit normals (facing the sensor)
    truth : dict
        Kind-specific parameters: ``normal``, ``offset`` (plane); ``centre``, ``axis``, ``radius``
        (cylinder, ``centre`` on the axis); ``centre``, ``radius`` (sphere); ``apex``, ``axis``,
        ``half_angle`` (cone, axis from the apex into the surface); ``centre``, ``axis``, ``major``,
        ``minor`` (torus).
    """

    kind: str
    points: np.ndarray
    sigma: np.ndarray
    normals: np.ndarray
    truth: dict = field(default_factory=dict)

    @property
    def true_class(self) -> str:
        return TRUE_CLASS[self.kind]


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation matrix (3, 3)."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _frame_with_axis(axis: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) whose third column is ``axis``."""
    a = axis / np.linalg.norm(axis)
    t = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(a, t)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(a, u), a], axis=1)


def _axis_across_view(rng: np.random.Generator, view: np.ndarray, min_angle: float) -> np.ndarray:
    while True:
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        if abs(a @ view) <= np.cos(min_angle):
            return a


def _local_shape(kind: str, rng: np.random.Generator, preset: NoisePreset, n: int):
    """Candidate points, normals, area per sample and truth in a local frame (axis z, centre at 0)."""
    r = rng.uniform(*preset.radius_m)
    if kind == "plane":
        hx, hy = r * rng.uniform(2, 6), r * rng.uniform(2, 6)
        p = np.stack([rng.uniform(-hx, hx, n), rng.uniform(-hy, hy, n), np.zeros(n)], axis=1)
        nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
        return p, nrm, 4 * hx * hy / n, {}
    if kind == "cylinder":
        length = r * rng.uniform(2, 8)
        th, h = rng.uniform(0, 2 * np.pi, n), rng.uniform(-length / 2, length / 2, n)
        nrm = np.stack([np.cos(th), np.sin(th), np.zeros(n)], axis=1)
        p = nrm * r
        p[:, 2] = h
        return p, nrm, 2 * np.pi * r * length / n, {"radius": r, "length": length}
    if kind == "sphere":
        R = r * rng.uniform(1, 3)
        v = rng.normal(size=(n, 3))
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        return v * R, v, 4 * np.pi * R * R / n, {"radius": R}
    if kind == "cone":
        alpha = np.radians(rng.uniform(5, 40))
        ta = np.tan(alpha)
        length = r * rng.uniform(1.5, 5)
        r_small = max(r - length * ta, 0.3 * r)
        h0, h1 = r_small / ta, r / ta
        h = np.sqrt(rng.uniform(h0**2, h1**2, n))
        th = rng.uniform(0, 2 * np.pi, n)
        ca, sa = np.cos(alpha), np.sin(alpha)
        p = np.stack([h * ta * np.cos(th), h * ta * np.sin(th), h], axis=1)
        nrm = np.stack([ca * np.cos(th), ca * np.sin(th), -sa * np.ones(n)], axis=1)
        area = np.pi * (h1**2 - h0**2) * ta / ca
        return p, nrm, area / n, {"half_angle": alpha, "h0": h0, "h1": h1}
    if kind == "torus":
        R = r * rng.uniform(1.5, 3)
        sweep = np.radians(rng.uniform(60, 90))
        m = 3 * n
        phi, psi = rng.uniform(0, sweep, m), rng.uniform(0, 2 * np.pi, m)
        keep = rng.uniform(0, R + r, m) < R + r * np.cos(psi)
        phi, psi = phi[keep][:n], psi[keep][:n]
        radial = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)], axis=1)
        nrm = radial * np.cos(psi)[:, None]
        nrm[:, 2] = np.sin(psi)
        p = radial * R + nrm * r
        area = 2 * np.pi * r * R * sweep
        return p, nrm, area / len(p), {"major": R, "minor": r}
    raise ValueError(f"unknown kind {kind!r}, expected one of {KINDS}")


def sample_patch(
    kind: str,
    rng: np.random.Generator,
    preset: str | NoisePreset = "mockup_laser",
    *,
    n_max: int = 5000,
    n_min: int = 200,
    noise_scale: float = 1.0,
    n_candidates: int = 40000,
) -> SyntheticPatch:
    """Sample a one-sided noisy patch of a primitive in a random pose and size.

    Parameters
    ----------
    kind : {"plane", "cylinder", "sphere", "cone", "torus"}
    rng : numpy.random.Generator
    preset : str or NoisePreset
        Noise level and scene scale (see :data:`PRESETS`).
    n_max, n_min : int
        The pixel count implied by the pixel size is clipped to ``[n_min, n_max]`` (poses whose patch has
        fewer than ``n_min / 2`` pixels are redrawn).
    noise_scale : float
        Multiplies the preset sigma (0 gives noise-free points with the nominal sigma).
    n_candidates : int
        Dense surface samples drawn before the pixel-density selection.

    Returns
    -------
    SyntheticPatch
    """
    ps = PRESETS[preset] if isinstance(preset, str) else preset
    for _ in range(200):
        p_loc, n_loc, dA, truth = _local_shape(kind, rng, ps, n_candidates)
        rng_c = rng.uniform(*ps.range_m)
        view = rng.normal(size=3) * np.array([0.3, 0.3, 0.0]) + np.array([0.0, 0.0, 1.0])
        view /= np.linalg.norm(view)
        centre = view * rng_c
        if kind in ("plane",):
            while True:
                nz = random_rotation(rng)[:, 2]
                if nz @ -view > np.cos(np.radians(65)):
                    break
            Rm = _frame_with_axis(nz)
        elif kind in ("sphere", "torus"):
            Rm = random_rotation(rng)
        else:
            Rm = _frame_with_axis(_axis_across_view(rng, view, np.radians(35)))
        shift = np.zeros(3)
        if kind == "cone":
            shift = np.array([0.0, 0.0, 0.5 * (truth["h0"] + truth["h1"])])
        if kind == "torus":
            shift = np.array([truth["major"] * np.cos(0.7), truth["major"] * np.sin(0.7), 0.0])
        pts = (p_loc - shift) @ Rm.T + centre
        nrm = n_loc @ Rm.T
        rngs = np.linalg.norm(pts, axis=1)
        u = pts / rngs[:, None]
        cos_inc = -np.einsum("ij,ij->i", nrm, u)
        # in front of the sensor and inside a 60 x 60 degree field of view, not at grazing incidence
        half_fov = 0.577 * pts[:, 2]
        in_fov = (pts[:, 2] > 0.1) & (np.abs(pts[:, 0]) < half_fov) & (np.abs(pts[:, 1]) < half_fov)
        vis = (cos_inc > 0.15) & in_fov
        if kind == "sphere" and np.any(vis):
            # a cap (tank end): keep points within a random polar angle of a direction facing the sensor
            pole = -view + rng.normal(size=3) * 0.4
            pole /= np.linalg.norm(pole)
            cap = np.radians(rng.uniform(40, 90))
            vis &= nrm @ pole > np.cos(cap)
        if not np.any(vis):
            continue
        w = cos_inc[vis] / (rngs[vis] * ps.pixel_rad) ** 2 * dA
        n_pix = float(w.sum())
        if n_pix < 0.5 * n_min:
            continue
        n = int(np.clip(n_pix, n_min, min(n_max, np.count_nonzero(vis))))
        idx_vis = np.flatnonzero(vis)
        pick = rng.choice(len(idx_vis), size=n, replace=False, p=w / w.sum())
        idx = idx_vis[pick]
        x, nn, uu = pts[idx], nrm[idx], u[idx]
        sig = ps.sigma(rngs[idx], x[:, 2], cos_inc[idx])
        noisy = x + (noise_scale * sig * rng.normal(size=n))[:, None] * uu
        a = Rm[:, 2]
        c_true = centre - shift @ Rm.T  # local origin in the sensor frame
        if kind == "plane":
            tr = {"normal": a, "offset": float(a @ centre)}
        elif kind == "cylinder":
            tr = {"centre": c_true, "axis": a, "radius": truth["radius"], "length": truth["length"]}
        elif kind == "sphere":
            tr = {"centre": c_true, "radius": truth["radius"]}
        elif kind == "cone":
            tr = {"apex": c_true, "axis": a, "half_angle": truth["half_angle"],
                  "length": truth["h1"] - truth["h0"]}
        else:
            tr = {"centre": c_true, "axis": a, "major": truth["major"], "minor": truth["minor"]}
        return SyntheticPatch(kind=kind, points=noisy, sigma=sig, normals=nn, truth=tr)
    raise RuntimeError(f"could not place a visible {kind} patch for preset {ps.name}")
