"""Stage-isolating oracles: each gives its stage's ideal input; attribution (that the core never imports the truth
is tests/test_layering.py)."""

import json
import os

import pytest

from evaluation.attribution import attribute, largest_losses
from harness.run import RunOptions, run_suite
from harness.suite import load_suite
from scenes import ConfigError

SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 200, height: 150, fov_deg: 45.0, min_range: 0.3, max_range: 2.5}
noise:
  range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
"""

SUITE = """
schema: suite/1
name: tiny_oracles
seed: 5
timeout_s: 120
methods: {core: {}}
oracles: [segmentation, classification, pairing, pose]
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    perturbation_seeds: [1]
    sensor: tiny_sensor.yaml
    viewpoints: 2
    min_view_pixels: 50
    min_view_surfaces: 3
"""


@pytest.fixture(scope="module")
def oracle_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("oracles")
    (d / "tiny_sensor.yaml").write_text(SENSOR)
    (d / "suite.yaml").write_text(SUITE)
    summary = run_suite(load_suite(str(d / "suite.yaml")), d / "run", RunOptions(workers=2, progress=False),
                        log=open(os.devnull, "w"))
    records = [json.loads(p.read_text()) for p in (d / "run" / "trials").glob("*.json")]
    return summary, records


def test_each_oracle_gives_its_stage_ideal_input(oracle_run):
    summary, records = oracle_run
    assert summary["n_failed"] == 0, summary["failures"]
    oracles = summary["oracles"]
    assert set(oracles) == {"segmentation", "classification", "pairing", "pose"}
    # truth segmentation: every truth region of >= 200 px is correctly detected
    assert oracles["segmentation"]["segmentation"]["correct_detection_rate"] == 1.0
    # truth classification: every patch carries its truth class
    assert oracles["classification"]["classification"]["accuracy"] == 1.0
    # true pose: no pose error at all
    assert oracles["pose"]["pose"]["rotation_error_deg"]["max"] == 0.0
    assert oracles["pose"]["pose"]["translation_error_mm"]["max"] == 0.0
    for r in records:
        # truth pairings: no search (no tree node), one hypothesis computed from the given correspondences
        pose = r["oracles"]["pairing"]["pose"]
        assert pose["n_nodes"] == 0 and pose["n_hypotheses"] <= 1
        # the oracles change one stage: the pose oracle reuses the core's segmentation and classification
        assert r["oracles"]["pose"]["classification"] == r["methods"]["core"]["classification"]
    # the summary's per-group sections carry the oracles too
    assert all("oracles" in g for g in summary["groups"].values())


def test_attribution_of_a_hand_made_summary():
    summary = {"classification": {"accuracy": 0.91}, "pose": {"success_rate": 0.8}, "change": {"macro_f1": 0.6},
               "oracles": {"segmentation": {"classification": {"accuracy": 0.97}, "pose": {"success_rate": 0.9},
                                            "change": {"macro_f1": 0.7}},
                           "pose": {"classification": {"accuracy": 0.91}, "change": {"macro_f1": 0.9}}}}
    rows = {r.figure: r for r in attribute(summary)}
    acc = rows["classification accuracy"]
    assert acc.cost == {"segmentation": pytest.approx(0.06)} and acc.share["segmentation"] == pytest.approx(2 / 3)
    assert set(rows["change macro-F1"].cost) == {"segmentation", "pose"}
    assert rows["change macro-F1"].cost["pose"] == pytest.approx(0.3)
    sentences = largest_losses(list(rows.values()))
    assert sentences["segmentation"].startswith("Segmentation costs most on classification accuracy: 0.91")
    assert "change macro-F1" in sentences["pose"]


def test_unknown_oracle_is_a_clear_error(tmp_path):
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    (tmp_path / "s.yaml").write_text(SUITE.replace("oracles: [segmentation, classification, pairing, pose]",
                                                   "oracles: [clairvoyance]"))
    with pytest.raises(ConfigError, match="oracles: expected a list of distinct oracles"):
        load_suite(str(tmp_path / "s.yaml"))
