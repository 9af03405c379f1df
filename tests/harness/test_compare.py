"""``harness compare`` as a verdict (evaluation.verdicts): the headline table first, a metric counted once, noise
told from a drop by paired per-trial deltas resampled by scene, other methods counted only when asked, a value
that became "no such patch" not a regression, and runs of different suites or trials refused.

The run directories are synthetic: trial records in the runner's format, several scenes (so that intervals
exist), summaries made by the runner's own :func:`harness.summary.summarise`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from evaluation.intervals import Clusters
from evaluation.verdicts import (
    HEADLINE_METRICS,
    Tolerances,
    decide,
    paired_interval,
)
from harness.cli import main
from harness.compare import compare, compare_dirs, load_run, pair_trials, regressions
from harness.summary import summarise

CLASSES_CYCLE = ("PLAN", "CYL", "SPH")
ACCURACY = next(m for m in HEADLINE_METRICS if m.key == "classification.accuracy")
ROTATION = next(m for m in HEADLINE_METRICS if m.key == "pose.rotation_error_deg.median")


# -- synthetic runs -----------------------------------------------------------------------------------------
def patches(right: int, total: int = 10, oth: bool = True) -> list[dict]:
    """``total`` patches of 300 pixels, the first ``right`` labelled correctly (wrong ones as CONE); with ``oth``
    one more patch, truth and label OTH (so OTH has a precision)."""
    out = []
    for i in range(total):
        truth = CLASSES_CYCLE[i % 3]
        label = truth if i < right else "CONE"
        probs = dict.fromkeys(("PLAN", "CYL", "SPH", "CONE", "OTH"), 0.025)
        probs[label] = 0.9
        out.append({"truth": truth, "label": label, "n_pixels": 300, "probabilities": probs})
    if oth:
        out.append({"truth": "OTH", "label": "OTH", "n_pixels": 300,
                    "probabilities": {"PLAN": 0.05, "CYL": 0.05, "SPH": 0.05, "CONE": 0.05, "OTH": 0.8}})
    return out


def method(right: int, rot: float = 0.2, oth: bool = True, pose: bool = True) -> dict:
    return {"segmentation": {"correct_detection_rate": 0.8, "over_rate": 0.05, "under_rate": 0.05,
                             "missed_rate": 0.1, "noise_rate": 0.02, "tolerance": 0.8, "n_truth": 5},
            "classification": {"patches": patches(right, oth=oth)},
            "pose": {"rotation_error_deg": rot, "translation_error_mm": 3.0, "success": True, "constrained": True}
            if pose else None,
            "change": {"features": [{"truth": "moved", "predicted": "moved"},
                                   {"truth": "missing", "predicted": "missing"},
                                   {"truth": "unchanged", "predicted": "unchanged"}],
                       "objects": [], "displacement_error_mm": [5.0]}}


def record(tid: str, scene: str, group: str, core: dict, paper: dict) -> dict:
    return {"schema": "harness.trial/1", "trial_id": tid, "status": "ok", "reason": "",
            "spec": {"trial_id": tid, "group": group, "scene": scene},
            "view": {"viewpoint_rejection_rate": 0.0, "valid_fraction": 0.9, "surfaces_seen": 6},
            "timing_s": {"sensor": 0.1, "total": 1.0}, "methods": {"core": core, "paper": paper}}


def trials(core_right: list[list[int]], paper_right: list[list[int]] | None = None, *, oth: bool = True,
           solo_rot: float | None = None, pose: bool = True) -> list[dict]:
    """Scenes s0..s5 (``core_right[k]``: the correct patches, out of 10, of each trial of scene k), s0-s2 in group
    a/x, s3-s5 in b/y; ``solo_rot``: one more group solo/z of one trial (one scene) with that rotation error."""
    paper_right = paper_right or [[8] * len(t) for t in core_right]
    out = []
    for k, (cr, pr) in enumerate(zip(core_right, paper_right, strict=True)):
        group = "a/x" if k < 3 else "b/y"
        for v, (c, p) in enumerate(zip(cr, pr, strict=True)):
            out.append(record(f"s{k}-v{v}", f"s{k}", group, method(c, oth=oth, pose=pose),
                              method(p, oth=oth, pose=pose)))
    if solo_rot is not None:
        out.append(record("solo-v0", "solo", "solo/z", method(8, rot=solo_rot), method(8)))
    return out


def write_run(root: Path, records: list[dict], suite: str = "synthetic", seed: int = 1) -> Path:
    """A run directory as the runner writes it: run.json, trials/*.json and summary.json (summarise)."""
    (root / "trials").mkdir(parents=True)
    config = {"schema": "suite/1", "name": suite, "seed": seed, "methods": {"core": {}, "paper": {}},
              "groups": [{"scene": "synthetic", "viewpoints": 2}]}
    (root / "run.json").write_text(json.dumps({"schema": "harness.run/1", "suite": suite, "config_hash": f"h{seed}",
                                               "suite_config": config, "trials": [r["trial_id"] for r in records]}))
    for r in records:
        (root / "trials" / f"{r['trial_id']}.json").write_text(json.dumps(r))
    summary = summarise(records, suite=suite, config_hash=f"h{seed}", version="0", methods=["core", "paper"])
    (root / "summary.json").write_text(json.dumps(summary))
    return root


BASE = [[8, 8]] * 6  # 16 of 20 patches right in every scene: accuracy (with the OTH patches) 17/22


@pytest.fixture()
def base_run(tmp_path: Path) -> Path:
    return write_run(tmp_path / "base", trials(BASE))


def run_compare(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(["compare", *map(str, argv)])
    out = capsys.readouterr()
    return code, out.out, out.err


def row_of(out: str, method: str, label: str, scope: str = "all") -> list[str]:
    """The non-empty cells of one headline row of the text output."""
    for line in out.splitlines():
        cells = [c.strip() for c in line.split("  ") if c.strip()]
        if len(cells) >= 4 and cells[:3] == [method, label, scope]:
            return cells
    raise AssertionError(f"no row {method} / {label} / {scope} in:\n{out}")


def verdict_of(out: str, method: str, label: str, scope: str = "all") -> str:
    """The verdict word of one headline row of the text output."""
    return row_of(out, method, label, scope)[-1]


# -- the tests ----------------------------------------------------------------------------------------------
def test_output_starts_with_the_headline_table(base_run, tmp_path, capsys):
    cand = write_run(tmp_path / "cand", trials(BASE))
    code, out, _ = run_compare(capsys, base_run, cand)
    assert code == 0
    lines = out.splitlines()
    assert lines[0].startswith("Headline metrics: ") and "6 scene(s), 12 trial(s) paired by trial id" in lines[0]
    assert lines[1].split() == ["method", "metric", "scope", "base", "candidate", "delta", "95", "%", "interval", "of",
                                "delta", "verdict"]
    body = lines[2:2 + 8 * 3 + 1]  # 8 headline metrics x (all, a/x, b/y), then failed trials
    assert [line.split()[0] for line in body] == ["core"] * 25
    assert {verdict_of(out, "core", m.display, s)
            for m in HEADLINE_METRICS for s in ("all", "a/x", "b/y")} == {"pass"}
    assert "What changed most" in out and "no trial's figures moved" in out
    assert out.rstrip().splitlines()[-1] == "PASS: no regression in 9 headline metric(s) of core"
    assert "classification.per_class" not in out  # every leaf only with --all
    assert "- code: base unrecorded: written before code identities; candidate unrecorded" in out
    assert "time per trial" not in out and verdict_of(run_compare(capsys, base_run, cand, "--check-time")[1], "core",
                                                      "time per trial, median s") == "pass"
    code, out, _ = run_compare(capsys, base_run, cand, "--all")
    assert code == 0 and "classification.per_class.CYL.recall" in out
    code, md, _ = run_compare(capsys, base_run, cand, "--format", "md")
    assert code == 0 and md.startswith("**Headline metrics: ") and "| method | metric | scope |" in md


def test_noise_level_change_passes_as_within_noise(base_run, tmp_path, capsys):
    # scenes move both ways (-6, +2, -3, +1, +2, 0 patches of 20): pooled -4/132 = -0.030, beyond the 0.02
    # tolerance, but the paired scene deltas straddle zero
    noisy = [[5, 5], [9, 9], [6, 7], [8, 9], [9, 9], [8, 8]]
    cand = write_run(tmp_path / "cand", trials(noisy))
    code, out, _ = run_compare(capsys, base_run, cand)
    assert code == 0, out
    assert verdict_of(out, "core", "classification accuracy") == "within noise"
    assert row_of(out, "core", "classification accuracy")[3:6] == ["0.818", "0.788", "-0.030"]
    assert "within noise: core classification accuracy (all" in out.splitlines()[-1]
    # the interval is the paired one, and reaches zero
    comp = compare_dirs(load_run(base_run), load_run(cand))
    fig = next(f for f in comp.figures if f.metric == ACCURACY and f.scope == "all" and f.method == "core")
    assert fig.interval[0] < 0 < fig.interval[1] and fig.delta == pytest.approx(-4 / 132)


def test_clear_drop_fails_and_counts_once(base_run, tmp_path, capsys):
    dropped = [[6, 7]] * 6  # every scene loses 3 patches of 20
    cand = write_run(tmp_path / "cand", trials(dropped))
    code, out, _ = run_compare(capsys, base_run, cand)
    assert code == 1
    for scope in ("all", "a/x", "b/y"):
        assert verdict_of(out, "core", "classification accuracy", scope) == "REGRESSION"
    last = out.rstrip().splitlines()[-1]
    # pooled and both groups fail: each metric once, naming its scopes (the wrong labels, confident, also
    # worsen the Brier score: a metric of its own)
    assert last == ("FAIL: 2 regression(s) in 9 headline metric(s) of core: core classification accuracy "
                    "(regression: all, a/x, b/y); core classification Brier score (regression: all, a/x, b/y)"), last
    comp = compare_dirs(load_run(base_run), load_run(cand))
    fig = next(f for f in comp.figures if f.metric == ACCURACY and f.scope == "all" and f.method == "core")
    assert fig.interval[1] < 0 and len(comp.regressions) == 2
    # what changed most: the trials, by id, with their own figures
    assert comp.moves and comp.moves[0].trial_id == "s0-v0"
    assert "s0-v0" in out and "classification accuracy 0.818 -> 0.636" in out


def test_a_one_trial_metric_counts_once(tmp_path, capsys):
    base = write_run(tmp_path / "base", trials(BASE, solo_rot=0.2))
    cand = write_run(tmp_path / "cand", trials(BASE, solo_rot=5.0))
    # leaf by leaf, the one trial of solo/z moves its median, p90, max and mean (and the pooled p90, max, mean)
    leaves = regressions(compare(load_run(base).summary, load_run(cand).summary))
    assert len(leaves) >= 4
    code, out, _ = run_compare(capsys, base, cand)
    assert code == 1
    assert verdict_of(out, "core", "rotation error, median deg", "solo/z") == "REGRESSION (tolerance alone)"
    assert verdict_of(out, "core", "rotation error, median deg", "all") == "pass"  # the pooled median: 0.2
    assert out.rstrip().splitlines()[-1] == ("FAIL: 1 regression(s) in 9 headline metric(s) of core: "
                                             "core rotation error, median (regression: solo/z)")


def test_a_drop_of_the_paper_baseline_alone_fails_only_when_asked(base_run, tmp_path, capsys):
    cand = write_run(tmp_path / "cand", trials(BASE, paper_right=[[5, 6]] * 6))
    code, out, _ = run_compare(capsys, base_run, cand)
    assert code == 0, out
    assert verdict_of(out, "paper", "classification accuracy") == "regression"  # shown, lower case: not counted
    assert "not counted: paper classification accuracy (regression: all, a/x, b/y)" in out
    assert out.rstrip().splitlines()[-1] == "PASS: no regression in 9 headline metric(s) of core"
    assert "--methods paper" in out
    for methods in ("paper", "all", "core,paper"):
        code, out, _ = run_compare(capsys, base_run, cand, "--methods", methods)
        assert code == 1, methods
        assert verdict_of(out, "paper", "classification accuracy") == "REGRESSION"
        assert out.rstrip().splitlines()[-1] == (
            "FAIL: 2 regression(s) in 17 headline metric(s) of core, paper: paper classification accuracy "
            "(regression: all, a/x, b/y); paper classification Brier score (regression: all, a/x, b/y)")
    code, _, err = run_compare(capsys, base_run, cand, "--methods", "nope")
    assert code == 2 and "--methods: no method 'nope' in either run (methods: core, paper)" in err


def test_a_value_that_became_no_such_patch_is_not_a_regression(base_run, tmp_path, capsys):
    cand = write_run(tmp_path / "cand", trials(BASE, oth=False))  # no OTH patch any more: its precision is null
    summary = load_run(cand).summary
    assert summary["classification"]["per_class"]["OTH"]["precision"] is None
    rows = {r.metric: r for r in compare(load_run(base_run).summary, summary)}
    assert rows["classification.per_class.OTH.precision"].verdict == "undefined"
    code, out, _ = run_compare(capsys, base_run, cand, "--all")
    assert code == 0, out
    leaf = next(line for line in out.splitlines() if line.startswith("classification.per_class.OTH.precision "))
    assert leaf.split()[1:3] == ["1", "null"] and leaf.split()[-1] == "undefined"
    # a headline figure undefined within a section that is there is "not scored"; a lost section is "missing"
    assert decide(ACCURACY, 0.8, None, None, Tolerances())[0] == "not scored"
    assert decide(ACCURACY, 0.8, None, None, Tolerances(), lost=True)[0] == "missing"


def test_a_lost_stage_is_missing_and_fails(base_run, tmp_path, capsys):
    cand = write_run(tmp_path / "cand", trials(BASE, pose=False))
    assert load_run(cand).summary["pose"] is None
    code, out, _ = run_compare(capsys, base_run, cand)
    assert code == 1
    assert verdict_of(out, "core", "pose success") == "MISSING"
    assert "core pose success (missing: all, a/x, b/y)" in out.splitlines()[-1]


def test_runs_of_different_suites_seeds_or_trials_exit_2_unless_forced(base_run, tmp_path, capsys):
    other_suite = write_run(tmp_path / "suite", trials(BASE), suite="other")
    code, out, err = run_compare(capsys, base_run, other_suite)
    assert code == 2 and out == ""
    assert err.strip() == ("harness: error: the runs differ: suite 'synthetic' vs 'other' (compare runs of one "
                           "suite, seeds and trials, or pass --force)")
    code, out, _ = run_compare(capsys, base_run, other_suite, "--force")
    assert code == 0 and out.startswith("Headline metrics")
    assert "compared with --force although the runs differ: suite 'synthetic' vs 'other'" in out
    other_seed = write_run(tmp_path / "seed", trials(BASE), seed=2)
    code, _, err = run_compare(capsys, base_run, other_seed)
    assert code == 2 and "suite seed 1 vs 2" in err
    fewer = write_run(tmp_path / "fewer", trials(BASE)[:-1])
    code, _, err = run_compare(capsys, base_run, fewer)
    assert code == 2 and "trial ids: 1 only in base (e.g. s5-v1)" in err
    assert run_compare(capsys, base_run, fewer, "--force")[0] == 0


def test_unreadable_input_exits_2(base_run, tmp_path, capsys):
    assert run_compare(capsys, base_run, tmp_path / "nowhere")[0] == 2
    broken = write_run(tmp_path / "broken", trials(BASE))
    (broken / "trials" / "s0-v0.json").write_text("{")
    code, _, err = run_compare(capsys, base_run, broken)
    assert code == 2 and "s0-v0.json: unreadable trial record" in err


def test_paired_delta_matches_the_summaries_and_resamples_scenes(tmp_path):
    b = load_run(write_run(tmp_path / "base", trials(BASE, solo_rot=0.2)))
    c = load_run(write_run(tmp_path / "cand", trials([[5, 5], [9, 9], [6, 7], [8, 9], [9, 9], [8, 8]], solo_rot=0.4)))
    pairs = pair_trials(b.records, c.records)
    clusters = Clusters.of([p.scene for p in pairs])
    assert clusters.names == ("s0", "s1", "s2", "s3", "s4", "s5", "solo")
    for metric in HEADLINE_METRICS:
        delta, ci = paired_interval(metric, "core", pairs, clusters)
        path = metric.path
        sb, sc = b.summary, c.summary
        for key in path:
            sb, sc = sb[key], sc[key]
        assert delta == pytest.approx(sc - sb, abs=1e-12), metric.key
        assert ci is not None and ci[0] <= ci[1], metric.key
    # the accuracy's interval: the percentile interval of the pooled delta on each resample of scenes
    delta, ci = paired_interval(ACCURACY, "core", pairs, clusters)
    right_b = np.array([16, 16, 16, 16, 16, 16, 8]) + np.array([2, 2, 2, 2, 2, 2, 1])
    right_c = np.array([10, 18, 13, 17, 18, 16, 8]) + np.array([2, 2, 2, 2, 2, 2, 1])
    n = np.array([22, 22, 22, 22, 22, 22, 11])
    w = clusters.weights
    want = np.percentile((w @ right_c) / (w @ n) - (w @ right_b) / (w @ n), [2.5, 97.5])
    assert ci == pytest.approx(tuple(want), abs=1e-12)
    # rotation median of the solo scene moved 0.2 -> 0.4: pooled median unchanged (0.2)
    assert paired_interval(ROTATION, "core", pairs, clusters)[0] == 0.0
