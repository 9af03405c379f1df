"""Benchmark of the H-K segmentation alone: time per frame and Hoover correct detection on a suite's scans.

``python -m harness.bench.segmentation [--suite default] [--repeat 3] [--groups mockup,...] [--limit N]
[--steps] [--json OUT]`` simulates each trial's scan as ``harness bench`` does, then segments it ``--repeat``
times in this one process, with the numerical libraries on one thread as in the runner's workers. Per group and
overall it prints the median and p90 over frames of the best-of-repeats time per frame: process time (the
machine may be shared) and wall time. Beside them: the correct detection rate at T = 0.8 over truth regions of
200 pixels or more, averaged over frames, of the segmenter's own labels (``seg.``) and of the description's
(``desc.``: after the classifier has merged touching patches that one primitive explains, untimed; the figure
``summary.json`` reports), and a SHA-1 of the segmenter's label images, so that a change made for speed can show
it left every label alone. ``--steps`` adds where the time goes: the process time of each step of
:func:`recognition.segmentation.segment` in the fastest repeat, per frame median and mean over frames.
``--json`` also writes all of it, per frame and per group.

``--against REV`` segments the same frames with the segmenter of another commit in the same run: REV is checked
out in a temporary git worktree (removed afterwards), and two worker processes, one running this tree's
segmenter and one REV's (``PYTHONPATH`` set to each tree alone; a worker refuses to run when a module of the
project resolves to another tree, as a package missing from an old commit would to the editable install), are
given each frame (points and sigma, in a temporary ``.npz``) in turn, ``--repeat`` times each, alternating which
goes first, after one untimed warm-up segmentation each. Per frame it prints both times (best of the repeats,
process time) and their ratio (this tree / REV), and at the end the median per group of both, the ratio of the
medians and each side's label hash; a shim finds the segmenter in either layout (``recognition.segmentation``,
a module at 0b5908a, a package today).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

#: the project's top-level packages: in an ``--against`` worker every one of them must come from its own tree
PROJECT_PACKAGES = ("scenes", "sensors", "recognition", "evaluation", "reports", "harness")
#: where the segmenter lives, layout by layout (module, function): ``segment(points, sigma) -> .labels``
SEGMENTER_LOCATIONS = (("recognition.segmentation", "segment"),)


def _mean(values: list[float | None]) -> float | None:
    rates = [x for x in values if x is not None]
    return float(np.mean(rates)) if rates else None


def _stats(cpu: list[float], wall: list[float], cd: list[float | None], cd_desc: list[float | None]) -> dict:
    return {"n": len(cpu), "cpu_median_s": float(np.median(cpu)), "cpu_p90_s": float(np.percentile(cpu, 90)),
            "wall_median_s": float(np.median(wall)), "wall_p90_s": float(np.percentile(wall, 90)),
            "correct_detection_rate": _mean(cd), "correct_detection_rate_described": _mean(cd_desc)}


def _rate(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.3f}"


def _row(name: str, st: dict) -> str:
    return (f"{name:32s} {st['n']:4d}  {st['cpu_median_s']:.3f}  {st['cpu_p90_s']:.3f}  {st['wall_median_s']:.3f}  "
            f"{st['wall_p90_s']:.3f}  {_rate(st['correct_detection_rate'])}  "
            f"{_rate(st['correct_detection_rate_described'])}")


def _print_steps(frames: list[dict]) -> None:
    """Per step of the segmenter (in the order it runs): median and mean process time over frames, in ms,
    and its share of the total."""
    names = list(dict.fromkeys(name for f in frames for name in f["steps_s"]))
    times = np.array([[f["steps_s"].get(name, 0.0) for name in names] for f in frames]) * 1e3
    total = times.sum()
    print("\nsegmenter steps, process time per frame (ms)")
    print(f"{'step':32s} {'median':>7s} {'mean':>7s} {'share':>6s}")
    for name, col in zip(names, times.T, strict=True):
        print(f"{name:32s} {np.median(col):7.1f} {col.mean():7.1f} {col.sum() / total:6.1%}")
    print(f"{'total':32s} {np.median(times.sum(axis=1)):7.1f} {times.sum(axis=1).mean():7.1f}")


def _labels_sha1(labels: np.ndarray) -> bytes:
    """The bytes a label hash is made of: the (H, W) labels as C-ordered int32, whatever the commit returns."""
    return np.ascontiguousarray(labels, dtype=np.int32).tobytes()


def _module_paths(module) -> list[str]:
    file = getattr(module, "__file__", None)
    paths = [file] if file else list(getattr(module, "__path__", None) or [])
    return [os.path.realpath(p) for p in paths]


def _foreign_modules(root: str) -> list[str]:
    """The project's modules loaded in this process from outside ``root`` (with where they came from)."""
    out = []
    for name, module in list(sys.modules.items()):
        if name.split(".")[0] not in PROJECT_PACKAGES or module is None:
            continue
        paths = _module_paths(module)
        if not paths or any(os.path.commonpath([p, root]) != root for p in paths):
            out.append(f"{name} ({', '.join(paths) or 'no file'})")
    return sorted(out)


def _worker(root: str) -> int:
    """An ``--against`` worker: segment the frames named on stdin with the segmenter of the tree at ``root``.

    Run as ``python -P harness/bench/segmentation.py --worker ROOT`` with ``PYTHONPATH=ROOT`` (``-P``: this
    file's folder is not put on the path). One JSON line per request on stdin: ``{"frame": npz}`` (arrays
    ``points``, ``sigma``) segments once and answers ``{"cpu_s", "wall_s", "labels_sha1"}``, adding the labels to
    the running hash when ``"digest": true``; ``{"close": true}`` answers ``{"labels_sha1"}`` of them all. The
    first line says ``{"ready": ...}`` or ``{"error": ...}``; every answer is an error once a project module has
    been loaded from outside ``ROOT``. What the segmenter prints goes to stderr.
    """
    import importlib
    import inspect

    reply = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)

    def say(obj: dict) -> None:
        reply.write(json.dumps(obj) + "\n")

    root = os.path.realpath(root)
    segment, tried = None, []
    for module_name, attr in SEGMENTER_LOCATIONS:
        try:
            segment = getattr(importlib.import_module(module_name), attr)
            break
        except (ImportError, AttributeError) as e:
            tried.append(f"{module_name}.{attr}: {type(e).__name__}: {e}")
    if segment is None:
        say({"error": f"no segmenter in {root} ({'; '.join(tried)})"})
        return 2
    foreign = _foreign_modules(root)
    if foreign:
        say({"error": f"modules from outside {root}: {', '.join(foreign)}"})
        return 2
    from threadpoolctl import threadpool_limits

    say({"ready": True, "segmenter": f"{module_name}.{attr}", "defined_in": segment.__module__,
         "file": os.path.realpath(inspect.getfile(segment))})
    digest = hashlib.sha1()
    with threadpool_limits(limits=1):
        for line in sys.stdin:
            request = json.loads(line)
            if request.get("close"):
                say({"labels_sha1": digest.hexdigest()})
                return 0
            with np.load(request["frame"]) as frame:
                points, sigma = frame["points"], frame["sigma"]
            t0, c0 = time.perf_counter(), time.process_time()
            labels = segment(points, sigma).labels
            cpu, wall = time.process_time() - c0, time.perf_counter() - t0
            foreign = _foreign_modules(root)
            if foreign:
                say({"error": f"modules from outside {root}: {', '.join(foreign)}"})
                return 2
            data = _labels_sha1(labels)
            if request.get("digest"):
                digest.update(data)
            say({"cpu_s": cpu, "wall_s": wall, "labels_sha1": hashlib.sha1(data).hexdigest()})
    return 0


class WorkerError(RuntimeError):
    """An ``--against`` worker could not segment: no segmenter, modules from another tree, or it ended."""


class _Worker:
    """One ``--against`` worker process (see :func:`_worker`) running the segmenter of the tree at ``root``;
    it starts at once and imports while the caller goes on (:attr:`ready` waits for it)."""

    def __init__(self, root: Path, name: str) -> None:
        self.name = name
        env = {**os.environ, "PYTHONPATH": str(root)}
        self.proc = subprocess.Popen([sys.executable, "-P", str(Path(__file__).resolve()), "--worker", str(root)],
                                     cwd=root, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                                     bufsize=1)
        self._ready: dict | None = None

    @property
    def ready(self) -> dict:
        """The worker's first answer: which segmenter it found, and in which file."""
        if self._ready is None:
            self._ready = self._answer()
        return self._ready

    def _answer(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise WorkerError(f"the {self.name} worker ended (exit {self.proc.wait()}); its stderr says why")
        answer = json.loads(line)
        if "error" in answer:
            raise WorkerError(f"the {self.name} worker: {answer['error']}")
        return answer

    def ask(self, request: dict) -> dict:
        _ = self.ready
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        return self._answer()

    def close(self) -> str | None:
        """The worker's label hash over the frames it was asked to digest (None when it had ended)."""
        try:
            return self.ask({"close": True})["labels_sha1"] if self.proc.poll() is None else None
        except WorkerError:
            return None
        finally:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), *args], check=True, capture_output=True,
                          text=True).stdout.strip()


@contextlib.contextmanager
def _worktree(rev: str) -> Iterator[tuple[Path, Path, str]]:
    """This tree's root, a temporary detached git worktree of ``rev`` and rev's commit; the worktree is removed
    on the way out."""
    here = Path(__file__).resolve().parents[2]  # the tree whose harness runs (harness/bench/segmentation.py)
    try:
        commit = _git(here, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}")
    except subprocess.CalledProcessError:
        raise SystemExit(f"--against: {rev!r} is not a commit of {here}") from None
    tmp = Path(tempfile.mkdtemp(prefix="bench-against-"))
    tree = tmp / commit[:12]
    try:
        _git(here, "worktree", "add", "--detach", "--quiet", str(tree), commit)
        yield here, tree, commit
    finally:
        with contextlib.suppress(subprocess.CalledProcessError):
            _git(here, "worktree", "remove", "--force", str(tree))
        shutil.rmtree(tmp, ignore_errors=True)
        with contextlib.suppress(subprocess.CalledProcessError):
            _git(here, "worktree", "prune")


class _Against:
    """Both sides of ``--against``: this tree's segmenter and REV's, each in its own worker, on the same frames."""

    def __init__(self, here: Path, tree: Path, rev: str, commit: str, repeat: int, tmp: Path) -> None:
        self.rev, self.commit, self.repeat, self.tmp = rev, commit, repeat, tmp
        self.sides = (_Worker(here, "this tree's"), _Worker(tree, f"{rev}'s"))
        self.warm = False
        self.frames: list[dict] = []

    def frame(self, trial_id: str, group: str, points: np.ndarray, sigma: np.ndarray) -> dict:
        path = self.tmp / "frame.npz"
        np.savez(path, points=points, sigma=sigma)
        if not self.warm:  # first calls (imports, caches, any compilation) stay out of the times
            for side in self.sides:
                side.ask({"frame": str(path)})
            self.warm = True
        cpu = [float("inf")] * 2
        wall = [float("inf")] * 2
        sha = [None, None]
        for r in range(self.repeat):
            for k in ((0, 1) if r % 2 == 0 else (1, 0)):  # alternate which side goes first
                answer = self.sides[k].ask({"frame": str(path), "digest": r == 0})
                cpu[k], wall[k] = min(cpu[k], answer["cpu_s"]), min(wall[k], answer["wall_s"])
                sha[k] = sha[k] or answer["labels_sha1"]
        path.unlink()
        row = {"trial_id": trial_id, "group": group, "cpu_s": cpu[0], "cpu_s_against": cpu[1],
               "wall_s": wall[0], "wall_s_against": wall[1], "ratio": cpu[0] / cpu[1] if cpu[1] > 0 else None,
               "labels_sha1": sha[0], "labels_sha1_against": sha[1]}
        self.frames.append(row)
        return row

    def close(self) -> dict:
        hashes = [side.close() for side in self.sides]
        groups = {}
        for key in sorted({f["group"] for f in self.frames}) + ["all"]:
            rows = [f for f in self.frames if key in ("all", f["group"])]
            if not rows:
                continue
            this, other = (float(np.median([f[k] for f in rows])) for k in ("cpu_s", "cpu_s_against"))
            groups[key] = {"n": len(rows), "cpu_median_s": this, "cpu_median_s_against": other,
                           "ratio_of_medians": this / other if other > 0 else None,
                           "wall_median_s": float(np.median([f["wall_s"] for f in rows])),
                           "wall_median_s_against": float(np.median([f["wall_s_against"] for f in rows])),
                           "identical_labels": sum(f["labels_sha1"] == f["labels_sha1_against"] for f in rows)}
        return {"rev": self.rev, "commit": self.commit, "repeat": self.repeat,
                "segmenter": self.sides[0].ready, "segmenter_against": self.sides[1].ready,
                "labels_sha1": hashes[0], "labels_sha1_against": hashes[1], "groups": groups, "frames": self.frames}

    def abort(self) -> None:
        for side in self.sides:
            if side.proc.poll() is None:
                side.proc.kill()
                side.proc.wait()


def _print_against(result: dict) -> None:
    rev = f"{result['rev']} ({result['commit'][:12]})"
    print(f"\n--against {rev}: the same frames, best of {result['repeat']} per frame, process time (s), in two "
          "workers taking turns; ratio = this tree / REV")
    print(f"{'group':32s} {'n':>4s}  {'this':>6s}  {'REV':>6s}  {'ratio':>5s}  {'wall':>6s}  {'REV':>6s}  same labels")
    for key, g in result["groups"].items():
        ratio = "n/a" if g["ratio_of_medians"] is None else f"{g['ratio_of_medians']:.2f}"
        print(f"{key:32s} {g['n']:4d}  {g['cpu_median_s']:6.3f}  {g['cpu_median_s_against']:6.3f}  {ratio:>5s}  "
              f"{g['wall_median_s']:6.3f}  {g['wall_median_s_against']:6.3f}  {g['identical_labels']}/{g['n']}")
    print(f"labels sha1 this tree {result['labels_sha1']}, {result['rev']} {result['labels_sha1_against']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--suite", default="default", help="a shipped suite's name or a suite YAML file")
    ap.add_argument("--repeat", type=int, default=3, help="segmentations per frame; the fastest one counts")
    ap.add_argument("--groups", default=None, help="comma-separated group names (default: all)")
    ap.add_argument("--limit", type=int, default=None, help="at most this many trials")
    ap.add_argument("--steps", action="store_true", help="also print the time of each step of the segmenter")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    ap.add_argument("--against", metavar="REV", default=None,
                    help="also segment the same frames with commit REV's segmenter (a temporary git worktree), "
                         "both in worker processes taking turns, and print both times, their ratio and label hashes")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")
    with contextlib.ExitStack() as stack:
        against = None
        if args.against is not None:
            here, tree, commit = stack.enter_context(_worktree(args.against))
            tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-frames-")))
            against = _Against(here, tree, args.against, commit, args.repeat, tmp)
            stack.callback(against.abort)
        try:
            return _run(args, ap, against)
        except WorkerError as e:
            print(f"--against {args.against}: {e}", file=sys.stderr)
            return 2


def _run(args: argparse.Namespace, ap: argparse.ArgumentParser, against: _Against | None) -> int:
    from threadpoolctl import threadpool_limits

    from evaluation.patches import segmentation_section
    from harness.suite import load_suite
    from harness.trial import method_params, prepare_scene, sensor_for, trial_scan, trial_viewpoints
    from recognition.describe import core_sigma, describe
    from recognition.segmentation import kernels, segment

    kernels.warm_up()  # the compiled kernels' first calls stay out of the times
    suite = load_suite(args.suite)
    trials = [t for t in suite.trials if args.groups is None or t.group in args.groups.split(",")]
    if args.groups is not None and not trials:
        ap.error(f"no trial in groups {args.groups!r}; the suite's groups: "
                 f"{', '.join(sorted({t.group for t in suite.trials}))}")
    trials = trials[:args.limit]
    core = method_params("core", suite.plan.methods.get("core", {}))
    rows: dict[str, tuple[list, list, list, list]] = {}
    frames: list[dict] = []
    digest = hashlib.sha1()
    with threadpool_limits(limits=1):
        for spec in trials:
            prepared = prepare_scene(spec, None)
            config = sensor_for(spec)
            views = trial_viewpoints(spec, prepared, config)
            if not views.viewpoints:
                print(f"{spec.trial_id}: no viewpoint, skipped", flush=True)
                continue
            scan, truth = trial_scan(spec, prepared, config, views.viewpoints[0].T_world_sensor)
            sigma = core_sigma(scan)
            cpu = wall = float("inf")
            steps: dict[str, float] = {}
            for _ in range(args.repeat):
                laps: dict[str, float] | None = {} if args.steps else None
                t0, c0 = time.perf_counter(), time.process_time()
                seg = segment(scan.points, sigma, steps=laps)
                c = time.process_time() - c0
                wall = min(wall, time.perf_counter() - t0)
                if c < cpu:
                    cpu, steps = c, laps or {}
            digest.update(seg.labels.tobytes())
            cd = segmentation_section(seg.labels, truth, scan.valid)["correct_detection_rate"]
            described = describe(scan, core, seg)
            cd_desc = segmentation_section(described.labels, truth, scan.valid)["correct_detection_rate"]
            for key in (spec.group, "all"):
                acc = rows.setdefault(key, ([], [], [], []))
                for a, v in zip(acc, (cpu, wall, cd, cd_desc), strict=True):
                    a.append(v)
            h, w = scan.valid.shape
            frames.append({"trial_id": spec.trial_id, "group": spec.group, "width": w, "height": h, "cpu_s": cpu,
                           "labels_sha1": hashlib.sha1(seg.labels.tobytes()).hexdigest(),
                           "wall_s": wall, "correct_detection_rate": cd, "correct_detection_rate_described": cd_desc,
                           **({"steps_s": steps} if args.steps else {})})
            print(f"{spec.trial_id}: {w}x{h} process {cpu:.3f} s, wall {wall:.3f} s, correct detection "
                  f"{_rate(cd)} (described {_rate(cd_desc)})", flush=True)
            if against is not None:
                row = against.frame(spec.trial_id, spec.group, scan.points, sigma)
                same = "same labels" if row["labels_sha1"] == row["labels_sha1_against"] else "labels differ"
                ratio = "n/a" if row["ratio"] is None else f"{row['ratio']:.2f}"
                print(f"  against {args.against}: this tree {row['cpu_s']:.3f} s, {args.against} "
                      f"{row['cpu_s_against']:.3f} s, ratio {ratio}, {same}", flush=True)
    if not rows:
        print("no frame segmented")
        return 1
    print(f"\nsegmentation per frame, best of {args.repeat} (s); correct detection at T = 0.8, mean over frames, "
          "of the segmenter's labels and of the description's (as summary.json)")
    print(f"{'group':32s} {'n':>4s}  {'cpu50':>5s}  {'cpu90':>5s}  {'wal50':>5s}  {'wal90':>5s}  seg.   desc.")
    groups = {key: _stats(*rows[key]) for key in sorted(rows, key=lambda k: (k == "all", k))}
    for key, st in groups.items():
        print(_row(key, st))
    print(f"labels sha1 {digest.hexdigest()}")
    if args.steps:
        _print_steps(frames)
    result = None
    if against is not None:
        result = against.close()
        _print_against(result)
    if args.json is not None:
        from harness.store import write_json_atomic

        write_json_atomic(args.json, {"suite": args.suite, "repeat": args.repeat, "frames": frames,
                                      "groups": groups, "labels_sha1": digest.hexdigest(),
                                      **({"against": result} if result is not None else {})})
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"] and len(sys.argv) == 3:
        raise SystemExit(_worker(sys.argv[2]))
    raise SystemExit(main())
