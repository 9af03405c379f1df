"""The runner: determinism, crash isolation, kill and resume, Dask equals local, locking, compare."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import _support
import pytest

from harness.cli import main
from harness.compare import Tolerances, compare, load_summary, regressions
from harness.run import RunOptions, run_suite
from harness.store import RunDirectory, RunLockedError
from harness.suite import load_suite
from harness.summary import comparable
from scenes import ConfigError

SENSOR = _support.TINY_SENSOR

SUITE = """
schema: suite/1
name: tiny
seed: 3
timeout_s: 60
methods: {core: {}, paper: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    perturbation_seeds: [0]
    sensor: tiny_sensor.yaml
    viewpoints: 3
    noise_seeds: [0]
    min_view_pixels: 50
    min_view_surfaces: 3
"""


@pytest.fixture()
def tiny_suite(tmp_path):
    (tmp_path / "tiny_sensor.yaml").write_text(SENSOR)
    path = tmp_path / "tiny.yaml"
    path.write_text(SUITE)
    return path


def _run(suite_path, out, **kw):
    return run_suite(load_suite(str(suite_path)), out, RunOptions(workers=kw.pop("workers", 2), progress=False, **kw),
                     log=open(os.devnull, "w"))


def test_two_runs_give_identical_summaries_and_trials(tiny_suite, tmp_path):
    a = _run(tiny_suite, tmp_path / "a")
    b = _run(tiny_suite, tmp_path / "b", workers=1)
    assert a["n_trials"] == 3 and a["n_failed"] == 0, a["failures"]
    assert comparable(a) == comparable(b)
    for p in (tmp_path / "a" / "trials").glob("*.json"):
        ra, rb = json.loads(p.read_text()), json.loads((tmp_path / "b" / "trials" / p.name).read_text())
        for r in (ra, rb):
            r.pop("timing_s")
            for m in r["methods"].values():
                m.pop("timing_s")
        assert ra == rb
    # the summary has the contract's keys, with stages not built yet as null
    for key in ("schema", "suite", "n_trials", "n_failed", "config_hash", "version", "segmentation",
                "classification", "pose", "change", "timing_s", "baselines", "groups"):
        assert key in a
    assert set(a["baselines"]) == {"paper"}
    assert a["segmentation"] is not None and a["classification"] is not None


def test_failures_are_recorded_and_the_run_goes_on(tiny_suite, tmp_path, monkeypatch):
    import harness.trial as trial

    real = trial.run_trial

    def faulty(spec, *args, **kw):
        if spec.viewpoint == 0:
            raise RuntimeError("injected failure")
        if spec.viewpoint == 1:
            time.sleep(30)
        if spec.viewpoint == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(spec, *args, **kw)

    monkeypatch.setattr(trial, "run_trial", faulty)
    summary = _run(tiny_suite, tmp_path / "f", timeout_s=3.0, workers=3)
    reasons = {f["trial_id"].split("-")[2]: f["reason"] for f in summary["failures"]}
    assert summary["n_failed"] == 3
    assert "RuntimeError: injected failure" in reasons["v0"]
    assert reasons["v1"] == "timed out after 3 s"
    assert "worker process died (killed by signal 9)" in reasons["v2"]
    rec = json.loads((tmp_path / "f" / "trials" / "mockup-p0-v0-tiny_sensor-n0.json").read_text())
    assert rec["status"] == "failed" and "injected failure" in rec["detail"]


def test_killed_run_resumes_without_redoing_finished_trials(tiny_suite, tmp_path):
    out = tmp_path / "k"
    cmd = [sys.executable, "-m", "harness", "bench", "--suite", str(tiny_suite), "--out", str(out), "--workers", "1",
           "--no-report", "--progress", "log"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((out / "trials").glob("*.json"))) < 1:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in (out / "trials").glob("*.json")}
    assert 1 <= len(finished) < 3
    assert main(["bench", "--suite", str(tiny_suite), "--out", str(out), "--resume", "--workers", "1",
                 "--no-report", "--progress", "log"]) == 0
    assert not list(out.rglob(".*.tmp"))
    for name, (data, mtime) in finished.items():  # finished trials kept bit-identical, not rerun
        p = out / "trials" / name
        assert p.read_bytes() == data and p.stat().st_mtime_ns == mtime
    resumed = load_summary(out)
    straight = _run(tiny_suite, tmp_path / "straight")
    assert resumed["n_trials"] == 3 and resumed["complete"]
    assert comparable(resumed) == comparable(straight)


def test_dask_local_cluster_equals_local_run(tiny_suite, tmp_path):
    pytest.importorskip("distributed")
    local = _run(tiny_suite, tmp_path / "local")
    dask = _run(tiny_suite, tmp_path / "dask", dask_local=2)
    assert dask["n_failed"] == 0, dask["failures"]
    assert comparable(dask) == comparable(local)


def test_an_existing_run_is_neither_mixed_nor_lost(tiny_suite, tmp_path):
    out = tmp_path / "x"
    _run(tiny_suite, out, only=("mockup-p0-v0-tiny_sensor-n0",))
    with pytest.raises(FileExistsError, match="already holds 1 trial record"):
        _run(tiny_suite, out)
    with RunDirectory(out):
        with pytest.raises(RunLockedError, match="another run is writing here"):
            _run(tiny_suite, out, resume=True)
    with pytest.raises(ValueError, match="--only: no trial 'nope'"):
        _run(tiny_suite, out, only=("nope",), resume=True)


def test_code_identity_of_a_checkout_and_of_a_plain_tree(tmp_path):
    import shutil

    from harness.provenance import CodeIdentity, code_identity

    repo = tmp_path / "repo"
    for rel, text in (("recognition/fit.py", "x = 1\n"), ("harness/cli.py", "y = 2\n"), ("docs/a.md", "doc\n")):
        (repo / rel).parent.mkdir(parents=True, exist_ok=True)
        (repo / rel).write_text(text)
    git = ["git", "-C", str(repo), "-c", "user.name=t", "-c", "user.email=t@example.org", "-c", "commit.gpgsign=false"]
    for args in (["init", "-q"], ["add", "."], ["commit", "-qm", "c"]):
        subprocess.run([*git, *args], check=True, capture_output=True)
    head = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    clean = code_identity(repo)
    assert clean == CodeIdentity(head) and clean.as_json() == {"commit": head, "diff_sha256": None,
                                                               "source_sha256": None, "plugins": {}}
    (repo / "recognition" / "fit.py").write_text("x = 2\n")  # a change under recognition/
    changed = code_identity(repo)
    assert changed.commit == head and len(changed.diff_sha256) == 64 and code_identity(repo) == changed
    assert "(clean)" in clean.describe() and f"uncommitted diff {changed.diff_sha256[:12]}" in changed.describe()
    (repo / "recognition" / "fit.py").write_text("x = 3\n")
    assert code_identity(repo).diff_sha256 not in (None, changed.diff_sha256)
    (repo / "recognition" / "fit.py").write_text("x = 1\n")
    assert code_identity(repo) == clean
    (repo / "docs" / "a.md").write_text("other\n")  # outside the packages: the same code
    assert code_identity(repo) == clean
    (repo / "recognition" / "new.py").write_text("z = 0\n")  # untracked under a package: other code
    assert code_identity(repo).diff_sha256 is not None
    tree = tmp_path / "tree"  # no git checkout: a hash of the packages' files
    shutil.copytree(repo, tree, ignore=shutil.ignore_patterns(".git"))
    plain = code_identity(tree)
    assert plain.commit is None and len(plain.source_sha256) == 64 and "no git checkout" in plain.describe()
    (tree / "recognition" / "fit.py").write_text("x = 9\n")
    assert code_identity(tree).source_sha256 != plain.source_sha256
    assert CodeIdentity.from_json(plain.as_json()) == plain and CodeIdentity.from_json(None) is None


def test_resume_refuses_other_code_unless_resume_any_code(tiny_suite, tmp_path, monkeypatch, capsys):
    import dataclasses

    import harness.run as runner
    from harness.provenance import code_identity
    from reports.render import code_text, render_report

    here = code_identity()  # fixed for the test: other engineers may edit the tree meanwhile
    edited = dataclasses.replace(here, diff_sha256="5" * 64)  # what an edit under recognition/ gives
    calls = []

    def identity(code):
        def compute():
            calls.append(code)
            return code
        return compute

    out = tmp_path / "r"
    argv = ["bench", "--suite", str(tiny_suite), "--out", str(out), "--workers", "1", "--no-report",
            "--progress", "log"]
    first = "mockup-p0-v0-tiny_sensor-n0"
    monkeypatch.setattr(runner, "code_identity", identity(here))
    assert main([*argv, "--only", first]) == 0 and calls == [here]  # once per run, in the parent
    record = json.loads((out / "trials" / f"{first}.json").read_text())
    manifest = json.loads((out / "run.json").read_text())
    assert record["code"] == manifest["code"] == here.as_json() and manifest["code"]["plugins"] == {}
    assert "mixed_codes" not in manifest
    assert json.loads((out / "summary.json").read_text())["provenance"]["code"] == here.as_json()

    monkeypatch.setattr(runner, "code_identity", identity(edited))
    capsys.readouterr()
    assert main([*argv, "--resume"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"harness: error: {out}: --resume refused: its ")
    assert f"({here.describe()}) than this ({edited.describe()})" in err and "--resume-any-code" in err
    assert [p.name for p in (out / "trials").glob("*.json")] == [f"{first}.json"]  # nothing ran

    assert main([*argv, "--resume-any-code"]) == 0
    manifest = json.loads((out / "run.json").read_text())
    assert manifest["code"] == edited.as_json() and manifest["mixed_codes"] == [here.as_json(), edited.as_json()]
    codes = {p.stem: json.loads(p.read_text())["code"] for p in (out / "trials").glob("*.json")}
    assert codes.pop(first) == here.as_json()  # kept, not rerun
    assert len(codes) == 2 and all(c == edited.as_json() for c in codes.values())
    assert main([*argv, "--resume"]) == 2  # a mixed run stays refused without --resume-any-code
    md = render_report(out)[1].read_text()
    assert f"| code identity | {code_text(edited.as_json())} |" in md
    assert "| mixed code | resumed with --resume-any-code" in md


@pytest.mark.parametrize("edit, message", [
    ("methods: {core: {}, paper: {}}", "methods: {magic: {}}"),
    ("sensor: tiny_sensor.yaml", "sensor: no_such_preset"),
    ("viewpoints: 3", "viewpoints: 0"),
    ("noise_seeds: [0]", "noise_seeds: [0, 0]"),
    ("scene: mockup", "scene: atlantis"),
])
def test_suite_validation_errors(tiny_suite, edit, message):
    text = tiny_suite.read_text()
    bad = tiny_suite.with_name("bad.yaml")
    bad.write_text(text.replace(edit, message))
    with pytest.raises((ConfigError, FileNotFoundError)) as info:
        load_suite(str(bad))
    assert str(bad) in str(info.value)


def test_cli_bench_bad_input_exit_codes(tmp_path, capsys):
    assert main(["bench", "--suite", "no_such_suite", "--out", str(tmp_path / "o")]) == 2
    assert "no shipped suite 'no_such_suite'" in capsys.readouterr().err
    assert main(["bench", "--suite", "smoke", "--workers", "0", "--out", str(tmp_path / "o")]) == 2


def _summary(**sections):
    base = {"schema": "harness.summary/1", "suite": "s", "n_trials": 4, "n_failed": 0, "config_hash": "x",
            "version": "0", "segmentation": {"correct_detection_rate": 0.9, "over_rate": 0.05, "tolerance": 0.8},
            "classification": {"accuracy": 0.95, "brier": 0.08},
            "pose": {"success_rate": 1.0, "rotation_error_deg": {"median": 0.02, "p90": 0.05, "max": 0.1}},
            "change": None, "timing_s": {"total": {"median": 1.0, "p90": 2.0}}, "baselines": {}, "groups": {}}
    for k, v in sections.items():
        base[k] = v
    return base


def test_compare_rules_and_exit_codes(tmp_path, capsys):
    base = _summary()
    assert regressions(compare(base, _summary())) == []
    worse = _summary(classification={"accuracy": 0.90, "brier": 0.08})
    bad = regressions(compare(base, worse))
    assert [r.metric for r in bad] == ["classification.accuracy"]
    assert regressions(compare(base, _summary(classification={"accuracy": 0.94, "brier": 0.08}))) == []
    assert [r.metric for r in regressions(compare(base, _summary(pose=None)))] == ["pose"]
    slower = _summary(timing_s={"total": {"median": 5.0, "p90": 9.0}})
    assert regressions(compare(base, slower)) == []  # time rules are off unless asked
    assert regressions(compare(base, slower, Tolerances(check_time=True)))
    err = _summary(pose={"success_rate": 1.0, "rotation_error_deg": {"median": 0.05, "p90": 0.05, "max": 0.1}})
    assert [r.metric for r in regressions(compare(base, err))] == ["pose.rotation_error_deg.median"]
    better = _summary(segmentation={"correct_detection_rate": 0.95, "over_rate": 0.01, "tolerance": 0.8})
    assert {r.verdict for r in compare(base, better) if r.metric.startswith("segmentation.")} >= {"improved"}

    for name, s in (("base", base), ("worse", worse)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "summary.json").write_text(json.dumps(s))
    assert main(["compare", str(tmp_path / "base"), str(tmp_path / "base")]) == 0
    assert main(["compare", str(tmp_path / "base"), str(tmp_path / "worse"), "--format", "md"]) == 1
    out = capsys.readouterr().out
    # summaries alone (no trial records): no interval, the tolerance alone decides, and says so
    assert "| core | classification accuracy | all | 0.950 | 0.900 | -0.050 |  | REGRESSION (tolerance alone) |" in out
    assert out.rstrip().endswith("**FAIL: 1 regression(s) in 6 headline metric(s) of core: core classification "
                                 "accuracy (regression: all)**")
    (tmp_path / "junk.json").write_text("{not json")
    assert main(["compare", str(tmp_path / "base"), str(tmp_path / "junk.json")]) == 2
    assert main(["compare", str(tmp_path / "base"), str(tmp_path / "missing")]) == 2


def test_shipped_suites_load_and_keep_every_seed_below_100000():
    from harness.suite import shipped_suites

    for name in shipped_suites():
        suite = load_suite(name)
        assert suite.trials and suite.methods["core"] is not None
        assert len({t.trial_id for t in suite.trials}) == len(suite.trials)
        for t in suite.trials:  # seeds from 100000 on are scenes no shipped suite holds
            assert max(t.suite_seed, t.perturbation_seed, t.noise_seed, t.viewpoint, t.scene_seed or 0) < 100_000


def test_default_is_broad_and_calibration_uses_other_seeds_of_the_same_families():
    default, calibration = load_suite("default"), load_suite("calibration")
    groups = {t.group for t in default.trials}
    assert groups == {"mockup/mockup_laser", "factory/factory_scanner", "factory/kinect_like"}
    scanner, kinect = ({t.scene for t in default.trials if t.group == g}
                       for g in ("factory/factory_scanner", "factory/kinect_like"))
    assert not scanner & kinect  # the Kinect-like group looks at other bays
    for g in groups:
        trials = [t for t in default.trials if t.group == g]
        assert len({t.scene for t in trials}) >= 8
        assert all(len({t.perturbation_seed for t in trials if t.scene == s}) >= 2 for s in {t.scene for t in trials})
    assert {t.group for t in calibration.trials} == groups
    for key in ("scene", "perturbation_seed"):
        assert not {getattr(t, key) for t in default.trials} & {getattr(t, key) for t in calibration.trials}, key
    assert len(load_suite("full").trials) >= 500


def test_store_writes_atomically_and_cleans_temporaries(tmp_path):
    from harness.store import write_json_atomic

    with RunDirectory(tmp_path / "r") as rd:
        (rd.trials_dir / ".x.json.123.tmp").write_text("partial")
        rd.write_trial({"trial_id": "t", "config_hash": "h"})
        assert rd.finished("h") == {"t"} and rd.finished("other") == set()
    with RunDirectory(tmp_path / "r") as rd:
        assert not list(rd.trials_dir.glob(".*.tmp"))
    target = tmp_path / "f.json"
    write_json_atomic(target, {"a": 1})
    with pytest.raises(ValueError):
        write_json_atomic(target, {"a": float("nan")})
    assert json.loads(target.read_text()) == {"a": 1}
    assert not list(tmp_path.glob(".*.tmp"))
    Path(tmp_path / "r" / "trials" / "broken.json").write_text("{")
    with RunDirectory(tmp_path / "r") as rd:
        assert rd.finished("h") == {"t"}  # an unreadable record is redone, not trusted


def test_segmentation_benchmark_times_and_scores_one_frame(tmp_path, capsys):
    from threadpoolctl import threadpool_limits

    from harness.bench.segmentation import main as bench_segmentation
    from harness.suite import load_suite
    from harness.trial import prepare_scene, run_trial

    out_json = tmp_path / "seg.json"
    assert bench_segmentation(["--suite", "smoke", "--limit", "1", "--repeat", "2", "--steps",
                               "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line.startswith(("all ", "mockup/", "factory_bay/"))]
    assert [r[0] for r in rows][-1] == "all" and all(r[1] == "1" for r in rows)
    cpu50, wall50, detection = float(rows[-1][2]), float(rows[-1][4]), float(rows[-1][6])
    assert 0 < cpu50 < 60 and 0 < wall50 < 60 and 0 <= detection <= 1
    res = json.loads(out_json.read_text())
    assert f"labels sha1 {res['labels_sha1']}" in out
    (frame,) = res["frames"]
    assert (frame["width"], frame["height"]) == (640, 480) and frame["cpu_s"] == res["groups"]["all"]["cpu_median_s"]
    assert f"{res['groups']['all']['correct_detection_rate']:.3f}" == rows[-1][6]
    # --steps: a VGA frame runs every step; they time the fastest repeat, within its total
    assert list(frame["steps_s"]) == ["edges", "curvature", "seeds", "growing", "merging", "full resolution",
                                      "merging at full resolution", "splits", "reassignment", "elbow joins",
                                      "peel", "border completion", "final fits"]
    assert 0.5 * frame["cpu_s"] < sum(frame["steps_s"].values()) <= frame["cpu_s"]
    assert "segmenter steps, process time per frame (ms)" in out
    # the described column is the figure the runner records for the core on the same trial
    suite = load_suite("smoke")
    spec = suite.trials[0]
    with threadpool_limits(limits=1):  # as in the runner's workers and the benchmark
        record = run_trial(spec, suite.plan, prepare_scene(spec, None))
    runner_rate = record["methods"]["core"]["segmentation"]["correct_detection_rate"]
    assert frame["correct_detection_rate_described"] == pytest.approx(runner_rate)
    assert f"{runner_rate:.3f}" == rows[-1][7]


@pytest.mark.parametrize("argv, message", [(["--repeat", "0"], "--repeat must be >= 1"),
                                           (["--groups", "no_such_group"], "no trial in groups 'no_such_group'")])
def test_segmentation_benchmark_refuses_bad_arguments(argv, message, capsys):
    from harness.bench.segmentation import main as bench_segmentation

    with pytest.raises(SystemExit) as exc:
        bench_segmentation(["--suite", "smoke", *argv])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("conditional_on, changes", [("cab_x", True), ("", False)])
def test_a_conditional_pose_gets_change_detection_and_a_failed_one_none(monkeypatch, conditional_on, changes):
    """A pose that is not ok only because it rests on one object (``conditional_on``) is the pose change detection
    judges the rest of the view against; a pose not ok for another reason gives no change record. The record
    keeps the verdict either way."""
    from dataclasses import replace

    from harness import trial

    real = trial.localise

    def not_ok(*args, **kwargs):
        return replace(real(*args, **kwargs), ok=False, reason="pose rests on cab_x alone",
                       conditional_on=conditional_on)

    monkeypatch.setattr(trial, "localise", not_ok)
    suite = load_suite("smoke")
    spec = suite.trials[0]
    core = trial.run_trial(spec, suite.plan, trial.prepare_scene(spec, None))["methods"]["core"]
    assert not core["pose"]["ok"] and core["pose"]["conditional_on"] == conditional_on
    assert (core["change"] is not None) == changes
