"""Readers of real range data (sensors.readers, sensors.lzf) on small files written here."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from scenes.config import ConfigError
from sensors.config import load_sensor
from sensors.io import save_npz
from sensors.lzf import LZFError, decompress
from sensors.models import PinholeCamera, ScanningLaser
from sensors.range_image import Scan
from sensors.readers import (
    Intrinsics,
    ReaderError,
    estimate_intrinsics,
    load_intrinsics,
    load_scan,
    organise_cloud,
    read_scan,
)

K = (300.0, 310.0, 20.3, 14.6)  # fx fy cx cy of the synthetic camera
H, W = 30, 40


# ------------------------------------------------------------------------------------------------ helpers


def lzf_compress(data: bytes) -> bytes:
    """A small greedy LZF compressor (3-byte hash of the last position), for round-trip tests."""
    out = bytearray()
    lit = bytearray()
    table: dict[bytes, int] = {}
    i, n = 0, len(data)

    def flush():
        for k in range(0, len(lit), 32):
            chunk = lit[k:k + 32]
            out.append(len(chunk) - 1)
            out.extend(chunk)
        lit.clear()

    while i < n:
        key = data[i:i + 3]
        ref = table.get(key) if len(key) == 3 else None
        table[key] = i
        if ref is not None and 0 < i - ref <= 8192:
            length = 0
            while i + length < n and length < 264 and data[ref + length] == data[i + length]:
                length += 1
            if length >= 3:
                flush()
                off = i - ref - 1
                ln = length - 2
                if ln < 7:
                    out.append((ln << 5) | (off >> 8))
                else:
                    out.append((7 << 5) | (off >> 8))
                    out.append(ln - 7)
                out.append(off & 0xFF)
                i += length
                continue
        lit.append(data[i])
        i += 1
    flush()
    return bytes(out)


def organised_points(rng: np.random.Generator | None = None) -> np.ndarray:
    """A (H, W, 3) cloud of a tilted plane seen by the pinhole camera K, with a few holes (NaN)."""
    fx, fy, cx, cy = K
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    x, y = (u - cx) / fx, (v - cy) / fy
    z = 1.5 / (1.0 + 0.3 * x + 0.2 * y)  # plane 0.3 X + 0.2 Y + Z = 1.5
    pts = np.stack([x * z, y * z, z], axis=-1)
    pts[3:6, 7:9] = np.nan
    pts[0, :] = np.nan
    return pts


def write_pcd(path, pts: np.ndarray, mode: str, extra_rgb: bool = True, header_edit=None) -> None:
    h, w = pts.shape[:2]
    flat = pts.reshape(-1, 3).astype("<f4")
    n = len(flat)
    rgb = np.arange(n, dtype="<u4")
    fields = ["x", "y", "z"] + (["rgba"] if extra_rgb else [])
    header = {"VERSION": "0.7", "FIELDS": " ".join(fields), "SIZE": " ".join(["4"] * len(fields)),
              "TYPE": " ".join(["F"] * 3 + (["U"] if extra_rgb else [])), "COUNT": " ".join(["1"] * len(fields)),
              "WIDTH": str(w), "HEIGHT": str(h), "VIEWPOINT": "0 0 0 1 0 0 0", "POINTS": str(n), "DATA": mode}
    if header_edit:
        header.update(header_edit)
    text = "# .PCD v0.7 - Point Cloud Data file format\n" + "".join(f"{k} {v}\n" for k, v in header.items() if v)
    if mode == "ascii":
        body = "\n".join(" ".join(["nan" if not np.isfinite(c) else repr(float(c)) for c in p]
                                  + ([str(r)] if extra_rgb else [])) for p, r in zip(flat, rgb, strict=True))
        path.write_bytes(text.encode() + body.encode() + b"\n")
        return
    if mode == "binary":
        rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + ([("c", "<u4")] if extra_rgb else []))
        rec["x"], rec["y"], rec["z"] = flat.T
        if extra_rgb:
            rec["c"] = rgb
        path.write_bytes(text.encode() + rec.tobytes())
        return
    soa = flat.T.tobytes() + (rgb.tobytes() if extra_rgb else b"")
    comp = lzf_compress(soa)
    path.write_bytes(text.encode() + struct.pack("<II", len(comp), len(soa)) + comp)


def write_ply(path, pts: np.ndarray, fmt: str = "binary_little_endian", with_faces: bool = False) -> None:
    n = len(pts)
    header = ["ply", f"format {fmt} 1.0", "comment test", f"element vertex {n}", "property double x",
              "property double y", "property double z", "property uchar red"]
    if with_faces:
        header += ["element face 1", "property list uchar int vertex_indices"]
    header.append("end_header")
    head = ("\n".join(header) + "\n").encode()
    if fmt == "ascii":
        body = "".join(f"{p[0]!r} {p[1]!r} {p[2]!r} 7\n" for p in pts.tolist())
        if with_faces:
            body += "3 0 1 2\n"
        path.write_bytes(head + body.encode())
        return
    e = "<" if fmt == "binary_little_endian" else ">"
    rec = np.empty(n, dtype=[("x", e + "f8"), ("y", e + "f8"), ("z", e + "f8"), ("r", "u1")])
    rec["x"], rec["y"], rec["z"], rec["r"] = pts[:, 0], pts[:, 1], pts[:, 2], 7
    tail = (b"\x03" + np.array([0, 1, 2], dtype=e + "i4").tobytes()) if with_faces else b""
    path.write_bytes(head + rec.tobytes() + tail)


def lattice_cloud_opengl(f: float = 400.0, n: tuple[int, int] = (50, 40)) -> np.ndarray:
    """A depth-camera lattice (focal f, pixel centres) of a box corner, in OpenGL convention (looking down -z)."""
    u, v = np.meshgrid(np.arange(n[0]) - 24.3, np.arange(n[1]) - 17.8)
    x, y = u / f, v / f
    z = np.where(x < 0, 2.0 - 0.5 * x, 2.0 + 0.8 * x)  # two planes meeting at a crease
    pts = np.stack([x * z, y * z, z], axis=-1).reshape(-1, 3)
    return pts * np.array([1.0, -1.0, -1.0])  # OpenCV -> OpenGL


# ------------------------------------------------------------------------------------------------ LZF


def test_lzf_hand_made_streams():
    assert decompress(bytes([2]) + b"abc" + bytes([0x20, 2]), 6) == b"abcabc"  # non-overlapping reference
    assert decompress(bytes([0]) + b"a" + bytes([0xE0, 3, 0]), 13) == b"a" * 13  # overlapping run, long length
    assert decompress(b"", 0) == b""


@pytest.mark.parametrize(("stream", "size", "match"), [
    (bytes([5]) + b"abc", 6, "truncated LZF stream: a literal run"),
    (bytes([0]) + b"a" + bytes([0xE0]), 13, "lacks its length byte"),
    (bytes([0]) + b"a" + bytes([0x20]), 4, "lacks its offset byte"),
    (bytes([0]) + b"a" + bytes([0x20, 5]), 4, "back reference 6 bytes behind output position 1"),
    (bytes([2]) + b"abc", 4, "decodes to 3 bytes, expected 4"),
    (bytes([2]) + b"abc", 2, "more than the expected 2 bytes"),
])
def test_lzf_bad_streams(stream, size, match):
    with pytest.raises(LZFError, match=match):
        decompress(stream, size)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from([b"a", b"b", b"xyz", b"\x00\x00\x00\x00", b"q"]), max_size=400), st.binary(max_size=64))
def test_lzf_round_trip(chunks, noise):
    data = b"".join(chunks) + noise
    assert decompress(lzf_compress(data), len(data)) == data


# ------------------------------------------------------------------------------------------------ PCD


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_organised_round_trip(tmp_path, mode):
    pts = organised_points()
    path = tmp_path / f"cloud_{mode}.pcd"
    write_pcd(path, pts, mode)
    loaded = load_scan(path)
    scan = loaded.scan
    assert scan.shape == (H, W)
    expected = pts.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(np.isnan(scan.points[..., 0]), np.isnan(pts[..., 0]))
    np.testing.assert_allclose(scan.points, expected, equal_nan=True)
    np.testing.assert_allclose(scan.range, np.linalg.norm(expected, axis=-1), equal_nan=True)
    assert isinstance(scan.sensor, PinholeCamera)
    np.testing.assert_allclose([scan.sensor.fx, scan.sensor.fy, scan.sensor.cx, scan.sensor.cy], K, rtol=1e-4,
                               atol=1e-3)
    assert loaded.info.format == f"pcd/{mode}" and loaded.info.organised
    assert loaded.info.n_valid == int(np.isfinite(pts[..., 0]).sum())
    assert scan.noise == load_sensor("kinect_like").noise


def test_pcd_given_intrinsics_and_preset(tmp_path):
    path = tmp_path / "c.pcd"
    write_pcd(path, organised_points(), "binary")
    scan = read_scan(path, intrinsics=(100.0, 100.0, 20.0, 15.0), sensor_preset="factory_scanner")
    assert (scan.sensor.fx, scan.sensor.cx) == (100.0, 20.0)
    assert scan.noise == load_sensor("factory_scanner").noise


def test_estimate_intrinsics_recovers_camera():
    est, rms = estimate_intrinsics(organised_points())
    np.testing.assert_allclose([est.fx, est.fy, est.cx, est.cy], K, rtol=1e-9)
    assert rms < 1e-6


def test_pcd_unorganised_is_projected(tmp_path):
    cloud = lattice_cloud_opengl() * np.array([1.0, -1.0, -1.0])  # back to OpenCV: looking along +z
    path = tmp_path / "flat.pcd"
    write_pcd(path, cloud.reshape(1, -1, 3), "binary", extra_rgb=False)
    loaded = load_scan(path)
    assert not loaded.info.organised and loaded.info.n_collisions == 0
    assert loaded.info.n_valid == len(cloud)


@pytest.mark.parametrize(("content", "match"), [
    (b"", "not a PCD file"),
    (b"hello world\nDATA ascii\n", "not a PCD file: unknown header line 'hello world'"),
    (b"VERSION 0.7\nFIELDS x y z\n", "header has no DATA line"),
])
def test_pcd_bad_header(tmp_path, content, match):
    path = tmp_path / "bad.pcd"
    path.write_bytes(content)
    with pytest.raises(ReaderError, match=match) as exc:
        read_scan(path)
    assert "bad.pcd" in str(exc.value)


@pytest.mark.parametrize(("edit", "match"), [
    ({"FIELDS": "x y w rgba"}, "unknown field layout: no z field"),
    ({"TYPE": "F F X U"}, "unknown field layout: field 'z' has TYPE X and SIZE 4"),
    ({"SIZE": "4 4 4"}, r"unknown field layout: FIELDS \(4\), SIZE \(3\)"),
    ({"POINTS": "17"}, "POINTS 17 != WIDTH x HEIGHT"),
    ({"WIDTH": "forty"}, "non-integer"),
])
def test_pcd_unknown_layout(tmp_path, edit, match):
    path = tmp_path / "bad.pcd"
    write_pcd(path, organised_points(), "binary", header_edit=edit)
    with pytest.raises(ReaderError, match=match):
        read_scan(path)


@pytest.mark.parametrize("mode", ["ascii", "binary", "binary_compressed"])
def test_pcd_truncated(tmp_path, mode):
    path = tmp_path / "t.pcd"
    write_pcd(path, organised_points(), mode)
    data = path.read_bytes()
    path.write_bytes(data[:len(data) - 200])
    with pytest.raises(ReaderError, match="truncated|corrupt"):
        read_scan(path)


def test_pcd_corrupt_compressed(tmp_path):
    path = tmp_path / "c.pcd"
    write_pcd(path, organised_points(), "binary_compressed")
    data = bytearray(path.read_bytes())
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n") + 8
    data[start] = 0xFF  # a back reference before the start of the output
    path.write_bytes(bytes(data))
    with pytest.raises(ReaderError, match="corrupt binary_compressed data"):
        read_scan(path)


def test_pcd_all_nan_is_an_error(tmp_path):
    path = tmp_path / "empty.pcd"
    write_pcd(path, np.full((H, W, 3), np.nan), "binary")
    with pytest.raises(ReaderError, match="no valid depth"):
        read_scan(path)


# ------------------------------------------------------------------------------------------------ PLY


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_lattice_is_organised_back(tmp_path, fmt):
    """A cloud made from a depth-camera lattice (OpenGL frame) lands one point per pixel, focal recovered."""
    cloud = lattice_cloud_opengl(f=400.0)
    path = tmp_path / "c.ply"
    write_ply(path, cloud, fmt, with_faces=True)
    loaded = load_scan(path)
    scan, info = loaded.scan, loaded.info
    assert isinstance(scan.sensor, PinholeCamera) and info.grid == "pinhole" and not info.organised
    assert scan.sensor.fx == pytest.approx(400.0, rel=1e-6)
    assert info.n_collisions == 0 and info.n_valid == len(cloud)
    np.testing.assert_allclose(info.T_file_sensor[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    # the exact points are kept: mapped back to the file's frame they are the file's points
    p = scan.points[scan.valid]
    back = p @ info.T_file_sensor[:3, :3].T + info.T_file_sensor[:3, 3]
    order = np.lexsort(back.T), np.lexsort(cloud.T)
    np.testing.assert_allclose(back[order[0]], cloud[order[1]], atol=1e-12)
    # every point sits within half a pixel of its pixel's ray
    rows, cols = np.nonzero(scan.valid)
    u = scan.sensor.fx * p[:, 0] / p[:, 2] + scan.sensor.cx
    v = scan.sensor.fy * p[:, 1] / p[:, 2] + scan.sensor.cy
    assert np.max(np.abs(u - cols)) < 0.5 and np.max(np.abs(v - rows)) < 0.5


def test_ply_nearest_point_wins(tmp_path):
    cloud = lattice_cloud_opengl()
    behind = cloud[:10] * 1.5  # same directions, farther
    path = tmp_path / "c.ply"
    write_ply(path, np.concatenate([behind, cloud]))
    loaded = load_scan(path)
    assert loaded.info.n_collisions == 10
    assert np.nanmax(loaded.scan.range) < np.max(np.linalg.norm(behind, axis=1))


def test_ply_wide_cloud_gets_a_spherical_grid(tmp_path):
    az = np.radians(np.arange(-100.0, 100.0, 0.5))
    el = np.radians(np.arange(-20.0, 20.0, 0.5))
    A, E = np.meshgrid(az, el)
    d = np.stack([np.cos(E) * np.sin(A), -np.sin(E), np.cos(E) * np.cos(A)], axis=-1).reshape(-1, 3)
    path = tmp_path / "wide.ply"
    write_ply(path, 3.0 * d)
    loaded = load_scan(path)
    scan = loaded.scan
    assert isinstance(scan.sensor, ScanningLaser) and loaded.info.grid == "laser"
    assert loaded.info.n_collisions == 0
    # every point lies along its pixel's ray (within half a grid step)
    rays = scan.sensor.ray_directions()[scan.valid]
    dirs = scan.points[scan.valid] / scan.range[scan.valid][:, None]
    assert np.degrees(np.max(np.arccos(np.clip(np.sum(rays * dirs, axis=1), -1, 1)))) < 0.5
    np.testing.assert_allclose(scan.range[scan.valid], 3.0)


def test_ply_origin_and_direction(tmp_path):
    cloud = lattice_cloud_opengl()
    path = tmp_path / "c.ply"
    write_ply(path, cloud + np.array([1.0, 2.0, 3.0]))
    loaded = load_scan(path, origin=(1.0, 2.0, 3.0), view_direction=(0.0, 0.0, -1.0))
    assert loaded.info.n_collisions == 0 and loaded.scan.sensor.fx == pytest.approx(400.0)
    np.testing.assert_allclose(loaded.info.T_file_sensor[:3, 3], [1.0, 2.0, 3.0])


@pytest.mark.parametrize(("content", "match"), [
    (b"hello", "not a PLY file"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n", "no end_header"),
    (b"ply\nformat weird 1.0\nend_header\n", "unknown PLY format"),
    (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "PLY has no vertex element"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
     "unknown field layout: vertex has no z property"),
    (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n1 2 3\n", "truncated: 1 vertex lines, expected 3"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
     b"property float z\nend_header\n" + b"\x00" * 20, "truncated: vertex data have 20 bytes, expected 36"),
    (b"ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n" + b"0 0 0\n" * 10, "no valid depth"),
])
def test_ply_bad_files(tmp_path, content, match):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(ReaderError, match=match) as exc:
        read_scan(path)
    assert "bad.ply" in str(exc.value)


def test_organise_cloud_rejects_behind_for_pinhole():
    pts = np.concatenate([lattice_cloud_opengl(), [[0.0, 0.0, 5.0]]])
    with pytest.raises(ReaderError, match="beside or behind"):
        organise_cloud(pts, noise=load_sensor("kinect_like").noise, grid="pinhole",
                       view_direction=(0.0, 0.0, -1.0))


# ------------------------------------------------------------------------------------------------ PNG


def write_depth_png(path, depth_mm: np.ndarray) -> None:
    Image.fromarray(depth_mm.astype(np.uint16)).save(path)


def test_depth_png_back_projection(tmp_path):
    depth = np.full((H, W), 1500, np.uint16)
    depth[2:5, 3:6] = 0
    depth[10, 10] = 2345
    path = tmp_path / "d.png"
    write_depth_png(path, depth)
    loaded = load_scan(path, intrinsics=K)
    scan = loaded.scan
    fx, fy, cx, cy = K
    assert np.isnan(scan.range[3, 4]) and not scan.valid[2:5, 3:6].any()
    np.testing.assert_allclose(scan.points[10, 10], [2.345 * (10 - cx) / fx, 2.345 * (10 - cy) / fy, 2.345])
    np.testing.assert_allclose(scan.depth[scan.valid & (depth == 1500)], 1.5)
    assert loaded.info.n_valid == int(np.count_nonzero(depth))
    # depth scale: 1.5 mm units (within kinect_like's working range, 0.5-4.5 m)
    scan2 = read_scan(path, intrinsics=K, depth_scale=1.5e-3)
    assert scan2.depth[10, 10] == pytest.approx(3.5175)
    # the sensor's rays go through the points
    rays = scan.sensor.ray_directions()
    np.testing.assert_allclose(scan.points[scan.valid], (rays * scan.range[..., None])[scan.valid], atol=1e-12)


CAPE_XML = """<?xml version="1.0"?>
<opencv_storage>
<RGB_intrinsic_params type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt>
  <data>5.0e+02 0. 3.0e+02 0. 5.1e+02 2.0e+02 0. 0. 1.</data></RGB_intrinsic_params>
<IR_intrinsic_params type_id="opencv-matrix"><rows>3</rows><cols>3</cols><dt>d</dt>
  <data>300. 0. 20.3 0. 310. 14.6 0. 0. 1.</data></IR_intrinsic_params>
<IR_distortion_coefficients type_id="opencv-matrix"><rows>1</rows><cols>5</cols><dt>d</dt>
  <data>0.1 0.2 0. 0. 0.3</data></IR_distortion_coefficients>
</opencv_storage>
"""


def test_depth_png_intrinsics_files(tmp_path):
    path = tmp_path / "d.png"
    write_depth_png(path, np.full((H, W), 1000))
    with pytest.raises(ReaderError, match="needs pinhole intrinsics"):
        read_scan(path)
    (tmp_path / "calib_params.xml").write_text(CAPE_XML)
    loaded = load_scan(path)  # found beside the image, IR (depth) camera preferred over RGB
    s = loaded.scan.sensor
    assert (s.fx, s.fy, s.cx, s.cy) == K
    assert "IR_intrinsic_params" in loaded.info.intrinsics_source
    assert any("distortion" in n for n in loaded.info.notes)
    yaml_file = tmp_path / "k.yaml"
    yaml_file.write_text("intrinsics: {fx: 100, fy: 101, cx: 19.5, cy: 14.5}\n")
    assert read_scan(path, intrinsics_file=yaml_file).sensor.fy == 101.0
    yaml_file.write_text("K: [[100, 0, 19.5], [0, 102, 14.5], [0, 0, 1]]\n")
    assert load_intrinsics(yaml_file).fy == 102.0


@pytest.mark.parametrize(("text", "match"), [
    ("fx: 1\n", "no intrinsics found"),
    ("K: [1, 2, 3]\n", "expected a 3x3 matrix"),
    ("fx: 0\nfy: 1\ncx: 0\ncy: 0\n", "focal lengths must be > 0"),
])
def test_bad_intrinsics_yaml(tmp_path, text, match):
    f = tmp_path / "k.yaml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=match):
        load_intrinsics(f)


def test_bad_intrinsics_xml(tmp_path):
    f = tmp_path / "k.xml"
    f.write_text("<opencv_storage><foo>1</foo></opencv_storage>")
    with pytest.raises(ConfigError, match="no intrinsic matrix found"):
        load_intrinsics(f)
    f.write_text("<opencv_storage><camera_matrix")
    with pytest.raises(ConfigError, match="not a readable XML file"):
        load_intrinsics(f)


def test_depth_png_bad_files(tmp_path):
    zero = tmp_path / "zero.png"
    write_depth_png(zero, np.zeros((H, W)))
    with pytest.raises(ReaderError, match="zero.png: no valid depth"):
        read_scan(zero, intrinsics=K)
    grey = tmp_path / "grey.png"
    Image.fromarray(np.full((H, W), 7, np.uint8)).save(grey)
    with pytest.raises(ReaderError, match="expected a single-channel 16-bit depth image, got mode L"):
        read_scan(grey, intrinsics=K)
    rgb = tmp_path / "rgb.png"
    Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(rgb)
    with pytest.raises(ReaderError, match="got mode RGB"):
        read_scan(rgb, intrinsics=K)
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not a png at all")
    with pytest.raises(ReaderError, match="junk.png: not a PNG image"):
        read_scan(junk, intrinsics=K)
    cut = tmp_path / "cut.png"
    write_depth_png(cut, np.arange(H * W).reshape(H, W))
    cut.write_bytes(cut.read_bytes()[:60])
    with pytest.raises(ReaderError, match="cut.png: unreadable or truncated PNG"):
        read_scan(cut, intrinsics=K)


# ------------------------------------------------------------------------------------------------ NPZ and dispatch


def test_npz_round_trip(tmp_path):
    cam = PinholeCamera(W, H, *K, 0.5, 4.5)
    pts = organised_points()
    scan = Scan(np.linalg.norm(pts, axis=-1), pts, cam, load_sensor("mockup_laser").noise)
    path = tmp_path / "s.npz"
    save_npz(path, scan)
    back = read_scan(path, sensor_preset="kinect_like")  # the file's own noise model wins
    np.testing.assert_array_equal(back.points, scan.points)
    assert back.sensor == cam and back.noise == scan.noise


def test_bad_npz_and_dispatch(tmp_path):
    bad = tmp_path / "bad.npz"
    np.savez(bad, a=np.zeros(3))
    with pytest.raises(ReaderError, match="bad.npz: not a scan file"):
        read_scan(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"junk")
    with pytest.raises(ReaderError, match="junk.npz: not a readable scan .npz"):
        read_scan(junk)
    with pytest.raises(ReaderError, match="unknown range data format '.xyz'"):
        read_scan(tmp_path / "cloud.xyz")
    with pytest.raises(ReaderError, match="missing.pcd: no such file"):
        read_scan(tmp_path / "missing.pcd")
    good = tmp_path / "g.pcd"
    write_pcd(good, organised_points(), "binary")
    with pytest.raises(ConfigError, match="unknown sensor preset 'nope'"):
        read_scan(good, sensor_preset="nope")
    with pytest.raises(ValueError, match="depth_scale must be a positive number"):
        read_scan(good, depth_scale=0.0)
    with pytest.raises(ValueError, match=r"intrinsics must be \(fx, fy, cx, cy\)"):
        read_scan(good, intrinsics=(1.0, 2.0))
    assert Intrinsics.coerce(None) is None


# ------------------------------------------------------------------------------------------------ working range


def test_returns_outside_the_working_range_are_counted_and_left_out(tmp_path):
    """kinect_like measures 0.5-4.5 m: a depth PNG's returns nearer or farther are left out, counted in the
    ReadInfo (and its dict) with a note, and the sensor model keeps the preset's limits."""
    depth = np.full((H, W), 1500, np.uint16)
    depth[:, :4] = 9000  # 10 % far beyond the range
    depth[0, 10:14] = 400  # 4 pixels too near
    depth[5, 5] = 0  # no return: not counted
    path = tmp_path / "d.png"
    write_depth_png(path, depth)
    loaded = load_scan(path, intrinsics=K)
    info, scan = loaded.info, loaded.scan
    assert info.n_out_of_range == 4 * H + 4 and info.working_range_m == (0.5, 4.5)
    assert info.n_points == H * W - 1 and info.n_valid == info.n_points - info.n_out_of_range
    assert not scan.valid[:, :4].any() and not scan.valid[0, 10:14].any() and np.isnan(scan.points[0, 0]).all()
    assert (scan.sensor.min_range, scan.sensor.max_range) == (0.5, 4.5)
    assert f"{info.n_out_of_range} of {info.n_points} returns (10.3 %) outside kinect_like's working range " \
           "0.5-4.5 m left out" in info.notes
    d = info.to_dict()
    assert d["n_out_of_range"] == info.n_out_of_range and d["working_range_m"] == [0.5, 4.5]
    # another preset, another range: mockup_laser's 0.3-2.5 m keeps the near pixels, not the far ones
    assert load_scan(path, intrinsics=K, sensor_preset="mockup_laser").info.n_out_of_range == 4 * H


def test_most_returns_outside_the_working_range_are_refused(tmp_path):
    depth = np.full((H, W), 9000, np.uint16)  # 9 m: beyond kinect_like's 4.5 m
    depth[:, :10] = 1500
    path = tmp_path / "far.png"
    write_depth_png(path, depth)
    with pytest.raises(ReaderError, match=r"far\.png: 75 % of returns outside kinect_like's working range 0\.5-4\.5 m: "
                                          r"choose `--sensor-preset` for this sensor$"):
        load_scan(path, intrinsics=K)
    assert load_scan(path, intrinsics=K, sensor_preset="factory_scanner").info.n_out_of_range == 0  # 0.5-20 m


def test_clouds_lose_their_out_of_range_points_before_projection(tmp_path):
    """An organised PCD and an unorganised PLY: points beyond the preset's range are dropped (a too-near point
    does not hide the pixel's valid one behind it)."""
    pts = organised_points()
    pts[10:12] *= 4.0  # two rows at about 6 m
    write_pcd(tmp_path / "o.pcd", pts, "binary")
    loaded = load_scan(tmp_path / "o.pcd", intrinsics=K)
    assert loaded.info.n_out_of_range == 2 * W and not loaded.scan.valid[10:12].any()
    cloud = lattice_cloud_opengl()
    near = cloud[:100] * 0.1  # 0.2 m from the sensor, on the rays of valid points
    write_ply(tmp_path / "c.ply", np.concatenate([cloud, near]))
    loaded = load_scan(tmp_path / "c.ply")
    assert loaded.info.n_out_of_range == 100 and loaded.info.n_collisions == 0
    assert loaded.info.n_valid == len(cloud)
