"""The scene of one trial in 3D, as a static matplotlib figure: the a priori model (wireframe) against the actual
scene (coloured by each feature's change label), the points the sensor measured, and the sensor's pose and
field of view (true, and as estimated before and after ICP).

Wireframes are drawn from each feature's own parameters (:mod:`scenes.features`): a plane's rectangle, a
cylinder's end circles and four generators, a cone's, a sphere's (or cap's) three great circles, a torus
section's spine and end circles. Deterministic: no random draw, points subsampled by a fixed stride.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import matplotlib
import numpy as np
from matplotlib.lines import Line2D

from reports.colours import CHANGE_COLOURS, METHOD_COLOURS, rgb, shade_variant
from reports.figures import WIDE_IN, new_figure, to_png
from scenes.features import Cone, Cylinder, Feature, Plane, Sphere, Torus
from scenes.geometry import frame_from_z

#: Lines and points outside a 3D view's limits are clipped (matplotlib >= 3.10; drawn whole before).
CLIP: dict[str, bool] = {"axlim_clip": True} if tuple(int(x) for x in matplotlib.__version__.split(".")[:2]) >= (
    3, 10) else {}
APRIORI_COLOUR = "#9ca3af"
TRUE_SENSOR = "#111827"
UNCHANGED_LINE = "#6b7280"  # the unchanged grey of the change palette, darkened to read as a line


def _circle(centre: np.ndarray, axis: np.ndarray, radius: float, n: int = 32) -> np.ndarray:
    R = frame_from_z(np.asarray(axis, dtype=float))
    t = np.linspace(0, 2 * np.pi, n + 1)
    return centre + radius * (np.cos(t)[:, None] * R[:, 0] + np.sin(t)[:, None] * R[:, 1])


def feature_wireframe(feature: Feature, n: int = 32) -> list[np.ndarray]:
    """Polylines (each an ndarray of shape (N, 3), world frame, metres) that outline ``feature``."""
    if isinstance(feature, Plane):
        c = feature.corners()
        return [np.vstack([c, c[:1]])]
    if isinstance(feature, Cylinder | Cone):
        if isinstance(feature, Cylinder):
            ends = feature.endpoints()
            radii = (feature.radius, feature.radius)
            axis = feature.axis
        else:
            axis = feature.axis
            ends = feature.apex + np.outer([feature.start, feature.end], axis)
            radii = tuple(float(feature.radius_at(d)) for d in (feature.start, feature.end))
        lines = [_circle(e, axis, r, n) for e, r in zip(ends, radii, strict=True)]
        R = frame_from_z(axis)
        for k in range(4):
            d = np.cos(k * np.pi / 2) * R[:, 0] + np.sin(k * np.pi / 2) * R[:, 1]
            lines.append(np.vstack([ends[0] + radii[0] * d, ends[1] + radii[1] * d]))
        return lines
    if isinstance(feature, Sphere):
        lines = [_circle(feature.centre, a, feature.radius, n) for a in np.eye(3)]
        if feature.cap_axis is not None:
            keep_from = feature.radius - feature.cap_height
            lines = [np.where(((ln - feature.centre) @ feature.cap_axis >= keep_from - 1e-9)[:, None], ln, np.nan)
                     for ln in lines]
        return lines
    if isinstance(feature, Torus):
        t = np.linspace(0, feature.sweep, n)
        spine, tangent = feature.spine(t)
        radial = spine - feature.centre
        radial /= np.linalg.norm(radial, axis=1, keepdims=True)
        r = feature.minor_radius
        lines = [spine + s * r * d for d in (radial, np.broadcast_to(feature.axis, radial.shape)) for s in (-1, 1)]
        for i in (0, len(t) - 1):
            lines.append(_circle(spine[i], tangent[i], r, n))
        return lines
    return []


def frustum_lines(T_world_sensor: np.ndarray, corner_rays: np.ndarray, depth_m: float) -> list[np.ndarray]:
    """The sensor's field of view as polylines: four edges from the origin to ``depth_m`` along the corner
    rays (shape (4, 3), sensor frame, in order around the image) and the far rectangle."""
    T = np.asarray(T_world_sensor, dtype=float)
    o = T[:3, 3]
    far = o + depth_m * (np.asarray(corner_rays, dtype=float) @ T[:3, :3].T)
    return [np.vstack([o, f]) for f in far] + [np.vstack([far, far[:1]])]


def corner_rays(ray_directions: np.ndarray) -> np.ndarray:
    """The unit rays of the four corner pixels of a ray image (H, W, 3), in order around the image."""
    d = np.asarray(ray_directions)
    return np.stack([d[0, 0], d[0, -1], d[-1, -1], d[-1, 0]])


def _box(points: np.ndarray, margin: float = 0.08) -> tuple[np.ndarray, np.ndarray]:
    """Centre and half-sizes (each at least 5 cm) of the bounding box of ``points`` (N, 3), with a margin."""
    p = np.asarray(points, dtype=float)
    p = p[np.all(np.isfinite(p), axis=1)]
    if not len(p):
        return np.zeros(3), np.full(3, 0.5)
    lo, hi = p.min(axis=0), p.max(axis=0)
    half = np.maximum((hi - lo) / 2 * (1 + margin), 0.05)
    return (lo + hi) / 2, half


def _inside(T: np.ndarray | None, centre: np.ndarray, half: np.ndarray, slack: float = 1.5) -> bool:
    return T is not None and bool(np.all(np.abs(np.asarray(T)[:3, 3] - centre) <= slack * half))


#: (pose key, colour, line style, width, legend): the true pose wide and solid, so that an estimate drawn over it
#: (thin, dashed or dotted) leaves it visible where they agree.
SENSORS = (("true", TRUE_SENSOR, "-", 2.6, "true pose"),
           ("initial", METHOD_COLOURS["core"], ":", 1.1, "estimated before ICP"),
           ("estimated", METHOD_COLOURS["core"], "--", 1.1, "estimated after ICP"))


def scene_figure(apriori: Sequence[Feature], actual: Sequence[Feature], labels: Mapping[str, str],
                 poses: Mapping[str, np.ndarray | None], rays: np.ndarray, depth_m: float,
                 points_world: np.ndarray | None = None, title: str = "") -> bytes:
    """The trial's scene in 3D, in two views: a close-up of what the sensor saw, from behind it, and the whole
    scene from above.

    Parameters
    ----------
    apriori, actual : the features of the a priori model and of the actual (perturbed) scene, world frame.
    labels : feature id -> its truth change label (``unchanged``, ``moved``, ``missing``, ``altered``,
        ``new``); the actual scene's features are drawn in their label's colour, the a priori model grey
        dashed, and a missing feature (a priori only) red dashed.
    poses : ``"true"``, ``"estimated"`` (after ICP) and ``"initial"`` (before ICP) -> ``T_world_sensor``
        (4, 4) or None (not drawn). An estimate far outside a view is left out of it (the legend says so).
    rays : ndarray of shape (4, 3), the corner rays of the sensor (:func:`corner_rays`).
    depth_m : how far the field of view is drawn (e.g. the trial's median range).
    points_world : optional ndarray of shape (N, 3), the measured points in the world frame (true pose).
    """
    fig = new_figure(WIDE_IN, 6.6)
    true_T = poses.get("true")
    scene_lines = [ln for f in (*apriori, *actual) for ln in feature_wireframe(f)]
    scene_pts = np.vstack(scene_lines) if scene_lines else np.zeros((1, 3))
    pts = None
    if points_world is not None and len(points_world):
        pts = np.asarray(points_world, dtype=float)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        pts = pts[:: max(len(pts) // 6000, 1)]
    near = [pts] if pts is not None and len(pts) else [scene_pts]
    if true_T is not None:
        near += frustum_lines(true_T, rays, min(depth_m, 0.25 * depth_m + 0.5))
    views = [("close-up of what the sensor saw, from behind it", _box(np.vstack(near), 0.15), False),
             ("the whole scene, from above", _box(np.vstack([scene_pts, *([] if true_T is None else
                                                                            [np.asarray(true_T)[None, :3, 3]])]),
                                                  0.05), True)]
    unchanged = shade_variant(rgb(CHANGE_COLOURS["unchanged"]), 2)
    left_out: set[str] = set()
    for k, (name, (centre, half), top) in enumerate(views):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        for f in apriori:
            missing = labels.get(f.id) == "missing"
            for ln in feature_wireframe(f):
                ax.plot(*ln.T, ls="--", lw=1.3 if missing else 0.7, **CLIP,
                        color=CHANGE_COLOURS["missing"] if missing else APRIORI_COLOUR)
        for f in actual:
            lab = labels.get(f.id, "unchanged")
            colour = unchanged if lab == "unchanged" else rgb(CHANGE_COLOURS.get(lab, UNCHANGED_LINE))
            for ln in feature_wireframe(f):
                ax.plot(*ln.T, lw=1.0 if lab == "unchanged" else 1.6, color=colour, **CLIP)
        if pts is not None and len(pts):
            ax.scatter(*pts.T, s=0.5 if not top else 0.3, color="#111827", alpha=0.3, depthshade=False,
                       linewidths=0, **CLIP)
        for key, colour, ls, lw, _label in SENSORS:
            T = poses.get(key)
            if T is None:
                continue
            if key != "true" and not _inside(T, centre, half):
                left_out.add(key)
                continue
            for ln in frustum_lines(T, rays, depth_m):
                ax.plot(*ln.T, ls=ls, lw=lw, color=colour, **CLIP)
            o, z = np.asarray(T)[:3, 3], np.asarray(T)[:3, 2]
            ax.scatter(*o, s=30 if key == "true" else 12, color=colour, depthshade=False)
            ax.plot(*np.vstack([o, o + 0.25 * depth_m * z]).T, lw=lw + 0.8, color=colour, ls=ls, **CLIP)
        ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
        ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
        ax.set_zlim(centre[2] - half[2], centre[2] + half[2])
        ax.set_box_aspect(tuple(half))
        if top:
            ax.view_init(elev=90, azim=-90)
            ax.set_zticks([])
        elif true_T is not None:
            back = -np.asarray(true_T)[:3, 2]
            ax.view_init(elev=25, azim=float(np.degrees(np.arctan2(back[1], back[0]))))
        ax.set_xlabel("x (m)", fontsize=8)
        ax.set_ylabel("y (m)", fontsize=8)
        if not top:
            ax.set_zlabel("z (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(name, fontsize=10)
    handles = [Line2D([], [], color=APRIORI_COLOUR, ls="--", label="a priori model"),
               Line2D([], [], color=unchanged, label="actual: unchanged")]
    present = {labels.get(f.id) for f in (*apriori, *actual)}
    handles += [Line2D([], [], color=CHANGE_COLOURS[lab], lw=1.6, ls="--" if lab == "missing" else "-",
                       label=f"{'a priori' if lab == 'missing' else 'actual'}: {lab}")
                for lab in ("moved", "missing", "altered", "new") if lab in present]
    if pts is not None:
        handles.append(Line2D([], [], ls="", marker=".", color="#111827", label="measured points"))
    handles += [Line2D([], [], color=c, ls=ls, lw=lw, label=f"sensor, {label}"
                       + (" (outside a view: not drawn there)" if key in left_out else ""))
                for key, c, ls, lw, label in SENSORS if poses.get(key) is not None]
    fig.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 5), fontsize=8.5, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    return to_png(fig)


def scene_labels(apriori: Sequence[Feature], actual: Sequence[Feature], label_of: Any) -> dict[str, str]:
    """feature id -> change label for every feature of both models (``label_of(id)``; unknown ids: unchanged)."""
    out = {}
    for f in (*apriori, *actual):
        try:
            out[f.id] = str(label_of(f.id))
        except KeyError:
            out[f.id] = "unchanged"
    return out
