"""``harness describe``: read a real (or saved) range scan and write the core's scene description.

Reads FILE with :func:`sensors.readers.load_scan` (organised PCD, PLY, 16-bit depth PNG, the project's ``.npz``),
runs segmentation and classification (:func:`recognition.describe.describe`) and writes to ``--out``:

- ``description.json``: the source (how the file was read), timings, and every patch with its label,
  probabilities, plausibilities, fitted parameters and their sigmas, invariants (schema
  ``harness.describe/1``; metres and radians, as inside the core);
- ``table.md``: the paper-style table (region, P(cyl), P(sphere), P(cone), class) plus size and main parameter;
- ``shaded.png`` (cosine-shaded range image), ``regions.png`` (patches coloured by id, black = none) and
  ``classes.png`` (pixels coloured by their patch's class).

``--model`` (matching, pose and change detection against an a priori model) comes once those stages exist.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from recognition.classify import CLASSES
from recognition.describe import CLASSIFIERS, DescribeParams, SceneDescription, describe
from sensors.config import preset_names
from sensors.io import save_labels_png, save_shaded_png
from sensors.readers import FORMATS, LoadedScan, load_scan

NAME = "describe"
HELP = "describe a real range scan (PCD, PLY, depth PNG, .npz): patches, labels, fits -> JSON, Markdown, PNGs"
SCHEMA = "harness.describe/1"

#: class colours of ``classes.png`` (RGB in [0, 1]).
CLASS_COLOURS = {"PLAN": (0.55, 0.55, 0.55), "CYL": (0.12, 0.47, 0.71), "SPH": (0.84, 0.15, 0.16),
                 "CONE": (1.0, 0.5, 0.05), "OTH": (0.58, 0.4, 0.74)}


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
                        help="a priori model for matching, pose and change detection (not built yet)")
    parser.add_argument("--out", type=Path, required=True, help="output directory")


def run(args: argparse.Namespace) -> int:
    if args.model is not None:
        raise ValueError("--model is not built yet: matching, pose and change detection against an a priori model "
                         "come in a later issue (DESIGN 10.12); run without --model for the scene description")
    t0 = time.perf_counter()
    loaded = load_scan(args.file, intrinsics=args.intrinsics, intrinsics_file=args.intrinsics_file,
                       sensor_preset=args.sensor_preset, depth_scale=args.depth_scale, origin=args.origin,
                       view_direction=args.view_direction)
    read_s = time.perf_counter() - t0
    desc = describe(loaded.scan, DescribeParams(classifier=args.classifier))
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    doc = description_dict(loaded, desc, args.classifier, read_s)
    (out / "description.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    (out / "table.md").write_text(paper_table(desc, title=f"{args.file.name} ({args.classifier} classifier)"),
                                  encoding="utf-8")
    save_shaded_png(out / "shaded.png", loaded.scan)
    save_labels_png(out / "regions.png", desc.labels)
    save_class_png(out / "classes.png", desc)
    counts = {c: sum(1 for p in desc.patches if p.label == c) for c in CLASSES}
    print(f"{args.file.name}: {loaded.scan.shape[1]}x{loaded.scan.shape[0]}, {loaded.info.n_valid} returns, "
          f"{len(desc.patches)} patches (" + ", ".join(f"{n} {c}" for c, n in counts.items() if n) + "), "
          f"read {read_s:.2f} s, describe {sum(desc.timing_s.values()):.2f} s -> {out}")
    return 0


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
    if "half_angle_rad" in inv:
        a, sa = (math.degrees(x) for x in inv["half_angle_rad"])
        return f"half-angle = {a:.1f} ± {sa:.1f} deg"
    if prim is not None and hasattr(prim, "normal"):
        n = np.asarray(prim.normal)
        return f"n = ({n[0]:.3f}, {n[1]:.3f}, {n[2]:.3f})"
    return ""


def paper_table(desc: SceneDescription, title: str = "", min_pixels: int = 0) -> str:
    """The paper's table of plausibilities as Markdown: region, P(cyl), P(sphere), P(cone), class (and size,
    main parameter), one row per patch of at least ``min_pixels`` pixels, largest first."""
    lines = [f"# {title}", ""] if title else []
    lines += ["| region | P(cyl) | P(sphere) | P(cone) | class | pixels | parameter |",
              "|---:|---:|---:|---:|:---|---:|:---|"]
    for p in sorted(desc.patches, key=lambda q: -q.n_pixels):
        if p.n_pixels < min_pixels:
            continue
        pl = p.classification.plausibilities
        lines.append(f"| {p.id} | {pl.get('CYL', 0.0):.2f} | {pl.get('SPH', 0.0):.2f} | {pl.get('CONE', 0.0):.2f} | "
                     f"{p.label} | {p.n_pixels} | {_main_parameter(p)} |")
    return "\n".join(lines) + "\n"


def save_class_png(path: Path, desc: SceneDescription) -> None:
    """Pixels coloured by their patch's class (:data:`CLASS_COLOURS`), black where no patch."""
    from matplotlib.image import imsave

    cls = desc.class_image()
    table = np.array([CLASS_COLOURS[c] for c in CLASSES])
    rgb = np.zeros((*cls.shape, 3))
    rgb[cls >= 0] = table[cls[cls >= 0]]
    imsave(path, rgb)


__all__ = ["NAME", "HELP", "add_arguments", "run", "paper_table", "description_dict", "patch_dict",
           "primitive_dict", "save_class_png"]
