"""The results directory: one JSON per finished trial, written atomically, a lock against concurrent runs,
and the run's manifest.

Layout::

    RUN_DIR/
      run.json                 suite, config hash, code identity, provenance, the list of trial ids
      trials/<trial_id>.json   one per finished (or failed) trial, written as temp file + rename; each
                               carries the config hash and the code identity of the run that wrote it
      summary.json             aggregate (DESIGN 8), rewritten atomically at the end
      cache/                   per-scene derived data (perturbed scenes), safe to delete
      .lock                    held while a run writes here
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import tempfile
from pathlib import Path
from typing import Any


class RunLockedError(RuntimeError):
    """Another run is writing into the same results directory."""


_HELD_LOCKS: set[int] = set()


def _release_locks_in_child() -> None:
    """A forked trial process must not share the run's lock: a lock is held while any copy of its descriptor is
    open, so a trial outliving a killed runner would keep the directory locked."""
    for fd in _HELD_LOCKS:
        try:
            os.close(fd)
        except OSError:
            pass
    _HELD_LOCKS.clear()


os.register_at_fork(after_in_child=_release_locks_in_child)


def write_json_atomic(path: Path, data: Any) -> None:
    """Write ``data`` as JSON to ``path`` atomically (see :func:`write_text_atomic`)."""
    write_text_atomic(path, json.dumps(data, indent=1, allow_nan=False, default=_json_default))


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory and a rename, so readers
    see the old file or the new one, never a partial one. A full disk raises OSError and leaves no
    temporary file behind."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def non_finite_paths(obj: Any, path: str = "") -> list[str]:
    """Paths (``a.b[2].c``) of the NaN / infinite floats inside plain data, which strict JSON cannot hold."""
    import numpy as np

    if isinstance(obj, float | np.floating):
        return [] if np.isfinite(obj) else [f"{path or '<root>'} ({float(obj)})"]
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in non_finite_paths(v, f"{path}.{k}" if path else str(k))]
    if isinstance(obj, list | tuple):
        return [p for i, v in enumerate(obj) for p in non_finite_paths(v, f"{path}[{i}]")]
    if isinstance(obj, np.ndarray) and obj.dtype.kind == "f" and not np.isfinite(obj).all():
        return [f"{path} (array with non-finite values)"]
    return []


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_json(path: Path) -> Any:
    with open(path, encoding="utf-8") as f:
        return json.load(f)


class RunDirectory:
    """A results directory, locked for writing while open (use as a context manager)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.trials_dir = self.root / "trials"
        self.cache_dir = self.root / "cache"
        self._lock_fd: int | None = None

    def __enter__(self) -> RunDirectory:
        self.root.mkdir(parents=True, exist_ok=True)
        self.trials_dir.mkdir(exist_ok=True)
        self.cache_dir.mkdir(exist_ok=True)
        fd = os.open(self.root / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in (errno.EAGAIN, errno.EACCES):
                raise RunLockedError(f"{self.root}: another run is writing here (lock held on {self.root / '.lock'}); "
                                     "wait for it or choose another --out") from None
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock_fd = fd
        _HELD_LOCKS.add(fd)
        self.clean_temporaries()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._lock_fd is not None:
            _HELD_LOCKS.discard(self._lock_fd)
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def clean_temporaries(self) -> int:
        """Remove temporary files left by an interrupted write (never a finished file)."""
        n = 0
        for d in (self.root, self.trials_dir, self.cache_dir):
            for p in d.glob(".*.tmp"):
                p.unlink(missing_ok=True)
                n += 1
        return n

    def trial_path(self, trial_id: str) -> Path:
        return self.trials_dir / f"{trial_id}.json"

    def finished(self, config_hash: str) -> set[str]:
        """Ids of trials already recorded by a run with the same configuration hash; a failure of the machinery
        (``retryable``: killed process, timeout, lost worker) does not count, so a resumed run retries it."""
        done = set()
        for p in self.trials_dir.glob("*.json"):
            try:
                rec = read_json(p)
            except (OSError, ValueError):
                continue  # unreadable: it will be run again
            if isinstance(rec, dict) and rec.get("config_hash") == config_hash and not rec.get("retryable"):
                done.add(rec.get("trial_id", p.stem))
        return done

    def recorded_codes(self, trial_ids: set[str] | list[str]) -> dict[str, Any]:
        """The code identity (``code`` entry, None if absent) of each readable record among ``trial_ids``."""
        out = {}
        for t in sorted(trial_ids):
            try:
                rec = read_json(self.trial_path(t))
            except (OSError, ValueError):
                continue
            if isinstance(rec, dict):
                out[t] = rec.get("code")
        return out

    def read_manifest(self) -> dict[str, Any] | None:
        """``run.json``, or None when absent or unreadable."""
        try:
            data = read_json(self.root / "run.json")
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def write_trial(self, record: dict[str, Any]) -> None:
        write_json_atomic(self.trial_path(record["trial_id"]), record)

    def read_trials(self, trial_ids: list[str] | None = None) -> list[dict[str, Any]]:
        paths = [self.trial_path(t) for t in trial_ids] if trial_ids is not None else \
            sorted(self.trials_dir.glob("*.json"))
        out = []
        for p in paths:
            if p.exists():
                out.append(read_json(p))
        return out
