"""A small exact pinhole ray caster of analytic surfaces, for the segmentation tests.

Sensor frame: OpenCV (x right, y down, z forward), sensor at the origin. Quadric surfaces (plane, sphere,
cylinder, cone, saddle) are intersected in closed form; the torus by marching plus bisection on its implicit
quartic. Each surface has a clip predicate (finite extent) and an integer id.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: ``height x width`` pixels, focal length ``f`` in pixels, principal point at the centre."""

    height: int = 120
    width: int = 160
    f: float = 150.0

    def rays(self) -> np.ndarray:
        """Unit ray directions (H, W, 3)."""
        v, u = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        d = np.stack(
            [(u - (self.width - 1) / 2) / self.f, (v - (self.height - 1) / 2) / self.f, np.ones(u.shape)], -1
        )
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


def frame(axis) -> np.ndarray:
    """Rotation (3, 3) whose third column is the unit ``axis``."""
    z = np.asarray(axis, float)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


@dataclass(frozen=True)
class Surface:
    """A surface: ``intersect(rays) -> t`` (H, W) with inf where missed, ``id`` for the truth image."""

    intersect: Callable[[np.ndarray], np.ndarray]
    id: int


def _quadric_surface(Al, bl, cl, R, o, clip_local, sid: int) -> Surface:
    """Quadric ``q' Al q + bl' q + cl = 0`` in the local frame ``q = R' (x - o)``, clipped by a predicate."""
    Al, bl, o = np.asarray(Al, float), np.asarray(bl, float), np.asarray(o, float)

    def intersect(d: np.ndarray) -> np.ndarray:
        dl = d @ R  # local directions
        ol = -(R.T @ o)  # sensor origin in local coords
        a = np.einsum("...i,ij,...j->...", dl, Al, dl)
        b = 2 * np.einsum("...i,ij,j->...", dl, Al, ol) + dl @ bl
        c = ol @ Al @ ol + bl @ ol + cl
        best = np.full(d.shape[:-1], np.inf)
        with np.errstate(invalid="ignore", divide="ignore"):
            lin = np.abs(a) < 1e-14
            disc = b * b - 4 * a * c
            sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
            roots = [(-b - sq) / (2 * a), (-b + sq) / (2 * a)]
            roots = [np.where(lin, -c / b, rt) for rt in roots]
        for t in sorted_roots(roots):
            q = ol + t[..., None] * dl
            ok = np.isfinite(t) & (t > 1e-9) & clip_local(q) & ~np.isfinite(best)
            best = np.where(ok, t, best)
        return best

    return Surface(intersect, sid)


def sorted_roots(roots):
    """Both roots of every ray ordered near first (NaN last)."""
    r0, r1 = roots
    lo = np.fmin(r0, r1)
    hi = np.fmax(r0, r1)
    # a negative near root: the far one may still be valid
    return [lo, hi]


def plane(point, normal, sid: int, half_extent: float | None = None) -> Surface:
    R = frame(normal)
    clip = (lambda q: np.ones(q.shape[:-1], bool)) if half_extent is None else (
        lambda q: (np.abs(q[..., 0]) <= half_extent) & (np.abs(q[..., 1]) <= half_extent))
    return _quadric_surface(np.zeros((3, 3)), [0, 0, 1.0], 0.0, R, point, clip, sid)


def sphere(centre, radius: float, sid: int) -> Surface:
    return _quadric_surface(np.eye(3), np.zeros(3), -radius**2, np.eye(3), centre,
                            lambda q: np.ones(q.shape[:-1], bool), sid)


def cylinder(centre, axis, radius: float, length: float, sid: int) -> Surface:
    return _quadric_surface(np.diag([1.0, 1.0, 0.0]), np.zeros(3), -radius**2, frame(axis), centre,
                            lambda q: np.abs(q[..., 2]) <= length / 2, sid)


def cone(apex, axis, half_angle: float, z0: float, z1: float, sid: int) -> Surface:
    t2 = np.tan(half_angle) ** 2
    return _quadric_surface(np.diag([1.0, 1.0, -t2]), np.zeros(3), 0.0, frame(axis), apex,
                            lambda q: (q[..., 2] >= z0) & (q[..., 2] <= z1), sid)


def saddle(origin, axis, a: float, half: float, sid: int) -> Surface:
    """``z = a (x² - y²)`` in a local frame whose z is ``axis``, clipped to ``|x|, |y| <= half``."""
    return _quadric_surface(np.diag([a, -a, 0.0]), [0, 0, -1.0], 0.0, frame(axis), origin,
                            lambda q: (np.abs(q[..., 0]) <= half) & (np.abs(q[..., 1]) <= half), sid)


def torus(centre, axis, R_major: float, a_minor: float, sid: int, steps: int = 600) -> Surface:
    Rm = frame(axis)
    o = np.asarray(centre, float)

    def f(q):
        s = np.sum(q * q, axis=-1)
        return (s + R_major**2 - a_minor**2) ** 2 - 4 * R_major**2 * (q[..., 0] ** 2 + q[..., 1] ** 2)

    def intersect(d):
        shape = d.shape[:-1]
        dl = (d @ Rm).reshape(-1, 3)
        ol = -(Rm.T @ o)
        rb = R_major + a_minor
        b = dl @ ol
        disc = b * b - (ol @ ol - rb**2)
        out = np.full(dl.shape[0], np.inf)
        hit = np.flatnonzero(disc > 0)
        if hit.size == 0:
            return out.reshape(shape)
        t0 = -b[hit] - np.sqrt(disc[hit])
        t1 = -b[hit] + np.sqrt(disc[hit])
        ts = t0[:, None] + (t1 - t0)[:, None] * np.linspace(0, 1, steps)[None, :]
        vals = f(ol + ts[..., None] * dl[hit][:, None, :])
        neg = vals < 0
        has = neg.any(axis=1)
        first = np.argmax(neg, axis=1)
        rows = np.flatnonzero(has & (first > 0))
        lo = ts[rows, first[rows] - 1]
        hi = ts[rows, first[rows]]
        dd = dl[hit][rows]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            inside = f(ol + mid[:, None] * dd) < 0
            hi = np.where(inside, mid, hi)
            lo = np.where(inside, lo, mid)
        out[hit[rows]] = 0.5 * (lo + hi)
        return out.reshape(shape)

    return Surface(intersect, sid)


def render(surfaces: list[Surface], camera: Camera = Camera(), sigma: float = 0.0,
           rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray cast a scene.

    Returns
    -------
    points : ndarray of shape (H, W, 3), metres, NaN where no hit
    sigma_img : ndarray of shape (H, W), metres (the given sigma where hit, NaN elsewhere)
    ids : ndarray of shape (H, W), int, -1 where no hit
    """
    d = camera.rays()
    best = np.full(d.shape[:-1], np.inf)
    ids = np.full(d.shape[:-1], -1, dtype=np.int64)
    for s in surfaces:
        t = s.intersect(d)
        closer = t < best
        best = np.where(closer, t, best)
        ids = np.where(closer, s.id, ids)
    hit = np.isfinite(best)
    r = np.where(hit, best, np.nan)
    if sigma > 0:
        rng = np.random.default_rng(0) if rng is None else rng
        r = r + sigma * rng.standard_normal(r.shape)
    points = r[..., None] * d
    sig = np.where(hit, sigma, np.nan)
    return points, sig, ids
