"""Readers for real range data: organised PCD, PLY point clouds, 16-bit depth PNG, and the project's ``.npz``.

Every reader returns the same :class:`sensors.range_image.Scan` the simulator produces (DESIGN 10.1-10.2):
``range`` (H, W) in metres along the ray (NaN = no return), ``points`` (H, W, 3) in the sensor frame (OpenCV:
x right, y down, z forward), a sensor model and a noise model. Real files carry no per-pixel sigma, so the
noise model comes from a named sensor preset (``kinect_like`` by default: structured light and stereo);
the core computes its own sigma from it.

Formats (:func:`read_scan` dispatches on the extension; :func:`load_scan` also returns a :class:`ReadInfo`
saying how the file was read):

``.pcd``
    PCL's Point Cloud Data v0.7 (and 0.6 headers), ``DATA ascii``, ``binary`` or ``binary_compressed`` (LZF,
    :mod:`sensors.lzf`); fields ``x y z`` required, any others (``rgba``, normals, padding ``_``) skipped.
    An organised cloud (``HEIGHT > 1``) keeps its 2-D organisation; its pinhole intrinsics are given or else
    estimated by least squares from the points themselves (column = ``fx x/z + cx``, row = ``fy y/z + cy``;
    the RMS residual in pixels is reported). Points are taken as given in the sensor frame; a non-default
    ``VIEWPOINT`` is recorded in the notes, not applied (PCL's mug scan says ``0 0 0 0 1 0 0``, a 180 degree
    turn that would put every point behind the camera). An unorganised cloud (``HEIGHT == 1``) is projected
    like a PLY.
``.ply``
    ASCII or binary (either byte order) PLY; the ``vertex`` element's ``x y z``. An unorganised cloud becomes
    an organised image by projecting it from its sensor origin (given, default the file's origin) onto a
    grid chosen to fit it (DESIGN 10.2): see :func:`organise_cloud`.
``.png``
    16-bit depth image (``depth_scale`` metres per unit, default 0.001: millimetres; 0 = no return) with
    pinhole intrinsics: given, or read from a YAML file (``fx fy cx cy``, or a 3x3 ``K`` / ``camera_matrix``)
    or an OpenCV calibration XML such as CAPE's ``calib_params.xml`` (its ``IR_intrinsic_params``: depth is
    measured by the IR camera). Without intrinsics, a ``calib_params.xml``, ``intrinsics.yaml`` or
    ``camera.yaml`` beside the image is used. Lens distortion coefficients are read but not applied (CAPE
    back-projects its depth images the same way).
``.npz``
    The project's own scans (:func:`sensors.io.load_npz`), with the noise model saved in the file.

**The sensor preset's working range.** A real sensor returns nothing outside its working range
(``min_range``-``max_range`` of the preset, e.g. 0.5-4.5 m for ``kinect_like``), and its noise model means nothing
there (``kinect_like``'s sigma grows with the square of the depth: metres at 30 m). Returns of a PCD, PLY or PNG
outside the preset's range are therefore counted (:attr:`ReadInfo.n_out_of_range`, with a note) and left out
(no return, NaN; an unorganised cloud's before it is projected); when they are more than
:data:`MAX_OUT_OF_RANGE_FRACTION` of the returns the file is refused (``ReaderError``: "... 94 % of returns
outside kinect_like's working range 0.5-4.5 m: choose `--sensor-preset` for this sensor"), since the data are not
what that sensor measures. ``.npz`` scans carry their own sensor model and are not checked.

A file that cannot be used (missing, truncated, wrong header, unknown field layout, no valid depth, most returns
outside the preset's working range) raises ``ValueError`` naming the file and what is wrong
(:class:`ReaderError`); intrinsics files that cannot be used raise :class:`scenes.config.ConfigError`.
"""

from __future__ import annotations

import dataclasses
import math
import re
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from scenes.config import ConfigError, load_yaml
from sensors.config import load_sensor
from sensors.lzf import LZFError, decompress
from sensors.models import PinholeCamera, ScanningLaser, SensorModel
from sensors.noise import NoiseModel
from sensors.range_image import Scan

__all__ = ["Intrinsics", "ReadInfo", "LoadedScan", "ReaderError", "read_scan", "load_scan", "read_pcd",
           "read_ply", "read_depth_png", "read_npz", "load_intrinsics", "organise_cloud", "estimate_intrinsics",
           "FORMATS", "MAX_OUT_OF_RANGE_FRACTION"]

FORMATS = (".pcd", ".ply", ".png", ".npz")
#: A file with more than this fraction of its returns outside the sensor preset's working range is refused.
MAX_OUT_OF_RANGE_FRACTION = 0.5
_CALIB_NAMES = ("calib_params.xml", "intrinsics.yaml", "intrinsics.yml", "camera.yaml", "camera.yml")


class ReaderError(ValueError):
    """A range data file that cannot be read: the message names the file and what is wrong."""

    def __init__(self, path: str | Path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{path}: {reason}")


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels (OpenCV: pixel centres at integer coordinates).

    Attributes
    ----------
    fx, fy : focal lengths (pixels, > 0).
    cx, cy : principal point (pixels).
    distortion : OpenCV distortion coefficients as read (not applied), may be empty.
    source : where they came from (for reports).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()
    source: str = "given"

    def __post_init__(self):
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ValueError(f"intrinsics: {name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics: focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def coerce(cls, value: Intrinsics | tuple | list | np.ndarray | None) -> Intrinsics | None:
        """Accept an :class:`Intrinsics`, a sequence ``(fx, fy, cx, cy)`` or None."""
        if value is None or isinstance(value, Intrinsics):
            return value
        v = np.asarray(value, dtype=np.float64).ravel()
        if v.shape != (4,):
            raise ValueError(f"intrinsics must be (fx, fy, cx, cy), got {v.size} numbers")
        return cls(*v)


@dataclass(frozen=True)
class ReadInfo:
    """How a file became a :class:`Scan` (for the scene description's provenance).

    Attributes
    ----------
    path : the file read.
    format : e.g. ``pcd/binary_compressed``, ``ply/binary_little_endian``, ``png/16-bit``, ``npz``.
    n_points : finite points (or non-zero depth pixels) in the file.
    n_valid : pixels of the scan with a return.
    organised : whether the file itself was organised (False: projected onto a grid).
    grid : ``pinhole`` or ``laser`` (spherical) grid of the scan.
    intrinsics_source : how the sensor geometry was obtained.
    T_file_sensor : (4, 4) maps sensor-frame points to the file's frame (``p_file = T @ p_sensor``).
    noise_preset : the preset whose noise model the scan carries (``file`` for ``.npz``).
    n_collisions : points dropped because a nearer point fell in the same pixel (projected clouds).
    notes : free-text remarks (estimated intrinsics residual, ignored distortion, ...).
    n_out_of_range : returns of the file outside the preset's working range, left out (module docstring).
    working_range_m : the preset's working range ``(min_range, max_range)`` in metres the returns were checked
        against (None: not checked, e.g. ``.npz`` or no preset).
    """

    path: str
    format: str
    n_points: int
    n_valid: int
    organised: bool
    grid: str
    intrinsics_source: str
    T_file_sensor: np.ndarray = field(default_factory=lambda: np.eye(4))
    noise_preset: str = ""
    n_collisions: int = 0
    notes: tuple[str, ...] = ()
    n_out_of_range: int = 0
    working_range_m: tuple[float, float] | None = None

    def to_dict(self) -> dict:
        return {"path": self.path, "format": self.format, "n_points": self.n_points, "n_valid": self.n_valid,
                "organised": self.organised, "grid": self.grid, "intrinsics_source": self.intrinsics_source,
                "T_file_sensor": np.asarray(self.T_file_sensor).tolist(), "noise_preset": self.noise_preset,
                "n_collisions": self.n_collisions, "notes": list(self.notes), "n_out_of_range": self.n_out_of_range,
                "working_range_m": None if self.working_range_m is None else list(self.working_range_m)}


@dataclass(frozen=True)
class LoadedScan:
    """A :class:`Scan` with its :class:`ReadInfo`."""

    scan: Scan
    info: ReadInfo


# ------------------------------------------------------------------------------------------------ entry points


def read_scan(path: str | Path, *, intrinsics: Intrinsics | tuple | None = None,
              intrinsics_file: str | Path | None = None, sensor_preset: str = "kinect_like",
              depth_scale: float | None = None, origin: np.ndarray | tuple | None = None,
              view_direction: np.ndarray | tuple | None = None, grid: str = "auto") -> Scan:
    """Read a range data file into a :class:`Scan` (see :func:`load_scan` for the parameters)."""
    return load_scan(path, intrinsics=intrinsics, intrinsics_file=intrinsics_file, sensor_preset=sensor_preset,
                     depth_scale=depth_scale, origin=origin, view_direction=view_direction, grid=grid).scan


def load_scan(path: str | Path, *, intrinsics: Intrinsics | tuple | None = None,
              intrinsics_file: str | Path | None = None, sensor_preset: str = "kinect_like",
              depth_scale: float | None = None, origin: np.ndarray | tuple | None = None,
              view_direction: np.ndarray | tuple | None = None, grid: str = "auto") -> LoadedScan:
    """Read a range data file, dispatching on its extension (:data:`FORMATS`).

    Parameters
    ----------
    path : the file.
    intrinsics : pinhole ``(fx, fy, cx, cy)`` in pixels (PNG: needed unless a file gives them; organised PCD:
        overrides the intrinsics estimated from the points).
    intrinsics_file : YAML or OpenCV XML file with the intrinsics (:func:`load_intrinsics`).
    sensor_preset : preset (or sensor YAML) whose noise model the scan carries (ignored for ``.npz``).
    depth_scale : metres per unit: PNG default 0.001 (mm); PCD and PLY default 1.0 (coordinates in metres).
    origin : (3,) sensor origin in the file's frame for unorganised clouds (default: the file's origin).
    view_direction : (3,) optical axis in the file's frame for unorganised clouds (default: the mean
        direction of the points seen from ``origin``).
    grid : ``auto``, ``pinhole`` or ``laser``: the grid an unorganised cloud is projected onto.

    Returns
    -------
    LoadedScan

    Raises
    ------
    ReaderError (a ValueError) : unknown extension, missing or unusable file; more than
        :data:`MAX_OUT_OF_RANGE_FRACTION` of the returns outside the preset's working range.
    ConfigError : unknown preset, unusable intrinsics file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ReaderError(path, f"unknown range data format {path.suffix!r} (known: {', '.join(FORMATS)})")
    if not path.is_file():
        raise ReaderError(path, "no such file")
    if depth_scale is not None and not (math.isfinite(depth_scale) and depth_scale > 0):
        raise ValueError(f"depth_scale must be a positive number, got {depth_scale}")
    if intrinsics is not None and intrinsics_file is not None:
        raise ValueError("give intrinsics or intrinsics_file, not both")
    K = load_intrinsics(intrinsics_file) if intrinsics_file is not None else Intrinsics.coerce(intrinsics)
    if suffix == ".npz":
        return read_npz(path)
    noise = load_sensor(sensor_preset).noise
    if suffix == ".pcd":
        return read_pcd(path, noise=noise, intrinsics=K, scale=depth_scale or 1.0, origin=origin,
                        view_direction=view_direction, grid=grid, preset=sensor_preset)
    if suffix == ".ply":
        return read_ply(path, noise=noise, scale=depth_scale or 1.0, origin=origin, view_direction=view_direction,
                        grid=grid, preset=sensor_preset)
    return read_depth_png(path, noise=noise, intrinsics=K, depth_scale=depth_scale or 1e-3, preset=sensor_preset)


# ------------------------------------------------------------------------------------------------ intrinsics


def load_intrinsics(path: str | Path) -> Intrinsics:
    """Read pinhole intrinsics from a YAML or an OpenCV ``FileStorage`` XML file.

    YAML: ``{fx, fy, cx, cy}`` (optionally under ``intrinsics:``), or a 3x3 ``K`` / ``camera_matrix`` (nested
    lists, or OpenCV's ``{rows, cols, data}``), optional ``distortion``. XML: the first matrix among
    ``IR_intrinsic_params``, ``depth_intrinsic_params``, ``camera_matrix``, ``K``, ``intrinsics`` (then any
    element whose name contains ``intrinsic``), with the matching ``*distortion*`` coefficients.

    Raises
    ------
    ConfigError : unreadable file, or no usable intrinsics in it (naming what is missing).
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(str(path), "", "no such intrinsics file")
    if path.suffix.lower() == ".xml":
        return _intrinsics_from_xml(path)
    data = load_yaml(path)
    if isinstance(data, dict) and isinstance(data.get("intrinsics"), dict):
        data = data["intrinsics"]
    if not isinstance(data, dict):
        raise ConfigError(str(path), "", "expected a mapping with fx, fy, cx, cy (or a 3x3 K)")
    dist = tuple(float(x) for x in np.ravel(_yaml_matrix(data.get("distortion", []), path, "distortion")))
    if all(k in data for k in ("fx", "fy", "cx", "cy")):
        try:
            return Intrinsics(*(float(data[k]) for k in ("fx", "fy", "cx", "cy")), distortion=dist, source=str(path))
        except (TypeError, ValueError) as exc:
            raise ConfigError(str(path), "", f"bad intrinsics ({exc})") from None
    for key in ("K", "camera_matrix"):
        if key in data:
            return _from_K(_yaml_matrix(data[key], path, key), dist, str(path), path, key)
    raise ConfigError(str(path), "", "no intrinsics found: expected fx, fy, cx, cy or a 3x3 K / camera_matrix")


def _yaml_matrix(value, path: Path, key: str) -> np.ndarray:
    if isinstance(value, dict) and "data" in value:
        value = value["data"]
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(str(path), key, f"expected numbers, got {value!r}") from None


def _from_K(K: np.ndarray, dist: tuple[float, ...], source: str, path: Path, key: str) -> Intrinsics:
    if K.size != 9:
        raise ConfigError(str(path), key, f"expected a 3x3 matrix, got {K.size} numbers")
    K = K.reshape(3, 3)
    try:
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], distortion=dist, source=source)
    except ValueError as exc:
        raise ConfigError(str(path), key, str(exc)) from None


def _intrinsics_from_xml(path: Path) -> Intrinsics:
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as exc:
        raise ConfigError(str(path), "", f"not a readable XML file ({exc})") from None
    names = [el.tag for el in root]
    preferred = ("IR_intrinsic_params", "depth_intrinsic_params", "camera_matrix", "K", "intrinsics")
    tag = next((t for t in preferred if t in names), None) or next((t for t in names if "intrinsic" in t.lower()),
                                                                   None)
    if tag is None:
        raise ConfigError(str(path), "", f"no intrinsic matrix found (elements: {', '.join(names) or 'none'})")
    K = _xml_matrix(root.find(tag), path, tag)
    prefix = tag.split("_")[0] if "_" in tag else ""
    dist_tag = next((t for t in names if "distortion" in t.lower() and t.startswith(prefix)), None)
    dist = tuple(_xml_matrix(root.find(dist_tag), path, dist_tag).ravel()) if dist_tag else ()
    return _from_K(K, tuple(float(d) for d in dist), f"{path.name}:{tag}", path, tag)


def _xml_matrix(el: ET.Element | None, path: Path, tag: str) -> np.ndarray:
    data = None if el is None else el.find("data")
    if data is None or not (data.text or "").strip():
        raise ConfigError(str(path), tag, "matrix has no <data>")
    try:
        values = np.array([float(x) for x in data.text.split()])
    except ValueError:
        raise ConfigError(str(path), tag, "matrix data are not numbers") from None
    rows, cols = (el.findtext(k) for k in ("rows", "cols"))
    if rows and cols and values.size != int(rows) * int(cols):
        raise ConfigError(str(path), tag, f"matrix of {rows}x{cols} has {values.size} numbers")
    return values.reshape(int(rows), int(cols)) if rows and cols else values


def estimate_intrinsics(points: np.ndarray) -> tuple[Intrinsics, float]:
    """Pinhole intrinsics of an organised cloud from its own points, by least squares.

    Parameters
    ----------
    points : ndarray of shape (H, W, 3), sensor frame (z forward), NaN where no return.

    Returns
    -------
    (Intrinsics, rms_px) : the fit of ``column = fx x/z + cx`` and ``row = fy y/z + cy`` over the valid pixels,
    and the RMS residual in pixels (a pinhole-organised cloud gives well under a pixel).

    Raises
    ------
    ValueError : fewer than 10 usable points, or points that do not spread over columns and rows.
    """
    p = np.asarray(points, dtype=np.float64)
    ok = np.all(np.isfinite(p), axis=-1) & (p[..., 2] > 0)
    if ok.sum() < 10:
        raise ValueError("fewer than 10 points in front of the sensor: cannot estimate intrinsics")
    rows, cols = np.nonzero(ok)
    q = p[ok]
    a, b = q[:, 0] / q[:, 2], q[:, 1] / q[:, 2]
    est, resid = [], []
    for coord, pix in ((a, cols), (b, rows)):
        A = np.stack([coord, np.ones_like(coord)], axis=1)
        if np.ptp(coord) <= 0 or np.ptp(pix) <= 0:
            raise ValueError("points do not spread over the image: cannot estimate intrinsics")
        sol, *_ = np.linalg.lstsq(A, pix.astype(np.float64), rcond=None)
        est.append(sol)
        resid.append(pix - A @ sol)
    if est[0][0] <= 0 or est[1][0] <= 0:
        raise ValueError("points are not organised like a pinhole image (negative focal length)")
    rms = float(np.sqrt(np.mean(np.concatenate(resid) ** 2)))
    K = Intrinsics(est[0][0], est[1][0], est[0][1], est[1][1], source=f"estimated from the points (rms {rms:.3f} px)")
    return K, rms


def _pinhole(K: Intrinsics, width: int, height: int, rng: np.ndarray, limits: tuple[float, float]) -> PinholeCamera:
    lo, hi = _range_limits(rng, limits)
    return PinholeCamera(width, height, K.fx, K.fy, K.cx, K.cy, lo, hi)


def _range_limits(rng: np.ndarray, preset: tuple[float, float]) -> tuple[float, float]:
    """The preset's range limits widened to include every return of the file."""
    finite = rng[np.isfinite(rng)]
    lo, hi = preset
    if finite.size:
        lo, hi = min(lo, 0.99 * float(finite.min())), max(hi, 1.01 * float(finite.max()))
    return max(lo, 0.0), hi


def _preset_limits(preset: str) -> tuple[float, float]:
    model = load_sensor(preset).model
    return model.min_range, model.max_range


def _out_of_range(path: Path, rng: np.ndarray, preset: str) -> tuple[np.ndarray, str]:
    """Mask of the returns (finite ``rng``, metres) outside the working range of ``preset`` (none without a preset),
    and the note saying how many were left out ("" when none); refuses the file (``ReaderError``) when they are
    more than :data:`MAX_OUT_OF_RANGE_FRACTION` of its returns."""
    finite = np.isfinite(rng)
    if not preset or not finite.any():
        return np.zeros(rng.shape, bool), ""
    config = load_sensor(preset)
    lo, hi = config.model.min_range, config.model.max_range
    with np.errstate(invalid="ignore"):
        out = finite & ((rng < lo) | (rng > hi))
    n_out, n = int(out.sum()), int(finite.sum())
    if not n_out:
        return out, ""
    name = config.name or str(preset)
    where = f"outside {name}'s working range {lo:g}-{hi:g} m"
    if n_out > MAX_OUT_OF_RANGE_FRACTION * n:
        raise ReaderError(path, f"{100.0 * n_out / n:.0f} % of returns {where}: choose `--sensor-preset` for this "
                          "sensor")
    return out, f"{n_out} of {n} returns ({100.0 * n_out / n:.1f} %) {where} left out"


def _drop_out_of_range(path: Path, rng: np.ndarray, pts: np.ndarray,
                       preset: str) -> tuple[np.ndarray, np.ndarray, int, str]:
    """``(range, points, n_out, note)`` with the returns outside the preset's working range set to NaN
    (:func:`_out_of_range`)."""
    out, note = _out_of_range(path, rng, preset)
    if not out.any():
        return rng, pts, 0, note
    return np.where(out, np.nan, rng), np.where(out[..., None], np.nan, pts), int(out.sum()), note


def _working_range(preset: str) -> tuple[float, float] | None:
    return _preset_limits(preset) if preset else None


def _finish(path: Path, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NaN-out unusable pixels; return (range, points); reject a file with no return."""
    pts = np.asarray(points, dtype=np.float64)
    ok = np.all(np.isfinite(pts), axis=-1) & np.any(pts != 0, axis=-1)
    pts = np.where(ok[..., None], pts, np.nan)
    rng = np.linalg.norm(pts, axis=-1)
    if not ok.any():
        raise ReaderError(path, "no valid depth: every pixel is empty, zero or NaN")
    return rng, pts


# ------------------------------------------------------------------------------------------------ PCD

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8",
              ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4", ("I", 8): "i8"}
_PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")


def _pcd_header(path: Path, raw: bytes) -> tuple[dict[str, list[str]], int]:
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise ReaderError(path, "not a PCD file: header has no DATA line" if header else
                              "not a PCD file (empty or no header)")
        try:
            line = raw[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            raise ReaderError(path, f"not a PCD file: non-text header line at byte {pos}") from None
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key not in _PCD_KEYS:
            raise ReaderError(path, f"not a PCD file: unknown header line {line[:40]!r}")
        header[key] = values
        if key == "DATA":
            return header, pos
        if len(header) > 20:
            raise ReaderError(path, "not a PCD file: no DATA line")


def _pcd_layout(path: Path, header: dict[str, list[str]]) -> tuple[list[str], list[np.dtype], list[int], int, int]:
    for key in ("FIELDS", "SIZE", "TYPE", "WIDTH", "DATA"):
        if key not in header:
            raise ReaderError(path, f"PCD header lacks {key}")
    fields = header["FIELDS"]
    n = len(fields)
    counts_s = header.get("COUNT", ["1"] * n)
    if not (len(header["SIZE"]) == len(header["TYPE"]) == len(counts_s) == n):
        raise ReaderError(path, f"unknown field layout: FIELDS ({n}), SIZE ({len(header['SIZE'])}), TYPE "
                          f"({len(header['TYPE'])}) and COUNT ({len(counts_s)}) do not match")
    try:
        sizes = [int(s) for s in header["SIZE"]]
        counts = [int(c) for c in counts_s]
        width = int(header["WIDTH"][0])
        height = int(header.get("HEIGHT", ["1"])[0])
        n_points = int(header.get("POINTS", [str(width * height)])[0])
    except (ValueError, IndexError):
        raise ReaderError(path, "PCD header has a non-integer SIZE, COUNT, WIDTH, HEIGHT or POINTS") from None
    dtypes = []
    for name, t, s in zip(fields, header["TYPE"], sizes, strict=True):
        code = _PCD_TYPES.get((t.upper(), s))
        if code is None:
            raise ReaderError(path, f"unknown field layout: field {name!r} has TYPE {t} and SIZE {s}")
        dtypes.append(np.dtype("<" + code))
    if any(c < 1 for c in counts) or width < 1 or height < 1:
        raise ReaderError(path, "PCD header has a COUNT, WIDTH or HEIGHT below 1")
    if n_points != width * height:
        raise ReaderError(path, f"PCD header: POINTS {n_points} != WIDTH x HEIGHT = {width} x {height}")
    missing = [c for c in "xyz" if c not in fields]
    if missing:
        raise ReaderError(path, f"unknown field layout: no {' '.join(missing)} field (FIELDS {' '.join(fields)})")
    return fields, dtypes, counts, width, height


def _pcd_xyz(path: Path, raw: bytes, start: int, mode: str, fields, dtypes, counts, n_points: int) -> np.ndarray:
    """The x y z columns, shape (n_points, 3), float64."""
    offsets = np.concatenate([[0], np.cumsum(counts)])
    idx = [int(offsets[fields.index(c)]) for c in "xyz"]
    if mode == "ascii":
        text = raw[start:].decode("ascii", errors="replace").split()
        total = int(offsets[-1])
        if len(text) < n_points * total:
            raise ReaderError(path, f"truncated: ascii data has {len(text)} values, expected "
                              f"{n_points} points x {total} = {n_points * total}")
        try:
            cols = [np.array(text[i:n_points * total:total], dtype=np.float64) for i in idx]
        except ValueError:
            raise ReaderError(path, "ascii data contain a value that is not a number") from None
        return np.stack(cols, axis=1)
    rec = np.dtype([(f"f{i}", dt, (c,)) for i, (dt, c) in enumerate(zip(dtypes, counts, strict=True))])
    if mode == "binary":
        need = n_points * rec.itemsize
        if len(raw) - start < need:
            raise ReaderError(path, f"truncated: binary data have {len(raw) - start} bytes, expected {need} "
                              f"({n_points} points x {rec.itemsize} bytes)")
        arr = np.frombuffer(raw, dtype=rec, count=n_points, offset=start)
        return np.stack([arr[f"f{fields.index(c)}"][:, 0].astype(np.float64) for c in "xyz"], axis=1)
    if mode == "binary_compressed":
        if len(raw) - start < 8:
            raise ReaderError(path, "truncated: binary_compressed data lack their two size words")
        csize, usize = struct.unpack_from("<II", raw, start)
        need = n_points * rec.itemsize
        if usize != need:
            raise ReaderError(path, f"binary_compressed uncompressed size {usize} != {n_points} points x "
                              f"{rec.itemsize} bytes = {need}")
        if len(raw) - start - 8 < csize:
            raise ReaderError(path, f"truncated: binary_compressed data have {len(raw) - start - 8} bytes, "
                              f"expected {csize}")
        try:
            data = decompress(memoryview(raw)[start + 8:start + 8 + csize], usize)
        except LZFError as exc:
            raise ReaderError(path, f"corrupt binary_compressed data ({exc})") from None
        # PCL stores the compressed payload field by field (all x, then all y, ...).
        cols = []
        off = 0
        block = {}
        for i, (dt, c) in enumerate(zip(dtypes, counts, strict=True)):
            block[fields[i]] = (off, dt, c)
            off += n_points * dt.itemsize * c
        for name in "xyz":
            o, dt, c = block[name]
            col = np.frombuffer(data, dtype=dt, count=n_points * c, offset=o).reshape(n_points, c)[:, 0]
            cols.append(col.astype(np.float64))
        return np.stack(cols, axis=1)
    raise ReaderError(path, f"unknown PCD DATA type {mode!r} (known: ascii, binary, binary_compressed)")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_pcd(path: str | Path, *, noise: NoiseModel, intrinsics: Intrinsics | None = None, scale: float = 1.0,
             origin=None, view_direction=None, grid: str = "auto", preset: str = "") -> LoadedScan:
    """Read a PCD file (module docstring). ``noise`` is the noise model the scan carries.

    An organised cloud keeps its (HEIGHT, WIDTH) organisation, its points taken as sensor-frame points (a
    non-default ``VIEWPOINT`` is noted, not applied). ``origin`` / ``view_direction`` / ``grid`` apply only to an
    unorganised cloud (``HEIGHT == 1``), projected with :func:`organise_cloud`.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ReaderError(path, f"cannot read ({exc.strerror or exc})") from None
    header, start = _pcd_header(path, raw)
    fields, dtypes, counts, width, height = _pcd_layout(path, header)
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    xyz = _pcd_xyz(path, raw, start, mode, fields, dtypes, counts, width * height) * scale
    notes = []
    vp = header.get("VIEWPOINT")
    if vp is not None and [float(x) if _is_number(x) else x for x in vp] != [0, 0, 0, 1, 0, 0, 0]:
        notes.append(f"VIEWPOINT {' '.join(vp)} recorded, not applied: points are taken as given in the sensor "
                     "frame (PCL's own convention for organised captures)")
    fmt = f"pcd/{mode}"
    n_points = int(np.all(np.isfinite(xyz), axis=1).sum())
    if height == 1:
        loaded = organise_cloud(xyz, noise=noise, path=path, fmt=fmt, origin=origin, view_direction=view_direction,
                                grid=grid, preset=preset)
        info = dataclasses.replace(loaded.info, notes=loaded.info.notes + tuple(notes))
        return LoadedScan(loaded.scan, info)
    pts = xyz
    rng, pts = _finish(path, pts.reshape(height, width, 3))
    rng, pts, n_out, note = _drop_out_of_range(path, rng, pts, preset)
    notes += [note] if note else []
    if intrinsics is None:
        try:
            intrinsics, rms = estimate_intrinsics(pts)
        except ValueError as exc:
            raise ReaderError(path, f"organised cloud: {exc}; give the intrinsics") from None
        if rms > 1.0:
            notes.append(f"estimated intrinsics fit the organisation poorly (rms {rms:.2f} px): not a pinhole image?")
    sensor = _pinhole(intrinsics, width, height, rng, _preset_limits(preset) if preset else (0.0, 1.0))
    scan = Scan(rng, pts, sensor, noise)
    info = ReadInfo(str(path), fmt, n_points, int(np.isfinite(rng).sum()), True, "pinhole", intrinsics.source,
                    np.eye(4), preset, 0, tuple(notes), n_out_of_range=n_out, working_range_m=_working_range(preset))
    return LoadedScan(scan, info)


# ------------------------------------------------------------------------------------------------ PLY

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
              "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
              "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


@dataclass
class _PlyElement:
    name: str
    count: int
    props: list[tuple[str, str, str | None]]  # (name, type, list item type or None)


def _ply_header(path: Path, raw: bytes) -> tuple[str, list[_PlyElement], int]:
    if not raw.startswith(b"ply"):
        raise ReaderError(path, "not a PLY file (no 'ply' magic)")
    m = re.search(rb"end_header\r?\n", raw[:65536])
    if m is None:
        raise ReaderError(path, "PLY header has no end_header line (truncated or not a PLY file)")
    try:
        lines = raw[:m.start()].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise ReaderError(path, "PLY header is not ASCII text") from None
    fmt = None
    elements: list[_PlyElement] = []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            if len(tok) < 2 or tok[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise ReaderError(path, f"unknown PLY format {line!r}")
            fmt = tok[1]
        elif tok[0] == "element":
            try:
                elements.append(_PlyElement(tok[1], int(tok[2]), []))
            except (IndexError, ValueError):
                raise ReaderError(path, f"bad PLY element line {line!r}") from None
        elif tok[0] == "property":
            if not elements:
                raise ReaderError(path, f"PLY property before any element: {line!r}")
            if len(tok) == 5 and tok[1] == "list":
                if tok[2] not in _PLY_TYPES or tok[3] not in _PLY_TYPES:
                    raise ReaderError(path, f"unknown PLY property type in {line!r}")
                elements[-1].props.append((tok[4], tok[2], tok[3]))
            elif len(tok) == 3 and tok[1] in _PLY_TYPES:
                elements[-1].props.append((tok[2], tok[1], None))
            else:
                raise ReaderError(path, f"unknown PLY property {line!r}")
        else:
            raise ReaderError(path, f"unknown PLY header line {line!r}")
    if fmt is None:
        raise ReaderError(path, "PLY header has no format line")
    return fmt, elements, m.end()


def read_ply(path: str | Path, *, noise: NoiseModel, scale: float = 1.0, origin=None, view_direction=None,
             grid: str = "auto", preset: str = "") -> LoadedScan:
    """Read the ``vertex`` x y z of a PLY file and organise them with :func:`organise_cloud`."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ReaderError(path, f"cannot read ({exc.strerror or exc})") from None
    fmt, elements, start = _ply_header(path, raw)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise ReaderError(path, f"PLY has no vertex element (elements: {', '.join(names) or 'none'})")
    vi = names.index("vertex")
    vertex = elements[vi]
    pnames = [p[0] for p in vertex.props]
    missing = [c for c in "xyz" if c not in pnames]
    if missing:
        raise ReaderError(path, f"unknown field layout: vertex has no {' '.join(missing)} property "
                          f"(properties: {' '.join(pnames)})")
    if any(p[2] is not None for p in vertex.props):
        raise ReaderError(path, "unknown field layout: list properties in the vertex element")
    if fmt == "ascii":
        lines = raw[start:].decode("ascii", errors="replace").splitlines()
        skip = sum(e.count for e in elements[:vi])
        rows = lines[skip:skip + vertex.count]
        if len(rows) < vertex.count:
            raise ReaderError(path, f"truncated: {len(rows)} vertex lines, expected {vertex.count}")
        idx = [pnames.index(c) for c in "xyz"]
        try:
            values = np.array([row.split() for row in rows], dtype=np.float64)
        except ValueError:
            raise ReaderError(path, "vertex lines are not all numbers with one value per property") from None
        if values.ndim != 2 or values.shape[1] != len(pnames):
            raise ReaderError(path, f"vertex lines do not have {len(pnames)} values each")
        xyz = values[:, idx]
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        offset = start
        for e in elements[:vi]:
            if any(p[2] is not None for p in e.props):
                raise ReaderError(path, f"unsupported: binary element {e.name!r} with list properties comes "
                                  "before the vertices")
            offset += e.count * sum(np.dtype(_PLY_TYPES[p[1]]).itemsize for p in e.props)
        rec = np.dtype([(p[0], order + _PLY_TYPES[p[1]]) for p in vertex.props])
        need = vertex.count * rec.itemsize
        if len(raw) - offset < need:
            raise ReaderError(path, f"truncated: vertex data have {max(len(raw) - offset, 0)} bytes, expected "
                              f"{need} ({vertex.count} vertices x {rec.itemsize} bytes)")
        arr = np.frombuffer(raw, dtype=rec, count=vertex.count, offset=offset)
        xyz = np.stack([arr[c].astype(np.float64) for c in "xyz"], axis=1)
    return organise_cloud(xyz * scale, noise=noise, path=path, fmt=f"ply/{fmt}", origin=origin,
                          view_direction=view_direction, grid=grid, preset=preset)


# ------------------------------------------------------------------------------------------------ projection


def _frame_from_direction(d: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) whose columns are the sensor axes (x right, y down, z = ``d``) in the file's frame.

    The image x axis is the file's x axis made orthogonal to ``d`` (its y when ``d`` is along x), so a cloud in
    the OpenGL convention (looking along -z, y up) gets ``diag(1, -1, -1)`` and an OpenCV one the identity.
    """
    z = d / np.linalg.norm(d)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


def _grid_step(coords: np.ndarray) -> float:
    """Median nearest-neighbour spacing of 2-D angular coordinates (N, 2) (queried for at most 20,000 points)."""
    from scipy.spatial import cKDTree

    query = coords[np.linspace(0, len(coords) - 1, min(len(coords), 20000)).astype(np.int64)]
    d, _ = cKDTree(coords).query(query, k=2)
    nn = d[:, 1]
    nn = nn[nn > 0]
    if nn.size == 0:
        raise ValueError("all points project to one direction")
    return float(np.median(nn))


def _phase(coords: np.ndarray, step: float) -> float:
    """Offset in [0, 1) pixels that puts grid-regular samples at pixel centres (circular mean)."""
    ang = 2 * np.pi * coords / step
    return float((np.arctan2(np.sin(ang).mean(), np.cos(ang).mean()) / (2 * np.pi)) % 1.0)


def organise_cloud(points: np.ndarray, *, noise: NoiseModel, path: str | Path = "<cloud>", fmt: str = "cloud",
                   origin=None, view_direction=None, grid: str = "auto", preset: str = "",
                   max_pixels: int = 4_000_000, pinhole_max_angle_deg: float = 60.0,
                   snap_deg: float = 30.0) -> LoadedScan:
    """Organise an unorganised cloud into a range image seen from ``origin`` (DESIGN 10.2).

    The sensor frame has its z axis along ``view_direction``; by default the mean unit direction of the points
    from ``origin``, replaced by the file's +z or -z axis when within ``snap_deg`` of it (a cloud saved in a
    camera's frame, OpenCV +z or OpenGL -z, keeps that camera's optical axis and pixel lattice). Its x axis
    is along the file's x made orthogonal to it (:func:`_frame_from_direction`).
    The grid is a pinhole camera when every point lies within ``pinhole_max_angle_deg`` of the axis
    (``grid="auto"``), else a spherical scanning-laser grid. Its angular pitch is the median nearest-neighbour
    spacing of the points' directions (so a cloud that came from a depth image lands one point per pixel,
    phase-aligned), enlarged if the image would exceed ``max_pixels``. Each pixel keeps its nearest point;
    the exact point is kept (not snapped to the pixel's ray), so the geometry is unchanged.

    Parameters
    ----------
    points : ndarray of shape (N, 3), metres, in the file's frame; non-finite rows are dropped.

    Returns
    -------
    LoadedScan with ``info.T_file_sensor`` the sensor pose in the file's frame.

    Raises
    ------
    ReaderError : fewer than 10 finite points, or all at the origin.
    """
    if grid not in ("auto", "pinhole", "laser"):
        raise ValueError(f"grid must be auto, pinhole or laser, got {grid!r}")
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n_file = len(p)
    p = p[np.all(np.isfinite(p), axis=1)]
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    q = p - o
    r = np.linalg.norm(q, axis=1)
    q, r = q[r > 0], r[r > 0]
    out, range_note = _out_of_range(Path(str(path)), r, preset)  # left out before the projection
    n_out = int(out.sum())
    q, r = q[~out], r[~out]
    if len(q) < 10:
        raise ReaderError(path, f"no valid depth: {len(q)} usable points of {n_file}")
    if view_direction is None:
        mean_dir = (q / r[:, None]).mean(axis=0)
        if np.linalg.norm(mean_dir) < 1e-6:
            mean_dir = np.array([0.0, 0.0, 1.0])
        elif abs(mean_dir[2]) >= math.cos(math.radians(snap_deg)) * np.linalg.norm(mean_dir):
            mean_dir = np.array([0.0, 0.0, np.sign(mean_dir[2])])  # a camera's own frame: keep its axis
    else:
        mean_dir = np.asarray(view_direction, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(mean_dir)) or np.linalg.norm(mean_dir) == 0:
            raise ValueError(f"view_direction must be a non-zero 3-vector, got {view_direction!r}")
    R = _frame_from_direction(mean_dir)
    s = q @ R  # sensor frame
    off_axis = np.degrees(np.arccos(np.clip(s[:, 2] / r, -1.0, 1.0)))
    kind = grid if grid != "auto" else ("pinhole" if off_axis.max() < pinhole_max_angle_deg else "laser")
    if kind == "pinhole":
        if off_axis.max() >= 89.0:
            raise ReaderError(path, "points lie beside or behind the sensor: a pinhole grid cannot hold them "
                              "(use grid='laser' or give view_direction)")
        coords = s[:, :2] / s[:, 2:3]
    else:
        coords = np.stack([np.arctan2(s[:, 0], s[:, 2]), np.arctan2(-s[:, 1], np.hypot(s[:, 0], s[:, 2]))], axis=1)
    try:
        step = _grid_step(coords)
    except ValueError as exc:
        raise ReaderError(path, str(exc)) from None
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    while np.prod(np.floor((hi - lo) / step) + 2) > max_pixels:
        step *= 1.25
    phase = np.array([_phase(coords[:, 0], step), _phase(coords[:, 1], step)])
    # Pixel index i holds coordinates in [lo + (i - 0.5 + phase) step, lo + (i + 0.5 + phase) step): samples at
    # lo + (k + phase) step fall at pixel centres.
    first = np.floor((lo - phase * step) / step + 0.5)  # index of the lowest sample, relative to the phase grid
    base = (first + phase) * step  # coordinate of pixel 0's centre (before the margin below)
    base -= step  # one empty pixel of margin
    n = (np.floor((hi - base) / step + 0.5) + 2).astype(int)
    W, H = int(n[0]), int(n[1])
    ij = np.floor((coords - base) / step + 0.5).astype(np.int64)
    if kind == "pinhole":
        # column u = fx x/z + cx with fx = 1/step and u = (x/z - base_x)/step -> cx = -base_x/step
        f = 1.0 / step
        K = Intrinsics(f, f, -base[0] * f, -base[1] * f, source=f"fitted to the cloud ({fmt})")
        col, row = ij[:, 0], ij[:, 1]
    else:
        col = ij[:, 0]
        row = (H - 1) - ij[:, 1]  # elevation grows upwards, rows downwards
    flat = row * W + col
    order = np.lexsort((r, flat))  # by pixel, nearest first
    flat_sorted = flat[order]
    first_of_pixel = np.ones(len(order), bool)
    first_of_pixel[1:] = flat_sorted[1:] != flat_sorted[:-1]
    keep = order[first_of_pixel]
    img = np.full((H * W, 3), np.nan)
    img[flat[keep]] = s[keep]
    rng, img = _finish(Path(str(path)), img.reshape(H, W, 3))
    limits = _preset_limits(preset) if preset else (0.0, 1.0)
    sensor: SensorModel
    if kind == "pinhole":
        sensor = _pinhole(K, W, H, rng, limits)
        source = K.source
    else:
        # Column j's azimuth centre is base_x + (j + 1 - 1) step: ScanningLaser puts it at az_min + (j + 0.5) step.
        lo_r, hi_r = _range_limits(rng, limits)
        az_min = base[0] - 0.5 * step
        el_max = base[1] + (H - 1) * step + 0.5 * step
        sensor = ScanningLaser(W, H, max(az_min, -math.pi), min(az_min + W * step, math.pi),
                               max(el_max - H * step, -math.pi / 2), min(el_max, math.pi / 2), lo_r, hi_r)
        source = f"spherical grid fitted to the cloud ({fmt}, {math.degrees(step):.4f} deg pitch)"
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, o
    notes = (f"projected from origin {o.tolist()} along {R[:, 2].round(4).tolist()}",) + \
        ((range_note,) if range_note else ())
    info = ReadInfo(str(path), fmt, len(p), int(np.isfinite(rng).sum()), False, kind, source, T, preset,
                    int(len(q) - len(keep)), notes, n_out_of_range=n_out, working_range_m=_working_range(preset))
    return LoadedScan(Scan(rng, img, sensor, noise), info)


# ------------------------------------------------------------------------------------------------ PNG


def read_depth_png(path: str | Path, *, noise: NoiseModel, intrinsics: Intrinsics | None = None,
                   depth_scale: float = 1e-3, preset: str = "") -> LoadedScan:
    """Read a 16-bit depth PNG (``depth_scale`` metres per unit, 0 = no return) with pinhole intrinsics.

    Without ``intrinsics``, a calibration file beside the image (``calib_params.xml``, ``intrinsics.yaml``,
    ``camera.yaml``) is used; without one either, ``ReaderError``. Depth is z in the camera frame:
    ``point = depth * ((u - cx) / fx, (v - cy) / fy, 1)``.
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            mode = im.mode
            im.load()
            depth_raw = np.asarray(im)
    except UnidentifiedImageError:
        raise ReaderError(path, "not a PNG image") from None
    except (OSError, SyntaxError, ValueError) as exc:
        raise ReaderError(path, f"unreadable or truncated PNG ({exc})") from None
    if mode not in ("I;16", "I;16B", "I;16L", "I") or depth_raw.ndim != 2:
        raise ReaderError(path, f"expected a single-channel 16-bit depth image, got mode {mode} "
                          f"with shape {depth_raw.shape}")
    if intrinsics is None:
        calib = next((path.parent / n for n in _CALIB_NAMES if (path.parent / n).is_file()), None)
        if calib is None:
            raise ReaderError(path, "a depth image needs pinhole intrinsics: give --intrinsics fx fy cx cy or "
                              f"--intrinsics-file (none of {', '.join(_CALIB_NAMES)} beside the image)")
        intrinsics = load_intrinsics(calib)
    height, width = depth_raw.shape
    d = depth_raw.astype(np.float64) * depth_scale
    d[d <= 0] = np.nan
    u = (np.arange(width) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(height) - intrinsics.cy) / intrinsics.fy
    pts = np.stack([d * u[None, :], d * v[:, None], d], axis=-1)
    rng, pts = _finish(path, pts)
    rng, pts, n_out, note = _drop_out_of_range(path, rng, pts, preset)
    notes = [note] if note else []
    if any(abs(c) > 0 for c in intrinsics.distortion):
        notes.append("lens distortion coefficients present but not applied")
    sensor = _pinhole(intrinsics, width, height, rng, _preset_limits(preset) if preset else (0.0, 1.0))
    info = ReadInfo(str(path), "png/16-bit", int(np.count_nonzero(depth_raw)), int(np.isfinite(rng).sum()), True,
                    "pinhole", intrinsics.source, np.eye(4), preset, 0, tuple(notes), n_out_of_range=n_out,
                    working_range_m=_working_range(preset))
    return LoadedScan(Scan(rng, pts, sensor, noise), info)


# ------------------------------------------------------------------------------------------------ NPZ


def read_npz(path: str | Path) -> LoadedScan:
    """Read the project's own ``.npz`` scan (:func:`sensors.io.load_npz`); its truth, if any, is dropped."""
    import zipfile

    from sensors.io import load_npz

    path = Path(path)
    if not zipfile.is_zipfile(path):
        raise ReaderError(path, "not a readable scan .npz (not a zip archive)")
    try:
        scan = load_npz(path).scan
    except ValueError as exc:
        msg = str(exc)
        raise ReaderError(path, msg.split(": ", 1)[1] if msg.startswith(str(path)) else msg) from None
    except (OSError, zipfile.BadZipFile, KeyError, EOFError) as exc:
        raise ReaderError(path, f"not a readable scan .npz ({exc})") from None
    if not np.isfinite(scan.range).any():
        raise ReaderError(path, "no valid depth: every pixel is NaN")
    info = ReadInfo(str(path), "npz", int(np.isfinite(scan.range).sum()), int(np.isfinite(scan.range).sum()), True,
                    scan.sensor.kind, "file", np.eye(4), "file")
    return LoadedScan(scan, info)
