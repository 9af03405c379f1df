"""Looking at trials from the command line: ``bench --list`` without running, ``show RUN TRIAL``, help texts."""

import pytest

from harness.cli import build_parser, main

SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise: {range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4}}
"""
SUITE = """
schema: suite/1
name: tiny
seed: 3
methods: {core: {}, paper: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    sensor: tiny_sensor.yaml
    viewpoints: 2
    min_view_pixels: 50
    min_view_surfaces: 3
"""


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("tiny")
    (d / "tiny_sensor.yaml").write_text(SENSOR)
    (d / "tiny.yaml").write_text(SUITE)
    assert main(["bench", "--suite", str(d / "tiny.yaml"), "--out", str(d / "run"), "--workers", "1",
                 "--no-report", "--progress", "log"]) == 0
    return d


def test_bench_list_prints_the_trials_without_running(tiny_run, capsys):
    assert main(["bench", "--suite", str(tiny_run / "tiny.yaml"), "--list", "--out", str(tiny_run / "nothing")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split()[:3] == ["trial", "id", "group"]
    assert [line.split()[0] for line in out[1:3]] == ["mockup-p0-v0-tiny_sensor-n0", "mockup-p0-v1-tiny_sensor-n0"]
    assert out[-1].startswith("suite tiny: 2 trials, 1 scenes")
    assert not (tiny_run / "nothing").exists()


def test_an_unknown_only_id_names_the_closest_and_the_list(tiny_run, capsys):
    assert main(["bench", "--suite", str(tiny_run / "tiny.yaml"), "--only", "mockup-p0-v0-tiny_sensr-n0",
                 "--out", str(tiny_run / "x")]) == 2
    err = capsys.readouterr().err
    assert "closest: mockup-p0-v0-tiny_sensor-n0" in err and "--list" in err


def test_show_prints_a_trials_figures_and_draws_its_pictures(tiny_run, capsys):
    out = tiny_run / "pictures"
    assert main(["show", str(tiny_run / "run"), "mockup-p0-v1-tiny_sensor-n0", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert text.startswith("mockup-p0-v1-tiny_sensor-n0: group mockup/tiny_sensor, scene mockup")
    assert "  core: correct detection" in text and "  paper: correct detection" in text
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) >= 4 and all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    index = (out / "index.md").read_text()
    assert all(p.name in index for p in pngs)
    assert main(["show", str(tiny_run / "run"), "mockup-p0-v9-tiny_sensor-n0"]) == 2
    assert "closest: mockup-p0-v" in capsys.readouterr().err


def test_every_option_has_help_and_the_top_help_is_plain_text():
    parser = build_parser()
    assert "``" not in parser.description and ":mod:" not in parser.format_help()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name, p in sub.choices.items():
        for action in p._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, f"harness {name} {action.option_strings[0]} has no help text"


def test_show_says_when_a_pose_is_conditional_and_a_view_twin_ambiguous():
    from harness.commands.show import trial_figures

    pose = {"ok": False, "conditional_on": "tank", "success": True, "rotation_error_deg": 0.1,
            "translation_error_mm": 2.0}
    record = {"trial_id": "t", "status": "ok", "spec": {}, "methods": {"core": {"pose": pose}},
              "view": {"median_range_m": 1.0, "valid_fraction": 0.5, "surfaces_seen": 4, "constrains_pose": False,
                       "twin_ambiguous": True}}
    text = "\n".join(trial_figures(record))
    assert "constrains 6 DOF: False (a twin pose explains it as well)" in text
    assert "core: pose conditional on tank, right" in text
    pose.update(conditional_on="", ok=False)
    assert "core: pose not ok, right" in "\n".join(trial_figures(record))
