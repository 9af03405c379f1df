"""``harness describe FILE --model SCENE``: a saved scan localised against its a priori model, its changes
detected, everything written (JSON, Markdown, change map)."""

import json

import numpy as np
import pytest

from harness.cli import main as harness_main
from harness.suite import load_suite
from harness.trial import prepare_scene, sensor_for, trial_scan, trial_viewpoints
from sensors.io import save_npz


@pytest.fixture(scope="module")
def saved_trial(tmp_path_factory):
    """A default-suite mock-up trial (a constrained view) saved as a scan file and an a priori scene YAML."""
    spec = next(t for t in load_suite("classic").trials if t.trial_id == "mockup-p0-v1-mockup_laser-n0")
    prepared = prepare_scene(spec, None)
    config = sensor_for(spec)
    view = trial_viewpoints(spec, prepared, config).viewpoints[0]
    scan, truth = trial_scan(spec, prepared, config, view.T_world_sensor)
    d = tmp_path_factory.mktemp("saved")
    save_npz(d / "scan.npz", scan)  # no truth in the file: the command must not need it
    prepared.apriori.save(d / "apriori.yaml")
    return d, truth, prepared.change_truth


def test_describe_with_a_model_localises_and_detects_changes(saved_trial, capsys):
    d, truth, change_truth = saved_trial
    out = d / "out"
    assert harness_main(["describe", str(d / "scan.npz"), "--model", str(d / "apriori.yaml"), "--out", str(out)]) == 0
    doc = json.loads((out / "description.json").read_text())
    pose = doc["pose"]
    assert pose["ok"], pose["reason"]
    T = np.array(pose["T_world_sensor"])
    E = np.linalg.inv(truth.T_world_sensor) @ T
    assert np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))) < 1.0
    assert np.linalg.norm(T[:3, 3] - truth.T_world_sensor[:3, 3]) < 0.01
    change = doc["change"]
    assert set(change["features"]) == set(change_truth.features)
    labels = {r["label"] for r in change["features"].values()}
    assert labels <= {"unchanged", "moved", "missing", "altered", "unobserved"} and "unchanged" in labels
    assert set(change["objects"]) == set(change_truth.objects)
    assert "| object | label | features (label) |" in (out / "changes.md").read_text()
    assert (out / "changes.png").stat().st_size > 0
    printed = capsys.readouterr().out
    assert "pose: sensor at" in printed and "change:" in printed
    # the mock-up's elbow (bend radius 70 mm, pipe radius 25 mm) is OTH with its torus and radii
    elbows = [p for p in doc["patches"] if p["primitive"] and p["primitive"]["type"] == "TorusFit"]
    assert elbows and all(p["label"] == "OTH" for p in elbows)
    big = max(elbows, key=lambda p: p["n_pixels"])
    assert big["invariants"]["major_radius_m"]["value"] == pytest.approx(0.07, rel=0.1)
    assert big["invariants"]["minor_radius_m"]["value"] == pytest.approx(0.025, rel=0.05)
    assert "elbow: bend R = " in (out / "table.md").read_text()


def test_describe_with_a_bad_model_fails_before_any_work(saved_trial, tmp_path, capsys):
    d, _, _ = saved_trial
    bad = tmp_path / "bad.yaml"
    bad.write_text("schema: scene/1\nobjects: [{id: a, kind: nonsense, features: []}]\n")
    assert harness_main(["describe", str(d / "scan.npz"), "--model", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "kind" in err
    assert not (tmp_path / "o").exists()
