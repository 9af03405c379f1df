"""Saving and loading scans: ``.npz`` (exact round trip), PLY point clouds, PNG pictures.

The ``.npz`` holds the scan's arrays, the truth's arrays when given, and a JSON ``meta`` string with
the sensor model, noise model and truth surface table in their exact plain-data form (floats written
with ``repr``, so loading gives back bit-identical parameters).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from scenes.mjcf import Surface
from sensors.config import noise_from_dict, noise_to_dict, sensor_model_from_dict, sensor_model_to_dict
from sensors.range_image import RangeImage, Scan, ScanTruth

NPZ_SCHEMA = "scan/1"
_TRUTH_ARRAYS = ("T_world_sensor", "sigma", "surface_id", "normals", "true_range", "flags")


def save_npz(path: str | Path, scan: Scan, truth: ScanTruth | None = None, compress: bool = False) -> None:
    """Write ``scan`` (and ``truth``) to ``path`` (``.npz``); see :func:`load_npz`."""
    meta = {"schema": NPZ_SCHEMA, "sensor": sensor_model_to_dict(scan.sensor), "noise": noise_to_dict(scan.noise),
            "has_truth": truth is not None, "has_pose_prior": scan.pose_prior is not None}
    arrays: dict[str, np.ndarray] = {"range": scan.range, "points": scan.points}
    if scan.pose_prior is not None:
        arrays["pose_prior"] = scan.pose_prior
    if truth is not None:
        meta["surfaces"] = [[s.index, s.feature_id, s.part, s.truth_class] for s in truth.surfaces]
        arrays |= {f"truth_{k}": getattr(truth, k) for k in _TRUTH_ARRAYS}
    arrays["meta"] = np.array(json.dumps(meta))
    with open(path, "wb") as fh:
        (np.savez_compressed if compress else np.savez)(fh, **arrays)


def load_npz(path: str | Path) -> RangeImage:
    """Read a scan saved by :func:`save_npz`; ``RangeImage.truth`` is None when it was saved without truth.

    Raises
    ------
    ValueError : not a scan file of a known schema.
    """
    with np.load(path, allow_pickle=False) as z:
        if "meta" not in z.files:
            raise ValueError(f"{path}: not a scan file (no meta entry)")
        meta = json.loads(str(z["meta"]))
        if meta.get("schema") != NPZ_SCHEMA:
            raise ValueError(f"{path}: unsupported scan schema {meta.get('schema')!r} (expected {NPZ_SCHEMA!r})")
        scan = Scan(z["range"], z["points"], sensor_model_from_dict(meta["sensor"]), noise_from_dict(meta["noise"]),
                    z["pose_prior"] if meta.get("has_pose_prior") else None)
        truth = None
        if meta.get("has_truth"):
            surfaces = tuple(Surface(int(i), f, p, c) for i, f, p, c in meta["surfaces"])
            a = {k: z[f"truth_{k}"] for k in _TRUTH_ARRAYS}
            truth = ScanTruth(a["T_world_sensor"], a["sigma"], a["surface_id"], a["normals"], surfaces,
                              a["true_range"], a["flags"])
    return RangeImage(scan, truth)


def write_ply(path: str | Path, points: np.ndarray, labels: np.ndarray | None = None) -> int:
    """Write the finite points of ``points`` ((N, 3) or (H, W, 3), metres) as a binary PLY (float64 x y z,
    plus an int32 ``label`` per point when ``labels`` ((N,) or (H, W)) is given). Returns the point count."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.all(np.isfinite(p), axis=1)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if labels is not None:
        fields.append(("label", "<i4"))
    rec = np.empty(int(keep.sum()), dtype=fields)
    rec["x"], rec["y"], rec["z"] = p[keep, 0], p[keep, 1], p[keep, 2]
    props = ["property double x", "property double y", "property double z"]
    if labels is not None:
        rec["label"] = np.asarray(labels).reshape(-1)[keep]
        props.append("property int label")
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {len(rec)}", *props,
                        "end_header"]) + "\n"
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())
    return len(rec)


def read_ply_points(path: str | Path) -> np.ndarray:
    """Read back the x y z of a PLY written by :func:`write_ply`, shape (N, 3)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    n = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if any(line.endswith(" label") for line in header):
        fields.append(("label", "<i4"))
    rec = np.frombuffer(data[end:], dtype=fields, count=n)
    return np.stack([rec["x"], rec["y"], rec["z"]], axis=1)


def shaded_image(scan: Scan) -> np.ndarray:
    """Cosine-shaded range image (like the paper's Fig. 2), (H, W) in [0, 1], NaN where no return.

    Normals come from the measured points themselves (cross product of the central differences along
    the image rows and columns); the shade is ``|cos|`` of the angle between that normal and the ray.
    """
    p = scan.points
    du = np.full_like(p, np.nan)
    dv = np.full_like(p, np.nan)
    du[:, 1:-1] = p[:, 2:] - p[:, :-2]
    dv[1:-1, :] = p[2:, :] - p[:-2, :]
    n = np.cross(du, dv)
    norm = np.linalg.norm(n, axis=-1)
    dist = np.linalg.norm(p, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        shade = np.abs(np.einsum("hwk,hwk->hw", n, p)) / (norm * dist)
    return np.where(np.isfinite(shade), shade, np.where(scan.valid, 0.5, np.nan))


def save_shaded_png(path: str | Path, scan: Scan) -> None:
    """Write :func:`shaded_image` as a grey PNG (no return: black)."""
    from matplotlib.image import imsave

    img = np.nan_to_num(shaded_image(scan), nan=0.0)
    imsave(path, img, cmap="gray", vmin=0.0, vmax=1.0)


def label_colours(n: int) -> np.ndarray:
    """``n`` distinct RGB colours (n, 3) in [0, 1], deterministic."""
    from matplotlib import colormaps

    base = np.concatenate([colormaps["tab20"].colors, colormaps["tab20b"].colors, colormaps["Set3"].colors])
    return np.asarray(base)[np.arange(n) % len(base)]


def save_labels_png(path: str | Path, surface_id: np.ndarray) -> None:
    """Write the truth surface-id image (H, W) as a colour PNG (-1: black)."""
    from matplotlib.image import imsave

    ids = np.asarray(surface_id)
    colours = label_colours(max(int(ids.max()) + 1, 1))
    rgb = np.zeros((*ids.shape, 3))
    rgb[ids >= 0] = colours[ids[ids >= 0]]
    imsave(path, rgb)


__all__ = ["save_npz", "load_npz", "write_ply", "read_ply_points", "shaded_image", "save_shaded_png",
           "save_labels_png", "label_colours", "NPZ_SCHEMA"]
