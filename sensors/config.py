"""Sensor configuration files: a sensor model, its noise model and an optional default pose.

YAML layout (schema ``sensor/1``; lengths in metres, angles in degrees with a ``_deg`` suffix)::

    schema: sensor/1
    name: kinect_like
    description: free text
    pinhole:                      # exactly one of `pinhole` or `laser`
      width: 640
      height: 480
      fov_deg: [57.0, 43.0]       # horizontal [, vertical]; or `intrinsics: {fx, fy, cx, cy}` (pixels)
      min_range: 0.5
      max_range: 4.5
    laser:
      n_azimuth: 640
      n_elevation: 480
      azimuth_deg: [-40, 40]
      elevation_deg: [-30, 30]
      min_range: 0.5
      max_range: 20.0
    pose:                         # optional default T_world_sensor
      position: [0, -3, 1.5]
      look_at: [0, 0, 0.5]
      up: [0, 0, 1]               # optional
      # or  matrix: 4 rows of 4 numbers
    noise:                        # every section optional; an absent section is that term switched off
      enabled: true
      range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
      #      {model: kinect_axial, s0_m: 0.0012, s2_per_m: 0.0019, z0_m: 0.4, incidence_coeff_m: 1.0e-4}
      #      matching_window_px: 7 (either model) correlates the errors over a 7 x 7 matching window
      quantisation: {mode: range, step_m: 5.0e-5}     # or {mode: inverse_depth, step_per_m: 2.85e-3}
      grazing: {start_deg: 70, end_deg: 85}
      footprint: {rays: 4, radius_px: 0.5, min_return_fraction: 0.5, mixed_threshold_sigma: 3}
      specular: {metal: 0.02, glossy: 0.1}            # dropout probability per material
      outliers: {rate: 1.0e-4}

Shipped presets live in ``sensors/presets/<name>.yaml``; :func:`load_sensor` accepts a preset name or a path.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scenes.config import ConfigError, Fields, check_number, load_yaml, parse_yaml, show
from scenes.features import MATERIALS
from scenes.geometry import check_transform, look_at
from sensors.models import PinholeCamera, ScanningLaser, SensorModel
from sensors.noise import QUANTISATION_MODES, RANGE_MODELS, NoiseModel

SCHEMA = "sensor/1"
MAX_PIXELS = 2048 * 2048  # largest image a sensor may produce; the core refuses larger ones (memory, see describe)
PRESET_DIR = Path(__file__).parent / "presets"


@dataclass(frozen=True)
class SensorConfig:
    """A configured sensor: geometry, noise, name and optional default pose ``T_world_sensor`` (4, 4)."""

    model: SensorModel
    noise: NoiseModel
    name: str = "sensor"
    T_world_sensor: np.ndarray | None = field(default=None, compare=False)
    description: str = ""

    def with_noise(self, noise: NoiseModel) -> SensorConfig:
        return dataclasses.replace(self, noise=noise)

    def with_model(self, model: SensorModel) -> SensorConfig:
        return dataclasses.replace(self, model=model)


def preset_names() -> tuple[str, ...]:
    """Names of the shipped presets."""
    return tuple(sorted(p.stem for p in PRESET_DIR.glob("*.yaml")))


def load_sensor(spec: str | Path) -> SensorConfig:
    """Load a sensor from a YAML file path or a preset name.

    Raises
    ------
    ConfigError
        Unknown preset (and no such file), or an invalid file (naming the field and the reason).
    """
    path = Path(spec)
    if path.suffix in (".yaml", ".yml") or _exists(path):
        if not _exists(path):
            raise ConfigError(str(spec), "", "no such sensor file")
        return sensor_from_dict(load_yaml(path), str(path))
    name = str(spec)
    preset = PRESET_DIR / f"{name}.yaml"
    if not _exists(preset):
        raise ConfigError("", "", f"unknown sensor preset {name!r} (known presets: {', '.join(preset_names())}; "
                          "or give a path to a .yaml file)")
    return sensor_from_dict(load_yaml(preset), f"preset {name}")


def _exists(path: Path) -> bool:
    try:
        return path.exists()
    except OSError:  # e.g. a name too long for the file system: no such file
        return False


def sensor_from_yaml(text: str, source: str = "<string>") -> SensorConfig:
    return sensor_from_dict(parse_yaml(text, source), source)


def sensor_from_dict(data: Any, source: str = "<sensor>") -> SensorConfig:
    """Build and validate a :class:`SensorConfig` from plain data (the YAML layout in the module docstring)."""
    root = Fields(data, source)
    schema = root.string("schema", SCHEMA)
    if schema != SCHEMA:
        raise root.error("schema", f"unsupported schema {schema!r} (expected {SCHEMA!r})")
    name = root.string("name", "sensor")
    description = root.raw("description", "")
    if not isinstance(description, str):
        raise root.error("description", f"expected a string, got {show(description)}")
    kinds = [k for k in ("pinhole", "laser") if root.has(k)]
    if len(kinds) != 1:
        raise root.error(None, "needs exactly one of the sections 'pinhole' or 'laser'"
                         + (", got both" if len(kinds) == 2 else ""))
    model = _pinhole(root.sub("pinhole")) if kinds[0] == "pinhole" else _laser(root.sub("laser"))
    noise = _noise(root.sub("noise", None)) if root.has("noise") else NoiseModel(enabled=False)
    T = _pose(root.sub("pose")) if root.has("pose") else None
    root.check_unknown()
    return SensorConfig(model, noise, name, T, description)


def _wrap(f: Fields, build):
    try:
        return build()
    except ConfigError:
        raise
    except ValueError as exc:
        raise ConfigError(f.source, f.path, str(exc)) from None


def _check_pixels(f: Fields, width: int, height: int) -> None:
    if width * height > MAX_PIXELS:
        raise f.error(None, f"{width} x {height} = {width * height} pixels is more than the {MAX_PIXELS} "
                            "(2048 x 2048) a simulated scan may have (memory grows with the pixel count)")


def _range_limits(f: Fields) -> tuple[float, float]:
    lo = f.number("min_range", 0.0, nonnegative=True)
    hi = f.number("max_range", positive=True)
    if hi <= lo:
        raise f.error("max_range", f"must be > min_range ({lo:g}), got {hi:g}")
    return lo, hi


def _pinhole(f: Fields) -> PinholeCamera:
    width = f.integer("width", min=1)
    height = f.integer("height", min=1)
    _check_pixels(f, width, height)
    lo, hi = _range_limits(f)
    if f.has("intrinsics"):
        if f.has("fov_deg"):
            raise f.error("fov_deg", "give either fov_deg or intrinsics, not both")
        k = f.sub("intrinsics")
        fx, fy = k.number("fx", positive=True), k.number("fy", positive=True)
        cx, cy = k.number("cx", (width - 1) / 2.0), k.number("cy", (height - 1) / 2.0)
        k.check_unknown()
        f.check_unknown()
        return _wrap(f, lambda: PinholeCamera(width, height, fx, fy, cx, cy, lo, hi))
    fov = f.raw("fov_deg")
    values = fov if isinstance(fov, list) else [fov]
    if len(values) not in (1, 2):
        raise f.error("fov_deg", f"expected a number or [horizontal, vertical], got {show(fov)}")
    angles = []
    for i, v in enumerate(values):
        path = f.child_path("fov_deg") + (f"[{i}]" if isinstance(fov, list) else "")
        a = check_number(v, f.source, path, positive=True)
        if a >= 180:
            raise ConfigError(f.source, path, f"must be < 180, got {a:g}")
        angles.append(a)
    f.check_unknown()
    return _wrap(f, lambda: PinholeCamera.from_fov(width, height, angles[0], angles[1] if len(angles) > 1 else None,
                                                   min_range=lo, max_range=hi))


def _angle_pair(f: Fields, key: str, limit: float) -> tuple[float, float]:
    value = f.raw(key)
    path = f.child_path(key)
    if not isinstance(value, list) or len(value) != 2:
        raise ConfigError(f.source, path, f"expected [min, max] in degrees, got {show(value)}")
    a, b = (Fields({"x": v}, f.source, f"{path}[{i}]").number("x", min=-limit, max=limit)
            for i, v in enumerate(value))
    if b <= a:
        raise ConfigError(f.source, path, f"max must be > min, got [{a:g}, {b:g}]")
    return math.radians(a), math.radians(b)


def _laser(f: Fields) -> ScanningLaser:
    n_az = f.integer("n_azimuth", min=1)
    n_el = f.integer("n_elevation", min=1)
    _check_pixels(f, n_az, n_el)
    az = _angle_pair(f, "azimuth_deg", 180.0)
    el = _angle_pair(f, "elevation_deg", 90.0)
    lo, hi = _range_limits(f)
    f.check_unknown()
    return _wrap(f, lambda: ScanningLaser(n_az, n_el, az[0], az[1], el[0], el[1], lo, hi))


def _pose(f: Fields) -> np.ndarray:
    if f.has("matrix"):
        rows = f.raw("matrix")
        if not isinstance(rows, list) or len(rows) != 4:
            raise f.error("matrix", "expected 4 rows of 4 numbers")
        T = np.array([Fields({"r": r}, f.source, f.child_path("matrix")).vector("r", size=4) for r in rows])
        f.check_unknown()
        return _wrap(f, lambda: check_transform(T, f"{f.path}.matrix"))
    position = f.vector("position")
    target = f.vector("look_at")
    up = f.vector("up", [0.0, 0.0, 1.0], nonzero=True)
    f.check_unknown()
    return _wrap(f, lambda: look_at(position, target, up))


def _noise(f: Fields) -> NoiseModel:
    kw: dict[str, Any] = {"enabled": f.boolean("enabled", True)}
    if f.has("range"):
        r = f.sub("range")
        kw["range_model"] = r.string("model", "ray", choices=RANGE_MODELS)
        kw["s0_m"] = r.number("s0_m", 0.0, nonnegative=True)
        kw["s2_per_m"] = r.number("s2_per_m", 0.0, nonnegative=True)
        kw["max_incidence"] = math.radians(r.number("max_incidence_deg", 80.0, min=0.0))
        kw["matching_window_px"] = r.integer("matching_window_px", 1, min=1, max=64)
        if kw["max_incidence"] >= math.pi / 2:
            raise r.error("max_incidence_deg", f"must be < 90, got {math.degrees(kw['max_incidence']):g}")
        if kw["range_model"] == "kinect_axial":
            kw["z0_m"] = r.number("z0_m", 0.0, nonnegative=True)
            kw["incidence_coeff_m"] = r.number("incidence_coeff_m", 0.0, nonnegative=True)
        r.check_unknown()
    if f.has("quantisation"):
        q = f.sub("quantisation")
        mode = q.string("mode", "range", choices=QUANTISATION_MODES)
        kw["quantisation_mode"] = mode
        kw["quantisation_step"] = q.number("step_m" if mode == "range" else "step_per_m", positive=True)
        q.check_unknown()
    if f.has("grazing"):
        g = f.sub("grazing")
        start = g.number("start_deg", min=0.0, max=90.0)
        end = g.number("end_deg", start, min=0.0, max=90.0)
        if end < start:
            raise g.error("end_deg", f"must be >= start_deg ({start:g}), got {end:g}")
        kw["grazing_start"], kw["grazing_end"] = math.radians(start), math.radians(end)
        g.check_unknown()
    if f.has("footprint"):
        p = f.sub("footprint")
        kw["footprint_rays"] = p.integer("rays", 1, min=1, max=64)
        kw["footprint_radius_px"] = p.number("radius_px", 0.5, nonnegative=True)
        kw["min_return_fraction"] = p.number("min_return_fraction", 0.5, positive=True, max=1.0)
        kw["mixed_threshold_sigma"] = p.number("mixed_threshold_sigma", 3.0, nonnegative=True)
        p.check_unknown()
    if f.has("specular"):
        s = f.sub("specular")
        probs = []
        for material in list(s.data):
            if material not in MATERIALS:
                raise s.error(str(material), f"unknown material (known: {', '.join(MATERIALS)})")
            probs.append((material, s.number(material, min=0.0, max=1.0)))
        kw["specular_dropout"] = tuple(probs)
    if f.has("outliers"):
        o = f.sub("outliers")
        kw["outlier_rate"] = o.number("rate", min=0.0, max=1.0)
        o.check_unknown()
    f.check_unknown()
    return _wrap(f, lambda: NoiseModel(**kw))


# -- exact plain-data forms (for .npz metadata and JSON summaries) -------------------------------
def sensor_model_to_dict(model: SensorModel) -> dict[str, Any]:
    """Exact plain-data form of a sensor model (internal units: radians)."""
    return {"kind": model.kind, **dataclasses.asdict(model)}


def sensor_model_from_dict(d: dict[str, Any]) -> SensorModel:
    d = dict(d)
    kind = d.pop("kind")
    cls = {"pinhole": PinholeCamera, "laser": ScanningLaser}.get(kind)
    if cls is None:
        raise ValueError(f"unknown sensor kind {kind!r}")
    return cls(**d)


def noise_to_dict(noise: NoiseModel) -> dict[str, Any]:
    """Exact plain-data form of a noise model (internal units: radians)."""
    d = dataclasses.asdict(noise)
    d["specular_dropout"] = [list(p) for p in noise.specular_dropout]
    return d


def noise_from_dict(d: dict[str, Any]) -> NoiseModel:
    d = dict(d)
    d["specular_dropout"] = tuple(tuple(p) for p in d.get("specular_dropout", ()))
    return NoiseModel(**d)


__all__ = ["SensorConfig", "load_sensor", "sensor_from_dict", "sensor_from_yaml", "preset_names", "PRESET_DIR",
           "sensor_model_to_dict", "sensor_model_from_dict", "noise_to_dict", "noise_from_dict", "SCHEMA",
           "MAX_PIXELS"]
