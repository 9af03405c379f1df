"""``harness describe``: read a real (or saved) range scan and write the core's scene description.

Reads FILE with :func:`sensors.readers.load_scan` (organised PCD, PLY, 16-bit depth PNG, the project's ``.npz``),
runs segmentation and classification (:func:`recognition.describe.describe`) and writes to ``--out``:

- ``description.json``: the source (how the file was read, with ``n_out_of_range``: the returns outside the
  sensor preset's working range ``working_range_m``, left out; more than half of them and the file is refused),
  timings, and every patch with its label, probabilities, plausibilities, fitted parameters and their sigmas,
  invariants (schema ``harness.describe/1``; metres and radians, as inside the core);
- ``table.md``: the paper-style table (region, P(cyl), P(sphere), P(cone), class: the paper's plausibilities)
  plus the class probability vector P(PLAN) ... P(OTH), size and main parameter;
- ``shaded.png`` (cosine-shaded range image), ``regions.png`` (patches coloured by id, numbered with the region
  ids of ``table.md``; black = none) and ``classes.png`` (pixels coloured by their patch's class, with the class
  legend). The colours are the report's (:mod:`reports.colours`: one palette for both).

With ``--model SCENE`` (an a priori scene YAML, world frame), the scan is also localised against the model
(:func:`recognition.localisation.localise`: matching, pose, verification, ICP; a pose prior saved in an ``.npz`` scan
restricts the search) and, when a pose is found, its changes are detected
(:func:`recognition.change.detect_changes`). ``description.json`` then carries ``pose`` (``T_world_sensor``
before and after ICP, covariance, free degrees of freedom, confidence, pairings) and ``change`` (every model
feature's and object's label, displacements, new patches); ``changes.md`` lists them and ``changes.png`` is the
change map over the shaded image.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from collections import Counter
from pathlib import Path

import numpy as np

from evaluation.metrics import MIN_SCORED_PIXELS
from recognition.describe import CLASSIFIERS, DescribeParams, SceneDescription, describe
from reports.colours import CLASS_COLOURS  # the report's palette, the same object (one colour language)
from scenes.model import SceneModel
from scenes.vocabulary import CLASSES
from sensors.config import preset_names
from sensors.io import save_shaded_png
from sensors.readers import FORMATS, LoadedScan, load_scan

NAME = "describe"
HELP = "describe a real range scan (PCD, PLY, depth PNG, .npz): patches, labels, fits -> JSON, Markdown, PNGs"
SCHEMA = "harness.describe/1"

#: Regions of this many pixels or more are numbered in ``regions.png`` (the report's scoring floor).
NUMBERED_MIN_PIXELS = MIN_SCORED_PIXELS


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", type=Path, help=f"range data file ({', '.join(FORMATS)})")
    k = parser.add_mutually_exclusive_group()
    k.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"),
                   help="pinhole intrinsics in pixels (depth PNG; overrides those estimated for an organised PCD)")
    k.add_argument("--intrinsics-file", type=Path, metavar="F",
                   help="YAML (fx fy cx cy, or K) or OpenCV XML (e.g. CAPE's calib_params.xml) with the intrinsics")
    parser.add_argument("--sensor-preset", default="kinect_like", metavar="NAME",
                        help=f"noise model for the core's per-pixel sigma ({', '.join(preset_names())}, or a "
                             "sensor YAML; default kinect_like); ignored for .npz, which carries its own")
    parser.add_argument("--depth-scale", type=float, metavar="S",
                        help="metres per unit (PNG default 0.001, i.e. millimetres; PCD/PLY default 1)")
    parser.add_argument("--origin", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="sensor origin of an unorganised cloud, in the file's frame (default: its origin)")
    parser.add_argument("--view-direction", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="optical axis of an unorganised cloud (default: from the points)")
    parser.add_argument("--classifier", choices=CLASSIFIERS, default="select",
                        help="select (the core's model-selection classifier, default) or paper (the paper's rule)")
    parser.add_argument("--model", type=Path, metavar="SCENE",
                        help="a priori scene YAML: also localise the scan against it and detect its changes")
    parser.add_argument("--out", type=Path, required=True, help="output directory")


def run(args: argparse.Namespace) -> int:
    model = SceneModel.load(args.model) if args.model is not None else None  # a bad YAML fails before any work
    t0 = time.perf_counter()
    loaded = load_scan(args.file, intrinsics=args.intrinsics, intrinsics_file=args.intrinsics_file,
                       sensor_preset=args.sensor_preset, depth_scale=args.depth_scale, origin=args.origin,
                       view_direction=args.view_direction)
    read_s = time.perf_counter() - t0
    desc = describe(loaded.scan, DescribeParams(classifier=args.classifier))
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    doc = description_dict(loaded, desc, args.classifier, read_s)
    located = changes = None
    if model is not None:
        located, changes = localise_and_compare(desc, loaded.scan, model)
        doc["model"] = {"file": str(args.model), "name": model.name, "n_objects": len(model.objects),
                        "n_features": len(model.features)}
        doc["pose"] = pose_dict(located)
        doc["change"] = change_dict(changes) if changes is not None else None
        (out / "changes.md").write_text(change_table(located, changes, model, title=args.file.name), encoding="utf-8")
        if changes is not None:
            from reports.figures import change_picture
            from sensors.io import shaded_image

            (out / "changes.png").write_bytes(change_picture(shaded_image(loaded.scan), changes.label_map,
                                                             f"{args.file.name}: change labels"))
    (out / "description.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    (out / "table.md").write_text(paper_table(desc, title=f"{args.file.name} ({args.classifier} classifier)"),
                                  encoding="utf-8")
    save_shaded_png(out / "shaded.png", loaded.scan)
    save_region_png(out / "regions.png", desc, title=f"{args.file.name}: regions")
    save_class_png(out / "classes.png", desc, title=f"{args.file.name}: classes ({args.classifier} classifier)")
    counts = {c: sum(1 for p in desc.patches if p.label == c) for c in CLASSES}
    info = loaded.info
    left_out = (f" ({info.n_out_of_range} outside {info.noise_preset}'s working range "
                f"{info.working_range_m[0]:g}-{info.working_range_m[1]:g} m left out)"
                if info.n_out_of_range and info.working_range_m else "")
    print(f"{args.file.name}: {loaded.scan.shape[1]}x{loaded.scan.shape[0]}, {info.n_valid} returns{left_out}, "
          f"{len(desc.patches)} patches (" + ", ".join(f"{n} {c}" for c, n in counts.items() if n) + "), "
          f"read {read_s:.2f} s, describe {sum(desc.timing_s.values()):.2f} s -> {out}")
    if located is not None:
        if not located.usable:
            print(f"  pose: not found ({located.reason})")
        else:
            t = located.T_world_sensor[:3, 3]
            given = "" if located.ok else f", conditional on {located.conditional_on} not having moved"
            print(f"  pose: sensor at ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, confidence {located.confidence:.2f}, "
                  f"{located.free_dof} free dof{given}")
        if changes is not None:
            tally = Counter(r.label for r in changes.features.values())
            print("  change: " + ", ".join(f"{n} {lab}" for lab, n in sorted(tally.items())) +
                  f", {len(changes.new_patches)} new region(s)")
    return 0


# ------------------------------------------------------------------------------------------------ with a model


def localise_and_compare(desc: SceneDescription, scan, model: SceneModel):
    """``(PoseResult, ChangeResult or None)``: the scan localised against ``model``, and its changes when a
    pose was found."""
    from recognition.change import detect_changes
    from recognition.localisation import localise

    located = localise(desc, scan, model)
    if not located.usable:
        return located, None
    return located, detect_changes(desc, scan, model, located.T_world_sensor, located.cov_T_world_sensor,
                                   predicted=located.predicted)


def pose_dict(located) -> dict:
    """A :class:`recognition.localisation.PoseResult` as plain data (world frame, metres; covariance over rotation
    vector (rad) and translation (m))."""
    return {
        "ok": bool(located.ok), "reason": located.reason, "conditional_on": located.conditional_on,
        "T_world_sensor": _plain(located.T_world_sensor),
        "T_world_sensor_initial": _plain(located.T_world_sensor_initial),
        "cov_T_world_sensor": _plain(located.cov_T_world_sensor),
        "free_dof": int(located.free_dof), "confidence": _plain(float(located.confidence)),
        "pairings": [{"patch": int(pid), "feature": fid} for pid, fid in located.pairings],
        "n_hypotheses": int(located.n_hypotheses), "time_s": _plain(located.timing_s),
    }


def change_dict(changes) -> dict:
    """A :class:`recognition.change.ChangeResult` as plain data (displacements in metres)."""
    return {
        "features": {fid: {"label": r.label, "displacement_m": _plain(r.displacement_m), "patches": list(r.patches),
                           "found": r.found, "revealed": r.revealed, "occluded": r.occluded, "reason": r.reason}
                     for fid, r in changes.features.items()},
        "objects": dict(changes.objects),
        "new_patches": [int(p) for p in changes.new_patches],
        "time_s": _plain(changes.timing_s),
    }


def change_table(located, changes, model: SceneModel, title: str = "") -> str:
    """Markdown: the pose found (or why none) and every object's and observed feature's change label."""
    lines = [f"# {title}: against the a priori model {model.name!r}", ""]
    if not located.usable:
        return "\n".join(lines + [f"No pose: {located.reason}. No change detection without a pose.", ""])
    t = located.T_world_sensor[:3, 3]
    given = "" if located.ok else (f" Conditional on {located.conditional_on} not having moved (the pose rests on it "
                                   "alone in some direction): every label below holds only if it did not.")
    lines += [f"Pose: sensor at ({t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f}) m, confidence {located.confidence:.2f}, "
              f"{located.free_dof} degrees of freedom unconstrained.{given}", "",
              "| object | label | features (label) |", "|:---|:---|:---|"]
    def verdict(fid: str) -> str:
        r = changes.features[fid]
        moved = f", {1e3 * r.displacement_m:.0f} mm" if r.displacement_m is not None else ""
        return f"{fid} ({r.label}{moved})"

    for obj in model.objects:
        feats = ", ".join(verdict(f.id) for f in obj.features if changes.features[f.id].label != "unobserved")
        lines.append(f"| {obj.id} | {changes.objects[obj.id]} | {feats or '(none observed)'} |")
    lines += ["", f"New regions (patch ids): {', '.join(map(str, changes.new_patches)) or 'none'}", ""]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ outputs


def _plain(value):
    """JSON-safe plain data: arrays to lists, non-finite floats to None."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, bool | int | str) or value is None:
        return value
    return str(value)


def primitive_dict(primitive) -> dict | None:
    """A dedicated fit as plain data: its type and every field (parameters, sigmas, covariance, residuals)."""
    if primitive is None:
        return None
    out = {"type": type(primitive).__name__}
    for f in dataclasses.fields(primitive):
        out[f.name] = _plain(getattr(primitive, f.name))
    return out


def patch_dict(patch, shape: tuple[int, int]) -> dict:
    """One :class:`recognition.describe.ScenePatch` as plain data (sensor frame, metres, radians)."""
    c = patch.classification
    rows, cols = np.unravel_index(patch.pixels, shape)
    return {
        "id": int(patch.id), "label": c.label, "n_pixels": int(patch.n_pixels),
        "surface_type": patch.surface_type.name, "small": bool(patch.small), "noisy": bool(patch.noisy),
        "bbox_rows_cols": [int(rows.min()), int(rows.max()), int(cols.min()), int(cols.max())] if len(rows) else None,
        "centroid_m": _plain(np.mean(patch.points, axis=0)) if len(patch.points) else None,
        "probabilities": _plain(c.probabilities), "plausibilities": _plain(c.plausibilities),
        "invariants": {k: {"value": _plain(float(v[0])), "sigma": _plain(float(v[1]))}
                       for k, v in c.invariants.items()},
        "primitive": primitive_dict(c.primitive), "reason": c.reason,
    }


def description_dict(loaded: LoadedScan, desc: SceneDescription, classifier: str, read_s: float) -> dict:
    """The whole ``description.json`` document."""
    scan = loaded.scan
    sensor = {"kind": scan.sensor.kind, **{f.name: _plain(getattr(scan.sensor, f.name))
                                          for f in dataclasses.fields(scan.sensor)}}
    return {
        "schema": SCHEMA, "source": loaded.info.to_dict(), "sensor": sensor, "classifier": classifier,
        "width": scan.shape[1], "height": scan.shape[0], "n_valid": int(scan.valid.sum()),
        "n_patches": len(desc.patches),
        "labels": {c: sum(1 for p in desc.patches if p.label == c) for c in CLASSES},
        "time_s": {"read": read_s, **{k: float(v) for k, v in desc.timing_s.items()}},
        "patches": [patch_dict(p, scan.shape) for p in desc.patches],
    }


def _main_parameter(patch) -> str:
    inv = patch.classification.invariants
    prim = patch.classification.primitive
    if "radius_m" in inv:
        return f"r = {1e3 * inv['radius_m'][0]:.1f} ± {1e3 * inv['radius_m'][1]:.1f} mm"
    if "major_radius_m" in inv:
        return (f"elbow: bend R = {1e3 * inv['major_radius_m'][0]:.1f} ± {1e3 * inv['major_radius_m'][1]:.1f} mm, "
                f"pipe r = {1e3 * inv['minor_radius_m'][0]:.1f} ± {1e3 * inv['minor_radius_m'][1]:.1f} mm")
    if "half_angle_rad" in inv:
        a, sa = (math.degrees(x) for x in inv["half_angle_rad"])
        return f"half-angle = {a:.1f} ± {sa:.1f} deg"
    if prim is not None and hasattr(prim, "normal"):
        n = np.asarray(prim.normal)
        return f"n = ({n[0]:.3f}, {n[1]:.3f}, {n[2]:.3f})"
    return ""


def paper_table(desc: SceneDescription, title: str = "", min_pixels: int = 0) -> str:
    """The paper's table of plausibilities as Markdown: region, P(cyl), P(sphere), P(cone), class, then the
    class probabilities P(PLAN) ... P(OTH), size and main parameter; one row per patch of at least
    ``min_pixels`` pixels, largest first. Region numbers are those of ``regions.png``."""
    lines = [f"# {title}", ""] if title else []
    lines += ["P(cyl), P(sphere), P(cone): the paper's plausibilities (each in [0, 1], independent); "
              f"P({'), P('.join(CLASSES)}): the classifier's probability vector over the five classes (sums to 1). "
              f"regions.png and classes.png number the regions of {NUMBERED_MIN_PIXELS} pixels or more with these "
              "ids.", "",
              "| region | P(cyl) | P(sphere) | P(cone) | class | " + " | ".join(f"P({c})" for c in CLASSES)
              + " | pixels | parameter |",
              "|---:|---:|---:|---:|:---|" + "---:|" * len(CLASSES) + "---:|:---|"]
    for p in sorted(desc.patches, key=lambda q: -q.n_pixels):
        if p.n_pixels < min_pixels:
            continue
        pl = p.classification.plausibilities
        probs = p.classification.probabilities or {}
        lines.append(f"| {p.id} | {pl.get('CYL', 0.0):.2f} | {pl.get('SPH', 0.0):.2f} | {pl.get('CONE', 0.0):.2f} | "
                     f"{p.label} | " + " | ".join(f"{probs.get(c, 0.0):.2f}" for c in CLASSES)
                     + f" | {p.n_pixels} | {_main_parameter(p)} |")
    return "\n".join(lines) + "\n"


def _numbers(desc: SceneDescription) -> list[tuple[float, float, str]]:
    from reports.figures import patch_centres

    return [(x, y, str(i)) for x, y, i in patch_centres(desc.labels, NUMBERED_MIN_PIXELS)]


def save_class_png(path: Path, desc: SceneDescription, title: str = "classes") -> None:
    """Pixels coloured by their patch's class (the report's :data:`reports.colours.CLASS_COLOURS`), black where
    no patch, with the class legend and the region numbers of ``table.md``."""
    from reports.figures import class_picture

    Path(path).write_bytes(class_picture(desc.class_image(), title, _numbers(desc)))


def save_region_png(path: Path, desc: SceneDescription, title: str = "regions") -> None:
    """Patches coloured by id (black: none), numbered with the region ids of ``table.md`` (regions of
    :data:`NUMBERED_MIN_PIXELS` pixels or more)."""
    from reports.figures import region_picture

    Path(path).write_bytes(region_picture(desc.labels, title, number_min_pixels=NUMBERED_MIN_PIXELS,
                                          key=f"numbers: the region ids of table.md (regions of "
                                              f"{NUMBERED_MIN_PIXELS} pixels or more); black: no region"))


__all__ = ["NAME", "HELP", "add_arguments", "run", "paper_table", "description_dict", "patch_dict",
           "primitive_dict", "save_class_png", "save_region_png", "CLASS_COLOURS",
           "localise_and_compare", "pose_dict", "change_dict", "change_table"]
