"""Soak test of the runner: many small trials on a Dask LocalCluster, watching memory, leaks and throughput.

Usage::

    python -m harness.bench.soak --trials 1000 --dask-local 2 --out runs/soak

It runs ``--trials`` smoke-like trials (the mock-up, its default perturbations, a tiny 160x120 pinhole
sensor) through the ordinary runner (:func:`harness.run.run_suite`) on a LocalCluster of ``--dask-local``
worker processes, while a sampler thread reads the resident memory (RSS) of every worker and of the trial
processes the workers fork. Afterwards it reports, in ``OUT/soak.json`` and on stdout:

- ``peak_worker_rss_mb``: the largest RSS seen per worker (and of any forked trial process), plus each
  worker's RSS at 10 % and at 100 % of the run (growth between the two is a leak);
- ``children_left``: processes of this program still alive after the cluster closed (must be 0);
- ``temp_files_left``: files left in the private temporary directory the run (and its workers) used, and
  ``.*.tmp`` files left in the results directory (both must be 0);
- ``trials_per_minute``: throughput over the first and the last 10 % of the trials (taken from the
  completion times of the trial records), which should agree within the machine's noise;
- the run's own summary figures (trials, failures, complete).

Exit code 0 when every check passes (no failed trial, nothing left behind, all trials written, last-10 %
throughput at least ``--min-throughput-ratio`` of the first 10 %), 1 otherwise, 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

SENSOR_YAML = """\
schema: sensor/1
name: soak_tiny
description: a 160x120 version of mockup_laser, so that a trial takes a fraction of a second
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise:
  range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4, max_incidence_deg: 80}
  quantisation: {mode: range, step_m: 2.0e-5}
  grazing: {start_deg: 72, end_deg: 86}
  footprint: {rays: 2, radius_px: 0.5, min_return_fraction: 0.5, mixed_threshold_sigma: 3}
  specular: {metal: 0.03, glossy: 0.15}
  outliers: {rate: 2.0e-4}
"""

MB = 1024 * 1024


def soak_suite(n_trials: int, directory: Path, seed: int = 11, timeout_s: float = 120.0):
    """A suite of exactly ``n_trials`` smoke-like trials (mock-up, 160x120 sensor), its sensor file in
    ``directory``. Trials spread over one perturbation seed (scene) per 100 trials, at most 10, then viewpoints."""
    from harness.suite import suite_from_dict

    if n_trials < 1:
        raise ValueError(f"--trials must be >= 1, got {n_trials}")
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "soak_sensor.yaml").write_text(SENSOR_YAML, encoding="utf-8")
    n_scenes = min(10, max(1, n_trials // 100))
    per_scene = [n_trials // n_scenes + (i < n_trials % n_scenes) for i in range(n_scenes)]
    groups = [{"scene": "mockup", "perturbation": "mockup_perturbation", "perturbation_seeds": [i],
               "sensor": "soak_sensor.yaml", "viewpoints": n, "noise_seeds": [0], "label": f"mockup/soak-p{i}",
               "min_view_pixels": 50, "min_view_surfaces": 3} for i, n in enumerate(per_scene)]
    data = {"schema": "suite/1", "name": "soak", "seed": seed, "timeout_s": timeout_s,
            "methods": {"core": {"classifier": "select"}}, "groups": groups}
    return suite_from_dict(data, str(directory / "soak.yaml"), base=directory)


@dataclass
class MemorySampler:
    """Polls the RSS of the given worker processes and of their children every ``interval_s`` seconds."""

    pids: list[int]
    interval_s: float = 0.5
    peak_worker: dict[int, int] = field(default_factory=dict)
    peak_child: int = 0
    samples: list[tuple[float, dict[int, int]]] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._loop, name="soak-memory", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def sample(self) -> None:
        import psutil

        now: dict[int, int] = {}
        for pid in self.pids:
            try:
                proc = psutil.Process(pid)
                now[pid] = proc.memory_info().rss
                for child in proc.children(recursive=True):
                    try:
                        self.peak_child = max(self.peak_child, child.memory_info().rss)
                    except psutil.Error:
                        pass  # a trial process that has just finished
            except psutil.Error:
                continue
        for pid, rss in now.items():
            self.peak_worker[pid] = max(self.peak_worker.get(pid, 0), rss)
        self.samples.append((time.time(), now))

    def _loop(self) -> None:
        while not self._stop.is_set():
            self.sample()
            self._stop.wait(self.interval_s)

    def rss_at(self, t: float) -> dict[int, int]:
        """The sample nearest to time ``t`` (epoch seconds)."""
        if not self.samples:
            return {}
        return min(self.samples, key=lambda s: abs(s[0] - t))[1]


def throughput(finish_times: list[float], fraction: float = 0.1) -> tuple[float | None, float | None]:
    """Trials per minute over the first and the last ``fraction`` of the sorted completion times.

    Each window of ``k`` completions spans from the completion before it (or the first one) to its
    last; None when there are too few trials for two completions per window.
    """
    t = sorted(finish_times)
    k = max(2, math.ceil(len(t) * fraction))
    if len(t) < k + 1:
        return None, None

    def rate(a: int, b: int) -> float | None:
        dt = t[b] - t[a]
        return 60.0 * (b - a) / dt if dt > 0 else None

    return rate(0, k), rate(len(t) - 1 - k, len(t) - 1)


def _alive(proc) -> bool:
    import psutil

    try:
        return proc.is_running() and proc.status() != psutil.STATUS_ZOMBIE
    except psutil.Error:
        return False


def _is_resource_tracker(proc) -> bool:
    """multiprocessing's resource tracker: one per parent process, started by Dask's process spawning and
    meant to live as long as the parent (it is not a per-trial leak)."""
    import psutil

    try:
        return "resource_tracker" in " ".join(proc.cmdline())
    except psutil.Error:
        return False


def _remove_dask_workspace(directory: Path) -> None:
    """Remove Dask's scratch workspace if it holds only its two persistent lock files (``global.lock``,
    ``purge.lock``: created once per process, reused, not a leak); anything else in it is left to report."""
    for ws in (directory / "dask-scratch-space", directory / "dask" / "dask-scratch-space"):
        if ws.is_dir() and {p.name for p in ws.rglob("*") if p.is_file()} <= {"global.lock", "purge.lock"}:
            shutil.rmtree(ws, ignore_errors=True)
    for d in (directory / "dask",):
        if d.is_dir() and not any(p.is_file() for p in d.rglob("*")):
            shutil.rmtree(d, ignore_errors=True)


def _temp_left(directory: Path) -> list[str]:
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*") if p.is_file())


def run_soak(n_trials: int, n_workers: int, out: Path, timeout_s: float = 120.0,
             log=sys.stderr) -> dict[str, Any]:
    """Run the soak and return its report (also written to ``out/soak.json``); see the module docstring."""
    import psutil
    from distributed import Client, LocalCluster

    from harness.run import RunOptions, run_suite
    from harness.store import write_json_atomic

    if n_workers < 1:
        raise ValueError(f"--dask-local must be >= 1, got {n_workers}")
    out = Path(out)
    if (out / "trials").exists() and any((out / "trials").glob("*.json")):
        raise FileExistsError(f"{out} already holds trial records: choose another --out")
    inputs = out / "soak_inputs"
    suite = soak_suite(n_trials, inputs, timeout_s=timeout_s)
    private_tmp = Path(tempfile.mkdtemp(prefix="soak-tmp-", dir=out))
    saved_env = {k: os.environ.get(k) for k in ("TMPDIR", "TEMP", "TMP")}
    for k in saved_env:  # the workers (spawned after this) and their trials inherit the private temp dir
        os.environ[k] = str(private_tmp)
    tempfile.tempdir = None
    me = psutil.Process()
    before = {p.pid for p in me.children(recursive=True)}
    report: dict[str, Any] = {"schema": "harness.soak/1", "trials": n_trials, "workers": n_workers, "out": str(out)}
    t0 = time.time()
    try:
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=40, local_directory=str(private_tmp / "dask"))
        try:
            with Client(cluster) as client:
                pids = sorted(client.run(os.getpid).values())
                sampler = MemorySampler(pids)
                sampler.sample()
                sampler.start()
                try:
                    summary = run_suite(suite, out, RunOptions(scheduler=cluster.scheduler_address, progress=False,
                                                               timeout_s=timeout_s), log=log)
                finally:
                    sampler.stop()
        finally:
            cluster.close()
        wall = time.time() - t0
        time.sleep(1.0)  # let the closed cluster's processes be reaped
        left = [p for p in me.children(recursive=True) if p.pid not in before and _alive(p)
                and not _is_resource_tracker(p)]
        finish = [p.stat().st_mtime for p in (out / "trials").glob("*.json")]
        first, last = throughput(finish)
        t_sorted = sorted(finish)
        k = max(1, math.ceil(len(t_sorted) * 0.1))
        rss_10 = sampler.rss_at(t_sorted[k - 1]) if t_sorted else {}
        rss_end = sampler.rss_at(t_sorted[-1]) if t_sorted else {}
        report |= {
            "wall_s": round(wall, 1),
            "n_written": len(finish), "n_failed": summary["n_failed"], "complete": summary.get("complete"),
            "failures": summary.get("failures", [])[:10],
            "peak_worker_rss_mb": {str(pid): round(v / MB, 1) for pid, v in sampler.peak_worker.items()},
            "peak_trial_process_rss_mb": round(sampler.peak_child / MB, 1),
            "worker_rss_at_10pct_mb": {str(pid): round(v / MB, 1) for pid, v in rss_10.items()},
            "worker_rss_at_end_mb": {str(pid): round(v / MB, 1) for pid, v in rss_end.items()},
            "n_memory_samples": len(sampler.samples),
            "children_left": [f"{p.pid} {' '.join(p.cmdline()[:3])}" for p in left],
            "trials_per_minute": {"first_10pct": first and round(first, 1), "last_10pct": last and round(last, 1),
                                  "overall": round(60 * len(finish) / wall, 1) if wall > 0 else None},
        }
    finally:
        for k, v in saved_env.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        tempfile.tempdir = None
    _remove_dask_workspace(private_tmp)
    report["temp_files_left"] = _temp_left(private_tmp)
    report["partial_files_left"] = sorted(str(p.relative_to(out)) for p in out.rglob(".*.tmp"))
    if not report["temp_files_left"]:
        shutil.rmtree(private_tmp, ignore_errors=True)
    report["checks"] = soak_checks(report)
    write_json_atomic(out / "soak.json", report)
    return report


def soak_checks(report: dict[str, Any], min_ratio: float = 0.7) -> dict[str, bool]:
    """Pass/fail of each soak criterion (see the module docstring)."""
    tpm = report["trials_per_minute"]
    steady = (tpm["first_10pct"] is None or tpm["last_10pct"] is None
              or tpm["last_10pct"] >= min_ratio * tpm["first_10pct"])
    return {"all_trials_written": report["n_written"] == report["trials"] and bool(report["complete"]),
            "no_failed_trial": report["n_failed"] == 0,
            "no_process_left": not report["children_left"],
            "no_temp_file_left": not report["temp_files_left"] and not report["partial_files_left"],
            "throughput_steady": steady}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m harness.bench.soak", description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=1000, help="number of trials (default 1000)")
    parser.add_argument("--dask-local", type=int, default=2, metavar="N", help="LocalCluster workers (default 2)")
    parser.add_argument("--out", type=Path, required=True, help="results directory (must not hold a run)")
    parser.add_argument("--timeout", type=float, default=120.0, help="per-trial timeout in seconds")
    parser.add_argument("--min-throughput-ratio", type=float, default=0.7,
                        help="last-10%% throughput must be at least this fraction of the first 10%%")
    args = parser.parse_args(argv)
    try:
        report = run_soak(args.trials, args.dask_local, args.out, args.timeout)
    except (ValueError, FileExistsError) as exc:
        print(f"soak: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("soak: interrupted", file=sys.stderr)
        return 130
    report["checks"] = soak_checks(report, args.min_throughput_ratio)
    print(json.dumps({k: v for k, v in report.items() if k != "failures"}, indent=1))
    return 0 if all(report["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
