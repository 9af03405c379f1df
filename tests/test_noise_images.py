"""Pure-noise depth images, read and described end to end (issue 34, "the sensor model is checked against the
data"): the reader refuses an image whose returns lie mostly outside the sensor preset's working range, and the
core labels no patch of a pure-noise image with a probability of 0.5 or more (its support is not better than
noise); salt and pepper on a real plane still gives the plane.

160 x 120 images with the Kinect-like preset's field of view (the default preset), each read and described in
about a second.
"""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from harness.cli import main as harness_main
from recognition.classification import SelectParams
from recognition.describe import DescribeParams, describe
from sensors.readers import ReaderError, load_scan

H, W = 120, 160
F = 589.0 * W / 640  # kinect_like's 57 degrees across
K = (F, F, (W - 1) / 2, (H - 1) / 2)


def _png(path, depth_mm: np.ndarray):
    Image.fromarray(np.clip(np.round(depth_mm), 0, 65535).astype(np.uint16)).save(path)
    return path


def _noise(kind: str, rng: np.random.Generator) -> np.ndarray:
    if kind == "uniform 0.5-4.5 m":  # within kinect_like's working range
        return rng.uniform(500, 4500, (H, W))
    if kind.startswith("gaussian"):  # about 2 m, sigma 8-50 times the sensor's (6 mm at 2 m)
        return rng.normal(2000, float(kind.split()[-2]), (H, W))
    raise ValueError(kind)


def _confident(desc, min_pixels: int) -> list:
    return [p for p in desc.patches if p.n_pixels >= min_pixels and max(p.classification.probabilities.values()) >= 0.5]


def test_wide_range_noise_is_refused(tmp_path, capsys):
    """Uniform random depths over 0-65 m are not what a Kinect-like sensor measures: refused, naming the file,
    the share outside the working range and what to do."""
    path = _png(tmp_path / "wide.png", np.random.default_rng(0).uniform(0, 65000, (H, W)))
    with pytest.raises(ReaderError) as err:
        load_scan(path, intrinsics=K)
    msg = str(err.value)
    assert msg.startswith(str(path)) and "\n" not in msg
    assert msg.endswith("94 % of returns outside kinect_like's working range 0.5-4.5 m: choose `--sensor-preset` "
                        "for this sensor")
    assert harness_main(["describe", str(path), "--intrinsics", *map(str, K), "--out", str(tmp_path / "o")]) == 2
    out = capsys.readouterr().err
    assert "94 % of returns outside kinect_like's working range" in out and "Traceback" not in out
    assert len(out.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("kind", ["uniform 0.5-4.5 m", "gaussian 2 m sigma 50 mm", "gaussian 2 m sigma 100 mm",
                                  "gaussian 2 m sigma 300 mm"])
def test_pure_noise_gives_no_confident_patch(tmp_path, kind):
    loaded = load_scan(_png(tmp_path / "noise.png", _noise(kind, np.random.default_rng(1))), intrinsics=K)
    params = DescribeParams()
    desc = describe(loaded.scan, params)
    # every patch the core classifies (smaller ones are OTH, "too small to classify")
    assert _confident(desc, params.min_classify_pixels) == []
    for p in desc.patches:
        if "not better than noise" in p.classification.reason:
            assert p.label == "OTH" and p.classification.primitive is None
            assert max(p.classification.probabilities.values()) < 0.5
            assert sum(p.classification.probabilities.values()) == pytest.approx(1.0)


def test_the_noise_test_is_what_removes_the_confidence(tmp_path):
    """Gaussian noise of 50 mm about 2 m forms one large patch; the classifier alone, with the base floor on every
    decision path, calls it OTH at high probability ("best primitive PLAN does not fit within noise"), the support
    test makes it unsure. (The floor of that decision path, ``SelectParams.unexplained_floor``, fitted on the
    calibration suite's merged patches, makes it unsure too.)"""
    loaded = load_scan(_png(tmp_path / "noise.png", _noise("gaussian 2 m sigma 50 mm", np.random.default_rng(1))),
                       intrinsics=K)
    base = SelectParams(unexplained_floor=SelectParams().prob_floor)
    without = describe(loaded.scan, DescribeParams(max_local_scatter=None, classifier_params=base))
    assert _confident(without, 200), "the image no longer gives confident patches without the test"
    floored = describe(loaded.scan, DescribeParams(max_local_scatter=None))
    assert not _confident(floored, 200)
    desc = describe(loaded.scan, DescribeParams())
    big = [p for p in desc.patches if p.n_pixels >= 200]
    assert big and all(p.classification.reason.startswith("support not better than noise") for p in big)


def test_salt_and_pepper_on_a_plane_keeps_the_plane(tmp_path):
    """A tilted plane at about 2 m with sensor-like noise, 10 % of its pixels replaced by 0.6 m (salt) and 10 % by
    4.4 m (pepper; beyond 4.5 m along the outer rays: left out): one PLAN patch, confident, over most of the plane's
    pixels."""
    rng = np.random.default_rng(2)
    u = np.arange(W)[None, :] - (W - 1) / 2
    v = np.arange(H)[:, None] - (H - 1) / 2
    z = 1000.0 / (0.5 + 0.2 * u / F + 0.1 * v / F) + rng.normal(0, 3, (H, W))  # 1/z linear in the pixel: a plane
    m = rng.random((H, W))
    z[m < 0.1], z[(m >= 0.1) & (m < 0.2)] = 600, 4400
    loaded = load_scan(_png(tmp_path / "sp.png", z), intrinsics=K)
    assert 0 < loaded.info.n_out_of_range < 0.2 * H * W
    desc = describe(loaded.scan, DescribeParams())
    plan = max(desc.patches, key=lambda p: p.n_pixels)
    assert plan.label == "PLAN" and plan.classification.probabilities["PLAN"] >= 0.5
    assert plan.n_pixels >= 0.6 * H * W
