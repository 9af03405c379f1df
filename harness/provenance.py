"""Provenance of a run: package version, git commit, code identity, Python and library versions, machine.

The *code identity* (DESIGN 11.4) says which code made a record: the checkout's commit, a SHA-256 of the
uncommitted changes to the project's packages (:data:`PACKAGES`: ``git diff HEAD`` of those directories plus
every untracked, not ignored file under them), and the versions of the plug-in packages whose methods the
suite runs (:func:`plugin_versions`; an empty mapping without plug-ins). Outside a git checkout (an installed
wheel, a copied tree) it is a SHA-256 of the packages' files instead. The runner computes it once per run, in
the parent process, and writes it into ``run.json`` and into every trial record; ``harness bench --resume``
refuses a run directory made by other code (:func:`harness.run.run_suite`).
"""

from __future__ import annotations

import hashlib
import os
import platform
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

LIBRARIES = ("numpy", "scipy", "mujoco", "trimesh", "open3d-cpu", "open3d", "pyyaml", "dask", "distributed")
#: the project's own packages, whose source the code identity covers
PACKAGES = ("scenes", "sensors", "recognition", "evaluation", "reports", "harness")
ROOT = Path(__file__).resolve().parent.parent
_GIT_TIMEOUT_S = 20


def package_version() -> str:
    try:
        return metadata.version("landmark-harness")
    except metadata.PackageNotFoundError:
        return "0+unknown"


def git_commit(root: Path | None = None) -> str | None:
    """The checkout's commit (with ``-dirty`` when it has uncommitted changes), or None outside git."""
    root = root or Path(__file__).resolve().parent.parent
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                                timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


@dataclass(frozen=True)
class CodeIdentity:
    """Which code made a run or a trial record (DESIGN 11.4).

    Attributes
    ----------
    commit : the checkout's ``HEAD`` commit (40 hex digits); None outside a git checkout.
    diff_sha256 : SHA-256 of the uncommitted changes to :data:`PACKAGES` (``git diff HEAD`` of those
        directories, then each untracked file's path and content); None when there are none, or outside git.
    source_sha256 : outside a git checkout, SHA-256 of every file of the packages (path and content, sorted by
        path, ``__pycache__`` left out); None in a checkout (the commit and the diff say it).
    plugins : ``(distribution, version)`` of each plug-in package the run's methods come from, sorted (empty
        without plug-ins; :func:`plugin_versions`).
    """

    commit: str | None
    diff_sha256: str | None = None
    source_sha256: str | None = None
    plugins: tuple[tuple[str, str], ...] = ()

    def as_json(self) -> dict[str, Any]:
        """The identity as written into ``run.json`` and trial records (key ``code``)."""
        return {"commit": self.commit, "diff_sha256": self.diff_sha256, "source_sha256": self.source_sha256,
                "plugins": dict(self.plugins)}

    @staticmethod
    def from_json(data: Any) -> CodeIdentity | None:
        """The identity of a ``code`` entry; None for a missing or malformed one (a record written before
        code identities existed)."""
        if not isinstance(data, Mapping) or not any(data.get(k) for k in ("commit", "source_sha256")):
            return None
        plugins = data.get("plugins") or {}
        if not isinstance(plugins, Mapping):
            return None
        return CodeIdentity(_str_or_none(data.get("commit")), _str_or_none(data.get("diff_sha256")),
                            _str_or_none(data.get("source_sha256")),
                            tuple(sorted((str(k), str(v)) for k, v in plugins.items())))

    def describe(self) -> str:
        """One line for messages and reports: ``commit f4785bc1e0a2 + uncommitted diff 3c9a0b71d2e4``,
        ``commit f4785bc1e0a2 (clean)`` or ``source 7d1e93aa0c55 (no git checkout)``, plus any plug-ins."""
        return describe_code(self.as_json())


def describe_code(code: Any) -> str:
    """:meth:`CodeIdentity.describe` of a ``code`` entry as found in a JSON file (``unrecorded`` if absent)."""
    if not isinstance(code, Mapping) or not any(code.get(k) for k in ("commit", "source_sha256")):
        return "unrecorded: written before code identities"
    if code.get("commit"):
        text = f"commit {str(code['commit'])[:12]}" + (f" + uncommitted diff {str(code['diff_sha256'])[:12]}"
                                                       if code.get("diff_sha256") else " (clean)")
    else:
        text = f"source {str(code['source_sha256'])[:12]} (no git checkout)"
    plugins = code.get("plugins") or {}
    return text + (", plug-ins " + ", ".join(f"{k} {v}" for k, v in sorted(plugins.items())) if plugins else "")


def _str_or_none(x: Any) -> str | None:
    return None if x is None else str(x)


def _git(root: Path, *args: str) -> bytes | None:
    """``git -C root ARGS`` stdout, or None when git fails or is absent."""
    try:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, timeout=_GIT_TIMEOUT_S,
                              check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None


def plugin_versions(plugins: Iterable[tuple[str, str | None]] = ()) -> tuple[tuple[str, str], ...]:
    """``(distribution, version)`` of the plug-in packages that provide a suite's methods (DESIGN 11.5), sorted.

    Parameters
    ----------
    plugins : ``(module, distribution or None)`` of each plug-in method (:attr:`harness.suite.Suite.plugins`);
        without a distribution, the one that installed the module's top-level package, if any.

    The version is the distribution's; for an editable install, or a module imported from a directory on the
    path that no distribution installed (keyed by its top-level package), the SHA-256 of its package's files is
    added (``0.1.0 (editable, source 3c9a0b71d2e4)``, ``unpackaged (source ...)``), so that editing a plug-in
    changes the code identity as editing the project does.
    """
    out: dict[str, str] = {}
    installed: Mapping[str, list[str]] | None = None
    for module, dist in plugins:
        top = module.split(".")[0]
        if dist is None:
            installed = metadata.packages_distributions() if installed is None else installed
            dist = (installed.get(top) or [None])[0]
        version, editable = None, dist is None
        if dist is not None:
            try:
                version = metadata.version(dist)
                editable = _editable(metadata.distribution(dist))
            except metadata.PackageNotFoundError:
                editable = True
        if editable:
            source = _module_source_hash(top)
            version = f"{version or 'unpackaged'} ({'editable, ' if dist else ''}source {source[:12]})"
        out[dist or top] = version or "unknown"
    return tuple(sorted(out.items()))


def _editable(dist: metadata.Distribution) -> bool:
    """Whether ``dist`` is an editable install (PEP 610 ``direct_url.json``: ``dir_info.editable``)."""
    import json

    try:
        info = json.loads(dist.read_text("direct_url.json") or "{}")
    except ValueError:
        return False
    return isinstance(info, dict) and bool((info.get("dir_info") or {}).get("editable"))


def _module_source_hash(top: str) -> str:
    """SHA-256 of the files of the top-level package or module ``top`` (as :func:`source_hash`; "unknown" when
    it cannot be found)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec(top)
    except (ImportError, ValueError):
        spec = None
    if spec is None:
        return "unknown"
    if spec.submodule_search_locations:
        base = Path(next(iter(spec.submodule_search_locations)))
        return source_hash(base.parent, [base.name])
    if spec.origin and Path(spec.origin).is_file():
        h = hashlib.sha256()
        _hash_file(h, Path(spec.origin).name, Path(spec.origin))
        return h.hexdigest()
    return "unknown"


def code_identity(root: Path | None = None, packages: Sequence[str] = PACKAGES,
                  plugins: Sequence[tuple[str, str]] | None = None) -> CodeIdentity:
    """The identity of the code under ``root`` (default: the checkout or tree these packages were imported
    from), with the plug-ins' ``(distribution, version)`` pairs ``plugins`` (:func:`plugin_versions`; default
    none). See :class:`CodeIdentity`.

    A git checkout counts only if it tracks the packages (a virtual environment's ``site-packages`` inside some
    repository's ignored ``.venv`` is not a checkout of them); otherwise the packages' files are hashed.
    """
    root = Path(root or ROOT)
    dirs = [d for d in packages if (root / d).is_dir()]
    plugins = tuple(sorted(plugins)) if plugins is not None else plugin_versions()
    commit = _git(root, "rev-parse", "--verify", "-q", "HEAD")
    tracked = _git(root, "ls-files", "--", *dirs) if commit and dirs else None
    if not commit or not tracked:
        return CodeIdentity(None, None, source_hash(root, dirs), plugins)
    diff = _git(root, "diff", "HEAD", "--binary", "--no-color", "--no-ext-diff", "--no-textconv", "--", *dirs)
    untracked = _git(root, "ls-files", "-z", "--others", "--exclude-standard", "--", *dirs)
    if diff is None or untracked is None:
        return CodeIdentity(None, None, source_hash(root, dirs), plugins)
    names = sorted(n for n in untracked.decode("utf-8", "surrogateescape").split("\0") if n)
    if not diff and not names:
        return CodeIdentity(commit.decode().strip(), None, None, plugins)
    h = hashlib.sha256(diff)
    for name in names:  # ls-files names are relative to root
        _hash_file(h, name, root / name)
    return CodeIdentity(commit.decode().strip(), h.hexdigest(), None, plugins)


def source_hash(root: Path, dirs: Sequence[str]) -> str:
    """SHA-256 of every file under ``root/<dir>`` (its path relative to ``root`` and its bytes, in path order;
    ``__pycache__`` and ``*.pyc`` left out)."""
    h = hashlib.sha256()
    files = sorted(p for d in dirs for p in (root / d).rglob("*")
                   if p.is_file() and "__pycache__" not in p.parts and p.suffix != ".pyc")
    for p in files:
        _hash_file(h, p.relative_to(root).as_posix(), p)
    return h.hexdigest()


def _hash_file(h: Any, name: str, path: Path) -> None:
    h.update(name.encode("utf-8", "surrogateescape") + b"\0")
    try:
        h.update(path.read_bytes())
    except OSError as exc:  # vanished or unreadable meanwhile: its name and the reason still count
        h.update(f"<unreadable: {exc.strerror}>".encode())
    h.update(b"\0")


def provenance(code: CodeIdentity | None = None) -> dict[str, Any]:
    """Versions, commit, code identity (``code``, computed here unless given) and machine of this process."""
    libs = {}
    for name in LIBRARIES:
        try:
            libs[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return {
        "version": package_version(),
        "git_commit": git_commit(),
        "code": (code or code_identity()).as_json(),
        "python": sys.version.split()[0],
        "libraries": libs,
        "machine": {"platform": platform.platform(), "processor": platform.machine(), "cpus": os.cpu_count(),
                    "hostname": platform.node()},
        "command": " ".join(["harness", *sys.argv[1:]]) if sys.argv and sys.argv[0].endswith("harness") else
        " ".join(sys.argv),
    }
