"""Running a suite into a results directory: resume, progress, summary; local or on a Dask cluster."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from harness.execute import failed_record, run_dask, run_local
from harness.provenance import CodeIdentity, code_identity, describe_code, plugin_versions, provenance
from harness.store import RunDirectory, non_finite_paths, write_json_atomic
from harness.suite import Suite, TrialSpec, closest_hint
from harness.summary import summarise


@dataclass(frozen=True)
class RunOptions:
    """How to run a suite (all optional)."""

    workers: int | None = None
    resume: bool = False
    only: tuple[str, ...] = ()
    artifacts: bool = False
    scheduler: str | None = None
    dask_local: int | None = None
    timeout_s: float | None = None
    progress: bool | None = None  # None: a progress bar on a terminal, log lines otherwise
    overwrite: bool = False
    resume_any_code: bool = False  # with resume: complete a run made by other code (run.json says so)


class CodeMismatchError(ValueError):
    """``--resume`` of a run directory whose run.json or trial records were made by other code."""


class Progress:
    """A one-line progress bar with ETA on a terminal, plain log lines otherwise."""

    def __init__(self, total: int, stream: TextIO = sys.stderr, bar: bool | None = None):
        self.total, self.stream = total, stream
        self.bar = stream.isatty() if bar is None else bar
        self.done = self.failed = 0
        self.t0 = time.perf_counter()

    def update(self, record: dict[str, Any]) -> None:
        self.done += 1
        self.failed += record.get("status") != "ok"
        elapsed = time.perf_counter() - self.t0
        eta = elapsed / self.done * (self.total - self.done)
        if self.bar:
            width = 30
            fill = int(width * self.done / max(self.total, 1))
            self.stream.write(f"\r[{'#' * fill}{'.' * (width - fill)}] {self.done}/{self.total} "
                              f"failed {self.failed}  {elapsed:5.0f} s  ETA {eta:5.0f} s ")
            if self.done == self.total:
                self.stream.write("\n")
        else:
            status = "ok" if record.get("status") == "ok" else f"FAILED: {record.get('reason', '')}"
            self.stream.write(f"[{self.done}/{self.total}] {record['trial_id']}: {status} "
                              f"({(record.get('timing_s') or {}).get('total') or 0:.2f} s, ETA {eta:.0f} s)\n")
        self.stream.flush()


def run_suite(suite: Suite, out: Path, options: RunOptions = RunOptions(), log: TextIO = sys.stderr) -> dict:
    """Run ``suite`` into ``out`` and return the summary (also written to ``out/summary.json``).

    Finished trials are written one by one as they complete; on Ctrl-C the children are killed, the
    summary of what finished is written, and KeyboardInterrupt propagates. ``resume`` skips trials already
    recorded with the same configuration hash, and refuses (:class:`CodeMismatchError`) when ``run.json`` or a
    record it would keep was made by other code (DESIGN 11.4), unless ``resume_any_code``: then ``run.json``
    lists every code identity the run mixes under ``mixed_codes``.

    The code identity (:func:`harness.provenance.code_identity`, with the versions of the plug-in packages the
    suite's methods come from) is computed once, here, and written into ``run.json``, the summary's provenance
    and every trial record (``code``) as it is written.
    """
    config_hash = suite.config_hash
    code = code_identity()
    if suite.plugins:  # the versions of the plug-in packages the suite's methods come from
        code = dataclasses.replace(code, plugins=plugin_versions(suite.plugins))
    code_json = code.as_json()
    specs: list[TrialSpec] = list(suite.trials)
    if options.only:
        unknown = sorted(set(options.only) - {t.trial_id for t in specs})
        if unknown:
            hint = closest_hint(unknown[0], [t.trial_id for t in specs])
            raise ValueError(f"--only: no trial {unknown[0]!r} in suite {suite.name!r}{hint}; "
                             f"`harness bench --suite {suite.name} --list` lists its {len(specs)} trials")
        specs = [t for t in specs if t.trial_id in options.only]
    with RunDirectory(out) as run_dir:
        done = run_dir.finished(config_hash) if options.resume else set()
        mixed = resume_codes(run_dir, done, code, options.resume_any_code) if options.resume else []
        todo = [t for t in specs if t.trial_id not in done]
        existing = sorted(run_dir.trials_dir.glob("*.json"))
        if existing and not options.resume:
            if not options.overwrite:
                raise FileExistsError(f"{out} already holds {len(existing)} trial record(s): use --resume to complete "
                                      "that run, --overwrite to discard it, or another --out")
            for p in existing:
                p.unlink()
        prov = provenance(code)
        manifest = {"schema": "harness.run/1", "suite": suite.name, "source": suite.source,
                    "config_hash": config_hash, "code": code_json, "suite_config": suite.raw,
                    "trials": [t.trial_id for t in suite.trials], "provenance": prov}
        if mixed:
            manifest["mixed_codes"] = prov["mixed_codes"] = mixed
        write_json_atomic(out / "run.json", manifest)
        workers = options.workers or os.cpu_count() or 1
        # what runs the trials: local worker threads, the LocalCluster's workers, or (a remote cluster) unknown
        executors = options.dask_local if options.dask_local else None if options.scheduler else workers
        timeout = options.timeout_s or suite.timeout_s
        artifacts_root = out / "artifacts"

        def artifacts(spec: TrialSpec) -> str | None:
            return str(artifacts_root / spec.trial_id) if options.artifacts else None

        log.write(f"suite {suite.name}: {len(specs)} trials ({len(specs) - len(todo)} already done), "
                  f"{'dask' if options.scheduler or options.dask_local else f'{workers} local worker(s)'} -> {out}\n")
        progress = Progress(len(todo), log, options.progress)
        t0 = time.perf_counter()
        try:
            by_id = {t.trial_id: t for t in todo}
            for record in _execute(todo, suite, options, workers, timeout, str(run_dir.cache_dir), artifacts):
                record["config_hash"] = config_hash
                record["code"] = code_json
                try:
                    run_dir.write_trial(record)
                except (ValueError, TypeError) as exc:  # NaN or an odd type in the record: a failed trial, explained
                    record = _unwritable(by_id[record["trial_id"]], record, exc, config_hash)
                    record["code"] = code_json
                    run_dir.write_trial(record)
                progress.update(record)
        finally:
            wall = time.perf_counter() - t0
            with _sigint_deferred():  # a second Ctrl-C lands after the summary is written, not inside it
                records = run_dir.read_trials([t.trial_id for t in specs])
                complete = len(records) == len(specs)
                summary = summarise(records, suite=suite.name, config_hash=config_hash, version=prov["version"],
                                    methods=list(suite.methods), oracles=list(suite.oracles), extra={
                                        "complete": complete, "n_planned": len(specs), "provenance": prov,
                                        "run": _throughput(records, progress.done, wall, executors)})
                write_json_atomic(out / "summary.json", summary)
    return summary


def resume_codes(run_dir: RunDirectory, kept: set[str], code: CodeIdentity, any_code: bool) -> list[Any]:
    """The code identities a resumed run would mix, checked before anything runs.

    Parameters
    ----------
    kept : ids of the trial records the resumed run keeps (the others are run again, so their code is moot).
    code : this process's code identity.
    any_code : accept other code (``--resume-any-code``) instead of refusing.

    Returns
    -------
    [] when ``run.json`` (and the identities it already lists as mixed) and every kept record carry ``code``;
    otherwise the distinct ``code`` entries of the run, this code last (None: a record or run.json written
    before code identities).

    Raises
    ------
    CodeMismatchError
        When other code made them and ``any_code`` is false: one line naming both identities.
    """
    found: list[tuple[str, Any]] = []
    manifest = run_dir.read_manifest()
    if manifest is not None:
        earlier = manifest.get("mixed_codes")
        found += [("run.json", c) for c in earlier] if isinstance(earlier, list) else []
        found.append(("run.json", manifest.get("code")))
    found += [(f"trial record {t}", c) for t, c in run_dir.recorded_codes(kept).items()]
    others = [(where, c) for where, c in found if CodeIdentity.from_json(c) != code]
    if not others:
        return []
    if not any_code:
        where, other = others[0]
        more = f" (and {len(others) - 1} more)" if len(others) > 1 else ""
        raise CodeMismatchError(f"{run_dir.root}: --resume refused: its {where}{more} was made by other code "
                                f"({describe_code(other)}) than this ({code.describe()}); use another --out, "
                                "or --resume-any-code to mix them")
    distinct: list[Any] = []
    for _, c in [*found, ("this run", code.as_json())]:
        if all(CodeIdentity.from_json(c) != CodeIdentity.from_json(d) for d in distinct):
            distinct.append(c)
    return [d for d in distinct if CodeIdentity.from_json(d) != code] + [code.as_json()]


@contextlib.contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Hold back Ctrl-C during the block (main thread only): one that arrives meanwhile is re-delivered to the
    previous handler at its end (KeyboardInterrupt by default), so the block is never cut in half."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: pending.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if pending and callable(previous):
            previous(signal.SIGINT, None)


def _unwritable(spec: TrialSpec, record: dict, exc: Exception, config_hash: str) -> dict[str, Any]:
    """The failed record that replaces a trial record strict JSON cannot hold (the run goes on)."""
    bad = non_finite_paths(record)
    why = f"non-finite numbers at {', '.join(bad[:5])}" + (f" and {len(bad) - 5} more" if len(bad) > 5 else "") \
        if bad else f"{type(exc).__name__}: {exc}"
    failed = failed_record(spec, f"trial record cannot be written as JSON: {why}", detail=str(exc),
                           elapsed=(record.get("timing_s") or {}).get("total"))
    failed["config_hash"] = config_hash
    return failed


def _throughput(records: list[dict], n_run: int, wall: float, workers: int | None) -> dict[str, Any]:
    """Wall time, trials per minute, and the runner's overhead: the share of the workers' time spent
    neither preparing scenes nor inside trials (fork, transfer, writing, scheduling). ``workers``: how many
    run trials at once (None for a remote Dask cluster, whose size the runner does not own: no overhead)."""
    work = sum((r.get("timing_s") or {}).get("total") or 0.0 for r in records)
    prepare = sum((r.get("timing_s") or {}).get("prepare") or 0.0 for r in records)
    isolated = sum((r.get("timing_s") or {}).get("isolated") or 0.0 for r in records)
    return {"wall_s": wall, "workers": workers, "n_run": n_run,
            "trials_per_minute": 60 * n_run / wall if wall > 0 else None,
            "trial_work_s": work, "prepare_s": prepare,
            "isolation_overhead_fraction": (isolated - work) / work if work > 0 else None,
            "overhead_fraction": (wall * min(workers, max(n_run, 1)) - work - prepare) / work
            if workers and work > 0 and n_run == len(records) else None}


def _execute(todo, suite, options, workers, timeout, cache_dir, artifacts):
    if options.scheduler or options.dask_local:
        from distributed import Client, LocalCluster

        if options.scheduler:
            client = Client(options.scheduler, timeout="30s")
            cluster = None
        else:
            import dask

            # the worker's statistical profiler samples every thread's stack each 10 ms: a few percent of a
            # core per worker for a picture nobody looks at here (no dashboard)
            with dask.config.set({"distributed.worker.profile.enabled": False}):
                cluster = LocalCluster(n_workers=options.dask_local, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=40)
            client = Client(cluster)
        try:
            yield from run_dask(todo, suite.plan, timeout, client, cache_dir, artifacts)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    else:
        yield from run_local(todo, suite.plan, timeout, workers, cache_dir, artifacts)
