"""The public Python API, ``recognition``'s facade: the README's snippet run verbatim, the exports, and
:func:`recognition.segmentation_from_labels` (one's own label image into the core's classifier)."""

from __future__ import annotations

import contextlib
import io
import re
import shlex
import shutil
from pathlib import Path

import _support
import numpy as np
import pytest
import yaml

import recognition
from evaluation.oracles import truth_segmentation
from evaluation.patches import truth_regions
from harness.cli import main
from harness.suite import suite_from_dict
from harness.trial import prepare_scene, sensor_for, trial_scan, trial_viewpoints
from recognition.describe import core_sigma

ROOT = Path(__file__).resolve().parent.parent
SENSOR = _support.TINY_SENSOR


def _readme_section(title: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    start = text.index(f"\n## {title}")
    end = text.find("\n## ", start + 1)
    return text[start:end if end > 0 else None]


def _fenced(section: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", section, flags=re.S)


def test_the_readme_snippet_runs_verbatim(tmp_path, monkeypatch):
    """The README's Python API snippet, on the scan its own commands make (the 640 x 480 mock-up laser, as the
    README says: on a 160 x 120 stand-in the pose's separation from its alternative, leaving out the patch that
    favours it most, rests on four patches and falls under one standard error)."""
    snippet = _fenced(_readme_section("Python API"), "python")[0]
    assert len(snippet.strip().splitlines()) <= 16
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scenes" / "data").mkdir(parents=True)
    for name in ("mockup.yaml", "mockup_perturbation.yaml"):
        shutil.copy(ROOT / "scenes" / "data" / name, tmp_path / "scenes" / "data" / name)
    commands = [c for block in _fenced(_readme_section("Python API"), "sh") for c in block.splitlines()
                if c.startswith(("harness scene perturb", "harness sense pert/"))]
    assert len(commands) == 2, commands
    for command in commands:
        assert main(shlex.split(command)[1:]) == 0, command
    assert (tmp_path / "scan" / "scan.npz").is_file()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(snippet, "README.md", "exec"), {"__name__": "__readme__"})
    printed = out.getvalue()
    assert "pose: True" in printed, printed
    assert re.search(r"^0 PLAN \d+ ", printed, flags=re.M), printed
    assert re.search(r"'(moved|missing|altered|new)'", printed), printed  # the perturbed scene's changes


def test_the_facade_exports_the_pipeline():
    import sensors.readers

    for name in recognition.__all__:
        assert getattr(recognition, name) is not None, name
    assert recognition.read_scan is sensors.readers.read_scan
    for name in ("describe", "localise", "detect_changes", "segmentation_from_labels", "Describer", "Localiser",
                 "ChangeDetector", "CoreParams", "Peer", "SceneModel", "Scan"):
        assert name in recognition.__all__


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Two small simulated scans of the perturbed mock-up with their truth."""
    d = tmp_path_factory.mktemp("api")
    (d / "tiny_sensor.yaml").write_text(SENSOR)
    suite = suite_from_dict(yaml.safe_load("""
schema: suite/1
name: api
seed: 3
methods: {core: {}}
groups:
  - {scene: mockup, perturbation: mockup_perturbation, sensor: tiny_sensor.yaml, viewpoints: 2,
      min_view_pixels: 50, min_view_surfaces: 3}
"""), str(d / "api.yaml"), d)
    out = []
    for spec in suite.trials:
        prepared, config = prepare_scene(spec, None), sensor_for(spec)
        view = trial_viewpoints(spec, prepared, config).viewpoints[0]
        out.append(trial_scan(spec, prepared, config, view.T_world_sensor))
    return out


def test_truth_labels_classify_as_the_segmentation_oracle(scans):
    """A truth label image fed in gives the patches of the truth regions and, on every scored patch (>= 200
    pixels), the classification the segmentation oracle gives (and the truth class)."""
    params = recognition.DescribeParams()
    for scan, truth in scans:
        labels = truth_regions(truth, scan.valid)
        seg = recognition.segmentation_from_labels(labels, scan)
        assert isinstance(seg, recognition.Segmentation)
        assert [p.id for p in seg.patches] == list(range(len(seg.patches)))
        sizes = [p.n_pixels for p in seg.patches]
        assert sizes == sorted(sizes, reverse=True)
        assert len(seg.patches) == len(np.unique(labels[(labels >= 0) & scan.valid]))
        mine = recognition.describe(scan, params, seg)
        oracle = recognition.describe(scan, params, truth_segmentation(scan, truth, core_sigma(scan)))
        by_pixels = {p.pixels.tobytes(): p.label for p in oracle.patches if p.n_pixels >= 200}
        scored = [p for p in mine.patches if p.n_pixels >= 200]
        assert scored and all(by_pixels.get(p.pixels.tobytes()) == p.label for p in scored)
        truth_class = [truth.surfaces[int(truth.surface_id.flat[p.pixels[0]])].truth_class for p in scored]
        assert [p.label for p in scored] == truth_class


def test_own_labels_any_values_and_bad_input(scans):
    scan, _ = scans[0]
    h, w = scan.range.shape
    labels = np.full((h, w), -5, dtype=np.int64)
    labels[:, : w // 2] = 1000  # arbitrary values; a user's segmenter labels the left half and a block
    labels[: h // 3, w // 2:] = 7
    seg = recognition.segmentation_from_labels(labels, scan)
    assert {int(v) for v in np.unique(seg.labels)} <= {-1, 0, 1}
    assert np.all(seg.labels[~scan.valid] == -1)
    desc = recognition.describe(scan, recognition.DescribeParams(), seg)
    assert {p.label for p in desc.patches} <= {"PLAN", "CYL", "SPH", "CONE", "OTH"}
    empty = recognition.segmentation_from_labels(np.full((h, w), -1), scan)
    assert empty.n_patches == 0 and recognition.describe(scan, segmentation=empty).patches == ()
    with pytest.raises(ValueError, match=r"labels must have the scan's shape \(120, 160\) \(H, W\), got \(3, 4\)"):
        recognition.segmentation_from_labels(np.zeros((3, 4), int), scan)
    with pytest.raises(ValueError, match="labels must be integers"):
        recognition.segmentation_from_labels(np.zeros((h, w)), scan)
