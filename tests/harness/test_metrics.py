"""One declaration of each metric (evaluation.metrics): it drives ``harness compare`` and the report, directions
come from it and never from a key's name, every numeric leaf of a summary is declared (or informative), and a
tolerances file names only declared metrics."""

from __future__ import annotations

import json
import re
from pathlib import Path

import _support
import pytest
from test_compare import BASE, row_of, run_compare, trials, write_run

from evaluation import metrics
from evaluation.metrics import Informative, Metric
from evaluation.verdicts import DEFAULT_TOLERANCES, Tolerances
from harness.compare import TOLERANCES_DIR, compare, direction, load_run
from harness.summary import summarise
from reports.render import render_report
from scenes.config import ConfigError

ROOT = _support.ROOT
ZORBLAX = Metric("classification.zorblax", "zorblax score", "higher", "rate", headline=True)


def _add_leaf(run: Path, value: float) -> None:
    """Put ``classification.zorblax`` (a made-up figure) into a run's summary, pooled and per group."""
    summary = json.loads((run / "summary.json").read_text())
    for scope in (summary, *summary["groups"].values()):
        scope["classification"]["zorblax"] = value
    (run / "summary.json").write_text(json.dumps(summary))


def _numbered(records: list[dict]) -> list[dict]:
    """The records with patch ids (the report's tables of patches want them)."""
    for r in records:
        for sec in r["methods"].values():
            for i, p in enumerate(sec["classification"]["patches"]):
                p["patch"] = i
    return records


def test_a_metric_added_to_the_registry_appears_in_compare_and_the_report(tmp_path, capsys, monkeypatch):
    base, cand = (write_run(tmp_path / name, _numbered(trials(BASE))) for name in ("base", "cand"))
    _add_leaf(base, 0.5)
    _add_leaf(cand, 0.3)
    # undeclared: judged by nothing, but visible (a note, and "undeclared" under --all)
    code, out, _ = run_compare(capsys, base, cand, "--all")
    assert code == 0 and "zorblax score" not in out
    assert ("2 numeric leaf(s) of summary.json are declared by no metric of evaluation/metrics.py (listed as "
            "undeclared by --all, judged by nothing): classification.zorblax, groups.*.classification.zorblax") in out
    leaf = next(line for line in out.splitlines() if line.startswith("classification.zorblax "))
    assert leaf.split()[-1] == "undeclared"
    # declared (one line in the registry): a headline metric of compare and of the report
    monkeypatch.setattr(metrics, "METRICS", (*metrics.METRICS, ZORBLAX))
    code, out, _ = run_compare(capsys, base, cand)
    assert code == 1
    assert row_of(out, "core", "zorblax score")[3:] == ["0.500", "0.300", "-0.200", "REGRESSION (tolerance alone)"]
    assert row_of(out, "core", "zorblax score", "a/x")[-1] == "REGRESSION (tolerance alone)"
    assert "core zorblax score (regression: all, a/x, b/y)" in out.splitlines()[-1]
    assert "declared by no metric" not in out
    html = render_report(cand)[0].read_text()
    head = re.search(r'<table id="headline">.*?</table>', html, re.S).group(0)
    assert "zorblax score" in head and "0.300" in head
    from harness.compare import compare_dirs

    html = render_report(cand, base, comparison=compare_dirs(load_run(base), load_run(cand)))[0].read_text()
    section = html[html.index('id="regression"'):]
    assert "zorblax score" in section and "REGRESSION" in section


def _summary(**segmentation: float) -> dict:
    return {"schema": "harness.summary/1", "suite": "s", "n_trials": 1, "n_failed": 0,
            "segmentation": {"correct_detection_rate": 0.8, **segmentation}, "classification": None, "pose": None,
            "change": None, "baselines": {}, "groups": {}}


def test_direction_comes_from_the_declaration_not_the_key_name(monkeypatch):
    base, cand = _summary(wobble=0.1), _summary(wobble=0.5)
    cand["segmentation"]["missed_causes"] = {"accuracy": 0.9}  # named like a metric, declared informative
    base["segmentation"]["missed_causes"] = {"accuracy": 0.1}
    rows = {r.metric: r for r in compare(base, cand)}
    assert direction(("segmentation", "wobble")) == "" and rows["segmentation.wobble"].verdict == "undeclared"
    assert rows["segmentation.missed_causes.accuracy"].direction == ""
    assert rows["segmentation.missed_causes.accuracy"].verdict == ""
    assert direction(("groups", "a.b/c[x=0.5]", "baselines", "paper", "segmentation", "correct_detection_rate")) \
        == "higher"
    shipped = metrics.METRICS
    for better, verdict in (("lower", "regression"), ("higher", "improved")):
        wobble = Metric("segmentation.wobble", "wobble", better, "error")
        monkeypatch.setattr(metrics, "METRICS", (*shipped, wobble))
        rows = {r.metric: r for r in compare(base, cand)}
        assert rows["segmentation.wobble"].direction == better and rows["segmentation.wobble"].verdict == verdict
    with pytest.raises(ValueError, match="direction must be one of higher, lower"):
        Metric("segmentation.wobble", "wobble", "up", "rate")
    with pytest.raises(ValueError, match="rule must be one of"):
        Metric("segmentation.wobble", "wobble", "higher", "percent")


def _full_records() -> list[dict]:
    """The synthetic records of test_compare with every optional part a trial record may carry."""
    recs = trials([[8, 7], [6, 9]])
    for i, r in enumerate(recs):
        for sec in r["methods"].values():
            sec["segmentation"].update(
                missed_causes={"merged": 0.05, "unlabelled": 0.03, "split": 0.02},
                by_size=[{"min_pixels": 200, "max_pixels": 500, "n_truth": 2, "n_correct": 1, "n_over": 0,
                          "n_under": 0, "n_missed": 1},
                         {"min_pixels": 500, "max_pixels": None, "n_truth": 3, "n_correct": 3, "n_over": 0,
                          "n_under": 0, "n_missed": 0}],
                sweep=[{"tolerance": t, "correct_detection_rate": 0.8, "over_rate": 0.05, "under_rate": 0.05,
                        "missed_rate": 0.1, "noise_rate": 0.02} for t in (0.51, 0.8)],
                min_truth_pixels=200, n_machine=6)
            for p in sec["classification"]["patches"]:
                if p["truth"] == p["label"] and p["truth"] in ("CYL", "SPH"):
                    p["radius"] = {"estimate_m": 0.101, "truth_m": 0.1, "sigma_m": 0.002}
            sec["pose"].update(initial={"rotation_error_deg": 2.0, "translation_error_mm": 30.0, "success": False},
                               add_mm=4.0 + i)
            sec["change"]["objects"] = [{"truth": "moved", "predicted": "moved"},
                                        {"truth": "unchanged", "predicted": "missing"}]
        r["oracles"] = {"segmentation": r["methods"]["core"]}
        r["timing_s"].update(segmentation=0.2)
    return recs


def test_every_numeric_leaf_of_a_summary_is_declared_or_informative():
    summary = summarise(_full_records(), suite="t", config_hash="c", version="v", methods=["core", "paper"],
                        oracles=["segmentation"], extra={"n_planned": 4, "complete": True,
                                                         "run": {"wall_s": 3.0, "workers": 2}})
    assert summary["pose"]["initial"] and summary["change"]["objects"] and summary["segmentation"]["by_size"]
    assert summary["classification"]["radius"]["CYL"]["n"] > 0 and summary["oracles"]["segmentation"]
    assert metrics.undeclared(summary) == []
    for name in ("default", "classic"):  # real summaries, as committed
        assert metrics.undeclared(json.loads((ROOT / f"docs/results/{name}.summary.json").read_text())) == [], name
    # what is not declared is named, lists included
    summary["groups"]["a/x"]["pose"]["jitter_mm"] = 1.0
    summary["segmentation"]["errors"] = [1.0, 2.0]
    summary["change"]["per_label"]["moved"]["f2"] = None
    assert metrics.undeclared(summary) == ["change.per_label.moved.f2", "groups.*.pose.jitter_mm",
                                           "segmentation.errors[]"]


def test_the_declarations_are_one_of_each():
    keys = [m.key for m in metrics.METRICS] + [i.key for i in metrics.INFORMATIVE]
    assert len(keys) == len(set(keys))
    assert [m.key for m in metrics.judged()] == [
        "segmentation.correct_detection_rate", "classification.accuracy", "classification.brier",
        "pose.success_rate", "pose.success_rate_constrained", "pose.rotation_error_deg.median",
        "pose.translation_error_mm.median", "change.macro_f1"]
    assert [m.key for m in metrics.run_checks()] == ["n_failed"]
    assert [m.key for m in metrics.run_checks(check_time=True)] == ["n_failed", "timing_s.total.median"]
    compact = [m.compact for m in metrics.compact()]
    assert len(compact) == len(set(compact))
    # the most specific declaration wins
    assert metrics.declaration(("timing_s", "total", "median")).headline
    assert metrics.declaration(("timing_s", "icp", "median")).key == "timing_s.*.median"
    assert isinstance(metrics.declaration(("groups", "g", "view", "surfaces_seen", "median")), Informative)
    with pytest.raises(KeyError, match="did you mean classification.accuracy"):
        metrics.metric("classification.acuracy")


def test_tolerances_name_declared_metrics_only(tmp_path, capsys):
    assert Tolerances.load(TOLERANCES_DIR / "default.yaml") == DEFAULT_TOLERANCES
    text = (TOLERANCES_DIR / "default.yaml").read_text()
    good = tmp_path / "good.yaml"
    good.write_text(text.replace("per_metric: {}", "per_metric: {classification.accuracy: 0.01, "
                                 "'groups.factory/scanner[noise_scale=0.5].baselines.paper.change.macro_f1': 0.05, "
                                 "classification.per_class.CYL.recall: 0.1}"))
    assert Tolerances.load(good).per_metric["classification.accuracy"] == 0.01
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("per_metric: {}", "per_metric: {classification.acuracy: 0.01}"))
    with pytest.raises(ConfigError) as info:
        Tolerances.load(bad)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{bad}: per_metric.classification.acuracy: not a declared "
                                                      "metric") and "did you mean classification.accuracy?" in message
    for edit in ("per_metric: {segmentation.tolerance: 0.1}", "per_metric: {oracles.pose: 0.1}"):
        bad.write_text(text.replace("per_metric: {}", edit))  # informative, or no metric at all
        with pytest.raises(ConfigError, match="not a declared metric"):
            Tolerances.load(bad)
    bad.write_text(text.replace("rate_drop:", "rate_dorp:"))
    with pytest.raises(ConfigError, match=r"unknown key\(s\) rate_dorp") as info:
        Tolerances.load(bad)
    assert str(info.value).startswith(f"{bad}: ") and "\n" not in str(info.value)
    # harness compare says it in one line and exits 2
    runs = [write_run(tmp_path / name, trials(BASE)) for name in ("base", "cand")]
    code, out, err = run_compare(capsys, *runs, "--tolerances", bad)
    assert code == 2 and out == "" and len(err.strip().splitlines()) == 1 and "rate_dorp" in err
