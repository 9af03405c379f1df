"""Faults in the runner: a full disk, Ctrl-C at random moments, two runs on one directory, trials that hang
(leaving processes behind), die or return records JSON cannot hold, and a Dask worker killed mid-run.

After each fault the results directory is consistent (every ``trials/*.json`` parses and is a complete
record, no temporary file is left, ``summary.json`` parses and agrees with the records), ``--resume``
completes the run, and every trial that had finished is kept bit-identical.

The full disk is simulated: ``os.fsync`` raises ``OSError(ENOSPC)`` for every write into ``trials/`` from
the N-th on (``write_text_atomic`` writes, flushes and fsyncs a temporary file, then renames it), which
is where a real ``ENOSPC`` surfaces for a small JSON file on most file systems. (A tiny tmpfs needs root.)
"""

from __future__ import annotations

import errno
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from harness.cli import main
from harness.commands.bench import EXIT_TRIALS_FAILED
from harness.run import RunOptions, run_suite
from harness.suite import load_suite

SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise:
  range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
  footprint: {rays: 2, radius_px: 0.5, min_return_fraction: 0.5, mixed_threshold_sigma: 3}
"""

SUITE = """
schema: suite/1
name: faults
seed: 5
timeout_s: 60
methods: {core: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    perturbation_seeds: [0]
    sensor: tiny_sensor.yaml
    viewpoints: VIEWPOINTS
    noise_seeds: [0]
    min_view_pixels: 50
    min_view_surfaces: 3
"""


def make_suite(directory: Path, viewpoints: int = 3) -> Path:
    (directory / "tiny_sensor.yaml").write_text(SENSOR)
    path = directory / "faults.yaml"
    path.write_text(SUITE.replace("VIEWPOINTS", str(viewpoints)))
    return path


@pytest.fixture()
def suite_path(tmp_path):
    return make_suite(tmp_path)


def run(suite_path: Path, out: Path, **kw) -> dict:
    options = RunOptions(workers=kw.pop("workers", 1), progress=False, **kw)
    with open(os.devnull, "w") as log:
        return run_suite(load_suite(str(suite_path)), out, options, log=log)


def bench_cmd(suite_path: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "harness", "bench", "--suite", str(suite_path), "--out", str(out), "--no-report",
            "--progress", "log", *extra]


def _default_sigint() -> None:
    """Child processes start with Ctrl-C handled (a background job of a non-interactive shell ignores it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def check_consistent(out: Path) -> dict[str, bytes]:
    """Assert the results directory is consistent; return the bytes of every record that counts as finished."""
    assert not list(out.rglob(".*.tmp")), "temporary files left behind"
    finished = {}
    trials = sorted((out / "trials").glob("*.json")) if (out / "trials").exists() else []
    for p in trials:
        rec = json.loads(p.read_bytes())  # parses, or the test fails here
        assert rec["schema"] == "harness.trial/1" and rec["trial_id"] == p.stem and rec["config_hash"]
        assert rec["status"] in ("ok", "failed"), rec["status"]
        if rec["status"] == "ok":
            assert rec["methods"]["core"], "a complete record has the core's results"
        else:
            assert rec["reason"], "a failure says why"
        if not rec.get("retryable"):
            finished[p.name] = p.read_bytes()
    if trials or (out / "run.json").exists():
        summary = json.loads((out / "summary.json").read_bytes())
        assert summary["schema"] == "harness.summary/1"
        assert summary["n_trials"] == len(trials)
    return finished


def resume_and_check(suite_path: Path, out: Path, finished: dict[str, bytes], n_trials: int) -> dict:
    code = main(["bench", "--suite", str(suite_path), "--out", str(out), "--resume", "--workers", "1",
                 "--no-report", "--progress", "log"])
    check_consistent(out)
    for name, data in finished.items():
        assert (out / "trials" / name).read_bytes() == data, f"{name} changed on resume"
    summary = json.loads((out / "summary.json").read_bytes())
    assert code == (EXIT_TRIALS_FAILED if summary["n_failed"] else 0)  # a failure kept on resume is still one
    assert summary["complete"] and summary["n_trials"] == n_trials
    return summary


# ------------------------------------------------------------------------------------------------ full disk


def _full_disk_after(monkeypatch, n_ok: int) -> list[str]:
    """Make every fsync of a file in a ``trials`` directory fail with ENOSPC after ``n_ok`` succeeded."""
    real = os.fsync
    seen: list[str] = []

    def fsync(fd: int) -> None:
        target = os.readlink(f"/proc/self/fd/{fd}")
        if Path(target).parent.name == "trials":
            seen.append(target)
            if len(seen) > n_ok:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), target)
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    return seen


def test_full_disk_stops_the_run_cleanly_and_resume_completes_it(suite_path, tmp_path, monkeypatch, capsys):
    out = tmp_path / "disk"
    writes = _full_disk_after(monkeypatch, n_ok=1)
    code = main(["bench", "--suite", str(suite_path), "--out", str(out), "--workers", "1", "--no-report",
                 "--progress", "log"])
    err = capsys.readouterr().err
    assert code == 1 and "No space left on device" in err and "Traceback" not in err
    assert len(writes) == 2  # the first record was written, the second hit the full disk and stopped the run
    assert not list(out.rglob(".*.tmp"))
    records = list((out / "trials").glob("*.json"))
    assert len(records) == 1
    finished = check_consistent(out)  # the summary was written beside (not into trials/)
    monkeypatch.undo()  # space is freed
    resume_and_check(suite_path, out, finished, n_trials=3)


@pytest.mark.slow
def test_full_disk_for_the_summary_too(suite_path, tmp_path, monkeypatch):
    """The disk stays full for every file: the records that made it are intact, the summary is absent or old,
    never partial."""
    out = tmp_path / "full"
    real = os.fsync
    count = {"trials": 0}

    def fsync(fd: int) -> None:
        target = Path(os.readlink(f"/proc/self/fd/{fd}"))
        if target.parent.name == "trials":
            count["trials"] += 1
        if count["trials"] >= 2 and target.parent.name != "cache":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(target))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    with pytest.raises(OSError) as info:
        run(suite_path, out)
    assert info.value.errno == errno.ENOSPC
    monkeypatch.undo()
    assert not list(out.rglob(".*.tmp"))
    assert len(list((out / "trials").glob("*.json"))) == 1
    assert not (out / "summary.json").exists()  # never a partial summary
    finished = {p.name: p.read_bytes() for p in (out / "trials").glob("*.json")}
    resume_and_check(suite_path, out, finished, n_trials=3)


# ------------------------------------------------------------------------------------------------ Ctrl-C


def _interrupt_at(suite_path: Path, out: Path, delay_s: float) -> int:
    proc = subprocess.Popen(bench_cmd(suite_path, out, "--workers", "2"), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, start_new_session=True, preexec_fn=_default_sigint)
    time.sleep(delay_s)
    try:
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
    except ProcessLookupError:
        pass
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"harness bench did not stop within 60 s of Ctrl-C at {delay_s:.2f} s")
    if proc.returncode == 130:
        assert b"interrupted" in err and b"Traceback" not in err, err.decode()[-2000:]
    return proc.returncode


@pytest.mark.parametrize("seed", [0])
def test_ctrl_c_at_a_random_moment(suite_path, tmp_path, seed):
    """SIGINT to the process group at a random time between start-up and the end of the run."""
    delay = random.Random(seed).uniform(0.3, 9.0)
    out = tmp_path / f"int{seed}"
    code = _interrupt_at(suite_path, out, delay)
    assert code in (130, 0), f"exit code {code} after Ctrl-C at {delay:.2f} s"
    finished = check_consistent(out)
    resume_and_check(suite_path, out, finished, n_trials=3)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(1, 10))
def test_ctrl_c_at_many_random_moments(tmp_path, seed):
    suite_path = make_suite(tmp_path, viewpoints=4)
    delay = random.Random(seed).uniform(0.05, 14.0)
    out = tmp_path / "int"
    code = _interrupt_at(suite_path, out, delay)
    assert code in (130, 0), f"exit code {code} after Ctrl-C at {delay:.2f} s"
    finished = check_consistent(out)
    resume_and_check(suite_path, out, finished, n_trials=4)


# ------------------------------------------------------------------------------------------------ two runs


def test_two_runs_on_one_directory_across_processes(suite_path, tmp_path):
    """Another process holds the directory's lock (as a running ``harness bench`` does for its whole run): every
    kind of second run is refused with a clear message, exit code 2, nothing written; once the holder is gone
    the run proceeds."""
    out = tmp_path / "shared"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time\nfrom harness.store import RunDirectory\n"
                               f"with RunDirectory({str(out)!r}):\n    print('locked', flush=True)\n"
                               "    time.sleep(120)"], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        for extra in ((), ("--resume",), ("--overwrite",)):
            second = subprocess.run(bench_cmd(suite_path, out, "--workers", "1", *extra), capture_output=True,
                                    text=True, timeout=60)
            assert second.returncode == 2, second.stderr
            assert "another run is writing here" in second.stderr and str(out) in second.stderr
            assert "Traceback" not in second.stderr
        assert not list((out / "trials").glob("*")) and not (out / "run.json").exists()
    finally:
        os.killpg(holder.pid, signal.SIGKILL)  # a holder killed outright: the kernel releases its lock
        holder.wait()
    assert main(["bench", "--suite", str(suite_path), "--out", str(out), "--workers", "1", "--no-report",
                 "--progress", "log"]) == 0
    assert len(check_consistent(out)) == 3


# ------------------------------------------------------------------------------------------------ trials


def test_a_hung_trial_and_the_processes_it_started_are_killed(suite_path, tmp_path, monkeypatch):
    """A trial that starts a helper process and hangs is killed at its timeout with everything it started; a
    trial that finishes but leaves a process behind has that process killed too."""
    import harness.trial as trial

    real = trial.run_trial
    pids = tmp_path / "pids"
    pids.mkdir()

    def leaky(spec, *args, **kw):
        helper = subprocess.Popen(["sleep", "300"])
        (pids / f"{spec.viewpoint}").write_text(str(helper.pid))
        if spec.viewpoint == 0:
            time.sleep(300)
        return real(spec, *args, **kw)

    monkeypatch.setattr(trial, "run_trial", leaky)
    out = tmp_path / "hang"
    t0 = time.perf_counter()
    summary = run(suite_path, out, timeout_s=4.0, workers=2, only=("mockup-p0-v0-tiny_sensor-n0",
                                                                     "mockup-p0-v1-tiny_sensor-n0"))
    assert time.perf_counter() - t0 < 60
    reasons = {f["trial_id"]: f["reason"] for f in summary["failures"]}
    assert reasons == {"mockup-p0-v0-tiny_sensor-n0": "timed out after 4 s"}
    time.sleep(0.5)
    for p in pids.iterdir():
        pid = int(p.read_text())
        assert not _alive(pid), f"process {pid} started by trial v{p.name} is still running"
    rec = json.loads((out / "trials" / "mockup-p0-v0-tiny_sensor-n0.json").read_text())
    assert rec["retryable"] is True


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_resume_retries_machinery_failures_and_keeps_the_rest(suite_path, tmp_path, monkeypatch):
    import harness.trial as trial

    real = trial.run_trial

    def faulty(spec, *args, **kw):
        if spec.viewpoint == 0:
            raise RuntimeError("a bug in the trial: deterministic, kept")
        if spec.viewpoint == 1:
            os.kill(os.getpid(), signal.SIGKILL)  # the machinery: retried on resume
        return real(spec, *args, **kw)

    monkeypatch.setattr(trial, "run_trial", faulty)
    out = tmp_path / "retry"
    first = run(suite_path, out, workers=2)
    assert first["n_failed"] == 2
    finished = check_consistent(out)
    assert sorted(finished) == ["mockup-p0-v0-tiny_sensor-n0.json", "mockup-p0-v2-tiny_sensor-n0.json"]
    monkeypatch.undo()
    summary = resume_and_check(suite_path, out, finished, n_trials=3)
    assert [f["trial_id"] for f in summary["failures"]] == ["mockup-p0-v0-tiny_sensor-n0"]


def test_a_record_json_cannot_hold_becomes_an_explained_failure(suite_path, tmp_path, monkeypatch):
    import harness.trial as trial

    real = trial.run_trial

    def with_nan(spec, *args, **kw):
        rec = real(spec, *args, **kw)
        if spec.viewpoint == 1:
            rec["methods"]["core"]["segmentation"]["correct_detection_rate"] = float("nan")
        return rec

    monkeypatch.setattr(trial, "run_trial", with_nan)
    out = tmp_path / "nan"
    summary = run(suite_path, out, workers=2)
    assert summary["n_trials"] == 3 and summary["complete"]
    [failure] = summary["failures"]
    assert failure["trial_id"] == "mockup-p0-v1-tiny_sensor-n0"
    assert "methods.core.segmentation.correct_detection_rate (nan)" in failure["reason"]
    check_consistent(out)


@pytest.mark.slow
def test_dask_worker_killed_mid_run(suite_path, tmp_path):
    """SIGKILL one of two Dask workers while trials run: the scheduler reschedules or the trial is recorded as a
    retryable failure; the run completes and resume leaves nothing failed."""
    pytest.importorskip("distributed")
    import threading

    from distributed import Client, LocalCluster

    suite_path = make_suite(tmp_path, viewpoints=6)
    out = tmp_path / "dask"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=40) as cluster, Client(cluster) as client:
        victim = next(iter(client.run(os.getpid).values()))

        def killer() -> None:
            deadline = time.time() + 120
            while time.time() < deadline and not list((out / "trials").glob("*.json")):
                time.sleep(0.05)
            time.sleep(0.3)
            os.kill(victim, signal.SIGKILL)

        thread = threading.Thread(target=killer, daemon=True)
        thread.start()
        summary = run(suite_path, out, scheduler=cluster.scheduler_address)
        thread.join()
    assert not _alive(victim)
    assert summary["n_trials"] == 6 and summary["complete"]
    for f in summary["failures"]:
        assert "dask worker failed" in f["reason"] or "worker process died" in f["reason"], f
    finished = check_consistent(out)
    final = resume_and_check(suite_path, out, finished, n_trials=6)
    assert final["n_failed"] == 0, final["failures"]


def test_a_second_ctrl_c_while_the_summary_is_written_does_not_cut_it(suite_path, tmp_path, monkeypatch, request):
    """Ctrl-C pressed again while the summary of an interrupted (or finished) run is being written: the summary
    is completed first, then the interrupt propagates."""
    import harness.run as run_module

    # Ctrl-C must mean KeyboardInterrupt here, as in a terminal; a pytest started as a background job of a
    # non-interactive shell inherits SIGINT ignored, and then a deferred interrupt is rightly dropped
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    real = run_module.summarise

    def interrupted(*args, **kw):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.1)  # the interrupt is pending here
        return real(*args, **kw)

    monkeypatch.setattr(run_module, "summarise", interrupted)
    out = tmp_path / "again"
    with pytest.raises(KeyboardInterrupt):
        run(suite_path, out, only=("mockup-p0-v0-tiny_sensor-n0",))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_trials"] == 1
