"""Garbage files into ``sensors.readers.read_scan``: a ReaderError naming the file (or a ConfigError for an
intrinsics file), never another exception, a hang, or an allocation sized by a lying header."""

from __future__ import annotations

import io
import struct
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from scenes.config import ConfigError
from sensors.io import save_npz
from sensors.models import PinholeCamera
from sensors.noise import NoiseModel
from sensors.range_image import Scan
from sensors.readers import ReaderError, read_scan

K = (300.0, 300.0, 19.5, 14.5)


def _valid_files() -> dict[str, bytes]:
    """One small valid file per format."""
    h, w = 30, 40
    v, u = np.mgrid[0:h, 0:w].astype(float)
    z = 1.0 + 0.01 * u
    pts = np.stack([(u - K[2]) / K[0] * z, (v - K[3]) / K[1] * z, z], -1).reshape(-1, 3).astype(np.float32)
    pcd = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\n"
           f"HEIGHT {h}\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {w * h}\nDATA binary\n").encode() + pts.tobytes()
    ply = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(pts)}\nproperty float x\n"
           "property float y\nproperty float z\nend_header\n").encode() + pts.tobytes()
    buf = io.BytesIO()
    Image.fromarray((z * 1000).astype(np.uint16)).save(buf, format="PNG")
    cam = PinholeCamera(w, h, *K, 0.1, 5.0)
    scan = Scan(z / cam.ray_directions()[..., 2], pts.reshape(h, w, 3).astype(float), cam, NoiseModel())
    with tempfile.TemporaryDirectory() as d:
        save_npz(Path(d) / "scan.npz", scan)
        npz = (Path(d) / "scan.npz").read_bytes()
    return {".pcd": pcd, ".ply": ply, ".png": buf.getvalue(), ".npz": npz}


VALID = _valid_files()


def _read(path) -> None:
    """read_scan must succeed or raise ReaderError / ConfigError naming the file, quickly."""
    t0 = time.perf_counter()
    try:
        read_scan(path, intrinsics=K if path.suffix == ".png" else None)
    except ReaderError as exc:
        assert str(path) in str(exc), exc
    except ConfigError as exc:
        assert str(path) in str(exc) or "intrinsics" in str(exc), exc
    assert time.perf_counter() - t0 < 10


@pytest.mark.parametrize("suffix", sorted(VALID))
def test_the_valid_files_read(tmp_path, suffix):
    path = tmp_path / f"ok{suffix}"
    path.write_bytes(VALID[suffix])
    assert np.isfinite(read_scan(path, intrinsics=K if suffix == ".png" else None).range).any()


@pytest.mark.parametrize("suffix", sorted(VALID))
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_truncated_and_corrupted_files(tmp_path, suffix, data):
    raw = bytearray(VALID[suffix])
    cut = data.draw(st.integers(0, len(raw)), label="truncate at")
    flips = data.draw(st.lists(st.tuples(st.integers(0, len(raw) - 1), st.integers(0, 255)), max_size=8),
                      label="byte changes")
    for pos, b in flips:
        raw[pos] = b
    path = tmp_path / f"bad{suffix}"
    path.write_bytes(bytes(raw[:cut]))
    _read(path)


@pytest.mark.parametrize("suffix", sorted(VALID))
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(blob=st.binary(max_size=2000))
def test_random_bytes(tmp_path, suffix, blob):
    path = tmp_path / f"noise{suffix}"
    path.write_bytes(blob)
    _read(path)


@pytest.mark.parametrize("suffix, content, match", [
    (".pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000\n"
             b"HEIGHT 100000\nPOINTS 10000000000\nDATA binary\n" + b"\0" * 64, "truncated"),
    (".pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100000\n"
             b"HEIGHT 1000\nPOINTS 100000000\nDATA binary_compressed\n" + struct.pack("<II", 4, 1200000000)
             + b"\0" * 4, "binary_compressed"),
    (".pcd", b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH -5\n"
             b"HEIGHT 1\nPOINTS -5\nDATA ascii\n", "PCD header"),
    (".ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\n"
             b"property float y\nproperty float z\nend_header\n" + b"\0" * 24, ""),
    (".ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
             b"end_header\nnan nan nan\ninf inf inf\n1e999 0 0\n", ""),
    (".npz", b"PK\x03\x04" + b"\0" * 100, "npz"),
    (".png", b"\x89PNG\r\n\x1a\n" + b"\0" * 100, "PNG"),
])
def test_lying_headers(tmp_path, suffix, content, match):
    path = tmp_path / f"liar{suffix}"
    path.write_bytes(content)
    t0 = time.perf_counter()
    with pytest.raises(ReaderError, match=match) as info:
        read_scan(path, intrinsics=K if suffix == ".png" else None)
    assert str(path) in str(info.value)
    assert time.perf_counter() - t0 < 5


def test_a_directory_and_a_missing_file(tmp_path):
    (tmp_path / "dir.pcd").mkdir()
    for p in (tmp_path / "dir.pcd", tmp_path / "missing.ply"):
        with pytest.raises(ReaderError, match="no such file"):
            read_scan(p)
    with pytest.raises(ReaderError, match="unknown range data format"):
        read_scan(tmp_path / "scan.exe")
