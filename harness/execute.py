"""Trial execution with crash isolation: each trial runs in a forked child process with a timeout.

A trial that raises, hangs past its timeout or kills its process is returned as a failed record with
its reason; the run goes on. Local runs drive up to N children from a thread pool; Dask runs send the
same isolated call to the cluster's workers (each forks its own child), so results are identical.
"""

from __future__ import annotations

import os
import pickle
import select
import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

from harness.suite import TrialPlan, TrialSpec

_CHILDREN: set[int] = set()
_CHILDREN_LOCK = threading.Lock()
_FORK_LOCK = threading.Lock()


def failed_record(spec: TrialSpec, reason: str, detail: str = "", elapsed: float | None = None,
                  retryable: bool = False) -> dict[str, Any]:
    """The record of a trial that did not finish. ``retryable``: the failure came from the machinery (a
    process killed, a timeout, a lost Dask worker), not from the trial's own code and data, so ``--resume``
    runs the trial again instead of keeping this record."""
    return {"schema": "harness.trial/1", "trial_id": spec.trial_id, "status": "failed", "reason": reason,
            "detail": detail, "retryable": retryable, "spec": spec.to_dict(), "timing_s": {"total": elapsed},
            "methods": {}}


def _single_threaded() -> None:
    """One thread per trial for BLAS and Open3D: results then do not depend on the executor (Dask workers
    already limit their threads) nor on the machine's load (a parallel reduction sums in whatever order its
    threads finish), and N trials on N cores do not oversubscribe them. The libraries are imported by the
    parent before it forks (:func:`_import_numerics`), so the child only sets the limits."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1)
    import open3d

    open3d.utility.set_max_threads(1)
    _large_malloc_thresholds()


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc mallopt parameters
_MMAP_THRESHOLD = 32 << 20  # glibc's own ceiling for its dynamic threshold on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX)


def _large_malloc_thresholds() -> None:
    """Let glibc keep freed memory for reuse, as it does once its dynamic thresholds have grown.

    A Dask nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``; setting any threshold switches
    glibc's dynamic mmap threshold off, so every numpy temporary over 128 KiB is a fresh ``mmap`` whose pages
    the kernel zeroes on first touch: measured here, a trial's own time rose by half and the kernel's time
    five-fold on Dask against local workers. The trial child is short-lived, so it sets the thresholds a local
    process reaches by itself (no-op where glibc or ``mallopt`` is not there)."""
    try:
        import ctypes

        libc = ctypes.CDLL(None)
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD)
    except (OSError, AttributeError):
        return


def _import_numerics() -> None:
    import open3d  # noqa: F401 - imported once here so that no trial child pays for it
    import threadpoolctl  # noqa: F401

    from recognition.segmentation import kernels

    kernels.warm_up()  # compiled (or loaded from numba's cache) once here, not in every trial child


def _child_record(spec: TrialSpec, plan: TrialPlan, prepared, artifacts_dir: str | None) -> dict[str, Any]:
    from harness.trial import TrialFailure, run_trial

    try:
        return run_trial(spec, plan, prepared, Path(artifacts_dir) if artifacts_dir else None)
    except TrialFailure as exc:
        return failed_record(spec, str(exc))
    except BaseException as exc:  # noqa: BLE001 - everything a trial raises is recorded, not re-raised
        return failed_record(spec, f"{type(exc).__name__}: {exc}", traceback.format_exc(limit=8))


def run_isolated(spec: TrialSpec, plan: TrialPlan, timeout_s: float, cache_dir: str | None = None,
                 artifacts_dir: str | None = None) -> dict[str, Any]:
    """Run one trial in a forked child; return its record, or a failed record on crash or timeout.

    The trial's scene is prepared (perturbed, compiled) in this process first and cached here, so the
    forked children of later trials of the same scene inherit it instead of redoing it. The child is a
    plain ``os.fork`` (Dask workers are daemonic processes, which multiprocessing forbids to have children)
    and sends its pickled record back through a pipe.
    """
    from harness.trial import prepare_scene

    _import_numerics()
    _large_malloc_thresholds()  # the scene is prepared here, in the (Dask worker's) own process
    t_prepare = time.perf_counter()
    try:
        prepared = prepare_scene(spec, Path(cache_dir) if cache_dir else None)
        t_prepare = time.perf_counter() - t_prepare
    except Exception as exc:  # noqa: BLE001 - a scene that cannot be prepared fails its trials, not the run
        return failed_record(spec, f"scene preparation failed: {type(exc).__name__}: {exc}",
                             traceback.format_exc(limit=8))
    t0 = time.perf_counter()
    # pipe, fork and the parent's close of the write end happen under a lock: a sibling forked by another
    # thread in between would inherit this write end and hide the child's death (no EOF)
    parent = os.getpid()
    with _FORK_LOCK:
        read_fd, write_fd = os.pipe()
        pid = os.fork()
        if pid != 0:
            os.close(write_fd)
            try:  # also set here (the classic race): a kill of the group right after fork must find it
                os.setpgid(pid, pid)
            except (PermissionError, ProcessLookupError):
                pass
    if pid == 0:  # the child: run, send, and leave without running the parent's exit handlers
        code = 0
        try:
            os.close(read_fd)
            signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C means
            os.setpgid(0, 0)  # its own process group: a timeout or Ctrl-C kills whatever the trial started too
            _die_with_parent(parent)  # ...and, outside the parent's group now, it must not outlive the parent
            _single_threaded()
            # the prepared scene reaches the child through fork's copy of memory, never through a lock
            # that another thread of the parent might hold at the time of the fork
            data = pickle.dumps(_child_record(spec, plan, prepared, artifacts_dir))
            with os.fdopen(write_fd, "wb") as f:
                f.write(data)
        except BaseException:  # noqa: BLE001
            code = 1
        finally:
            os._exit(code)
    with _CHILDREN_LOCK:
        _CHILDREN.add(pid)
    try:
        chunks, timed_out = [], False
        deadline = t0 + timeout_s
        while True:
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                timed_out = True
                break
            ready, _, _ = select.select([read_fd], [], [], remaining)
            if not ready:
                continue
            chunk = os.read(read_fd, 1 << 20)
            if not chunk:
                break
            chunks.append(chunk)
        elapsed = time.perf_counter() - t0
        if timed_out:
            _kill(pid)
            return failed_record(spec, f"timed out after {timeout_s:g} s", elapsed=elapsed, retryable=True)
        _kill_group(pid)  # processes the trial left behind (before reaping the child: its group id stays ours)
        _, status = os.waitpid(pid, 0)
        if chunks:
            try:
                record = pickle.loads(b"".join(chunks))
            except Exception:  # noqa: BLE001 - a truncated record is a crashed trial
                record = None
            if record is not None:
                record.setdefault("timing_s", {})["prepare"] = t_prepare
                record["timing_s"]["isolated"] = elapsed
                return record
        if os.WIFSIGNALED(status):
            how = f"killed by signal {os.WTERMSIG(status)}"
        else:
            how = f"exit code {os.WEXITSTATUS(status)}"
        return failed_record(spec, f"worker process died ({how})", elapsed=elapsed, retryable=True)
    finally:
        os.close(read_fd)
        with _CHILDREN_LOCK:
            _CHILDREN.discard(pid)


def _die_with_parent(parent: int) -> None:
    """In a trial child: be killed when the parent dies (Linux ``PR_SET_PDEATHSIG``; elsewhere a no-op), so a
    runner killed outright (SIGKILL, OOM) leaves no trial running."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL, 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the call
        os._exit(1)


def _kill(pid: int) -> None:
    """Kill a trial child and its process group (anything it started), and reap it."""
    _kill_group(pid)
    try:
        os.kill(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    try:
        os.waitpid(pid, 0)
    except ChildProcessError:
        pass


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass  # no process left in the group


def kill_children() -> None:
    """Kill every trial child still running (on Ctrl-C)."""
    with _CHILDREN_LOCK:
        pids = list(_CHILDREN)
    for pid in pids:
        _kill_group(pid)
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def run_local(specs: list[TrialSpec], plan: TrialPlan, timeout_s: float, workers: int, cache_dir: str | None,
              artifacts: Callable[[TrialSpec], str | None]) -> Iterator[dict[str, Any]]:
    """Yield trial records as they finish, running up to ``workers`` trials at once."""
    pending = iter(specs)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="trial") as pool:
        running = set()
        try:
            for spec in pending:
                running.add(pool.submit(run_isolated, spec, plan, timeout_s, cache_dir, artifacts(spec)))
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


def run_dask(specs: list[TrialSpec], plan: TrialPlan, timeout_s: float, client, cache_dir: str | None,
             artifacts: Callable[[TrialSpec], str | None]) -> Iterator[dict[str, Any]]:
    """Yield trial records from a Dask cluster (each worker forks an isolated child per trial).

    The trials of one scene go to the cluster as tasks of up to ``DASK_BATCH`` trials, run one after the other
    on one worker: the scene is prepared once per batch, nearly as in a local run (where the worker threads
    share one process), not once per worker that happens to draw one of its trials. A batch's records arrive
    together, so a batch is kept small."""
    from distributed import as_completed

    futures = {client.submit(run_isolated_batch, batch, plan, timeout_s, cache_dir, [artifacts(s) for s in batch],
                             key=f"trials-{batch[0].trial_id}", pure=False): batch for batch in scene_batches(specs)}
    try:
        for fut in as_completed(futures):
            batch = futures[fut]
            try:
                yield from fut.result()
            except Exception as exc:  # noqa: BLE001 - a lost worker is a failed trial, not a failed run
                for spec in batch:
                    yield failed_record(spec, f"dask worker failed: {type(exc).__name__}: {exc}", retryable=True)
    except BaseException:
        client.cancel(list(futures))
        raise


DASK_BATCH = 4


def scene_batches(specs: list[TrialSpec], size: int = DASK_BATCH) -> list[list[TrialSpec]]:
    """``specs`` grouped by prepared scene (a priori scene, perturbation spec and seed), in first-seen order,
    in batches of at most ``size``."""
    by_scene: dict[tuple, list[TrialSpec]] = {}
    for spec in specs:
        by_scene.setdefault(spec.prepared_key, []).append(spec)
    return [group[i:i + size] for group in by_scene.values() for i in range(0, len(group), size)]


def run_isolated_batch(specs: list[TrialSpec], plan: TrialPlan, timeout_s: float, cache_dir: str | None,
                       artifacts_dirs: list[str | None]) -> list[dict[str, Any]]:
    """:func:`run_isolated` on each trial of a batch, in order (each in its own child, with its own timeout)."""
    return [run_isolated(s, plan, timeout_s, cache_dir, a) for s, a in zip(specs, artifacts_dirs, strict=True)]
