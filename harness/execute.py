"""Trial execution with crash isolation: each trial runs in a forked child process with a timeout.

A trial that raises, hangs past its timeout or kills its process is returned as a failed record with
its reason; the run goes on. Local runs drive up to N children from a thread pool; Dask runs send the
same isolated call to the cluster's workers (each forks its own child), so results are identical.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

from harness.suite import TrialSpec

_CHILDREN: set[int] = set()
_CHILDREN_LOCK = threading.Lock()


def failed_record(spec: TrialSpec, reason: str, detail: str = "", elapsed: float | None = None) -> dict[str, Any]:
    return {"schema": "harness.trial/1", "trial_id": spec.trial_id, "status": "failed", "reason": reason,
            "detail": detail, "spec": spec.to_dict(), "timing_s": {"total": elapsed}, "methods": {}}


def _child(conn, spec: TrialSpec, methods: dict, prepared, artifacts_dir: str | None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C means
    try:
        from harness.trial import TrialFailure, run_trial

        try:
            rec = run_trial(spec, methods, prepared, Path(artifacts_dir) if artifacts_dir else None)
        except TrialFailure as exc:
            rec = failed_record(spec, str(exc))
        conn.send(rec)
    except BaseException as exc:  # noqa: BLE001 - everything a trial raises is recorded, not re-raised
        conn.send(failed_record(spec, f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8)))
    finally:
        conn.close()


def run_isolated(spec: TrialSpec, methods: dict, timeout_s: float, cache_dir: str | None = None,
                 artifacts_dir: str | None = None) -> dict[str, Any]:
    """Run one trial in a forked child; return its record, or a failed record on crash or timeout.

    The trial's scene is prepared (perturbed, compiled) in this process first and cached here, so the
    forked children of later trials of the same scene inherit it instead of redoing it.
    """
    from harness.trial import prepare_scene

    try:
        prepared = prepare_scene(spec, Path(cache_dir) if cache_dir else None)
    except Exception as exc:  # noqa: BLE001 - a scene that cannot be prepared fails its trials, not the run
        return failed_record(spec, f"scene preparation failed: {type(exc).__name__}: {exc}",
                             traceback.format_exc(limit=8))
    ctx = mp.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    t0 = time.perf_counter()
    # the child receives the prepared scene through fork's copy of memory, never through a lock that another
    # thread of this process might hold at the time of the fork
    proc = ctx.Process(target=_child, args=(send, spec, methods, prepared, artifacts_dir), daemon=True)
    proc.start()
    send.close()
    with _CHILDREN_LOCK:
        _CHILDREN.add(proc.pid)
    try:
        record = None
        if recv.poll(timeout_s):
            try:
                record = recv.recv()
            except EOFError:
                record = None  # the child died before sending
        proc.join(timeout=5.0 if record is not None else 0.5)
        elapsed = time.perf_counter() - t0
        if record is not None:
            return record
        if proc.is_alive():
            proc.kill()
            proc.join()
            return failed_record(spec, f"timed out after {timeout_s:g} s", elapsed=elapsed)
        code = proc.exitcode
        how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        return failed_record(spec, f"worker process died ({how})", elapsed=elapsed)
    finally:
        if proc.is_alive():
            proc.kill()
            proc.join()
        recv.close()
        with _CHILDREN_LOCK:
            _CHILDREN.discard(proc.pid)


def kill_children() -> None:
    """Kill every trial child still running (on Ctrl-C)."""
    with _CHILDREN_LOCK:
        pids = list(_CHILDREN)
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def run_local(specs: list[TrialSpec], methods: dict, timeout_s: float, workers: int, cache_dir: str | None,
              artifacts: Callable[[TrialSpec], str | None]) -> Iterator[dict[str, Any]]:
    """Yield trial records as they finish, running up to ``workers`` trials at once."""
    pending = iter(specs)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="trial") as pool:
        running = set()
        try:
            for spec in pending:
                running.add(pool.submit(run_isolated, spec, methods, timeout_s, cache_dir, artifacts(spec)))
                if len(running) >= workers:
                    done, running = wait(running, return_when=FIRST_COMPLETED)
                    for fut in done:
                        yield fut.result()
            while running:
                done, running = wait(running, return_when=FIRST_COMPLETED)
                for fut in done:
                    yield fut.result()
        except BaseException:
            for fut in running:
                fut.cancel()
            kill_children()
            raise


def run_dask(specs: list[TrialSpec], methods: dict, timeout_s: float, client, cache_dir: str | None,
             artifacts: Callable[[TrialSpec], str | None]) -> Iterator[dict[str, Any]]:
    """Yield trial records from a Dask cluster (each worker forks an isolated child per trial)."""
    from distributed import as_completed

    futures = {client.submit(run_isolated, s, methods, timeout_s, cache_dir, artifacts(s), key=f"trial-{s.trial_id}",
                             pure=False): s for s in specs}
    try:
        for fut in as_completed(futures):
            spec = futures[fut]
            try:
                yield fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker is a failed trial, not a failed run
                yield failed_record(spec, f"dask worker failed: {type(exc).__name__}: {exc}")
    except BaseException:
        client.cancel(list(futures))
        raise
