"""The evaluation report: every section on hand-made runs (null and present pose/change, sweeps, peers,
baselines), escaping and self-containment, figures, the gallery helpers, the trial index and its links, and the
page as a person sees it in headless Chromium at 1400 px (a hand-made report always; the smoke suite's report in
the slow test): no horizontal overflow, every figure captioned, every local link resolving, a screenshot."""

from __future__ import annotations

import base64
import json
import re
from pathlib import Path
from types import SimpleNamespace

import _chromium  # tests/ is on sys.path under pytest's default import mode
import numpy as np
import pytest

from harness.summary import summarise
from reports import figures
from reports.colours import CHANGE_LABELS, CLASSES, method_colour
from reports.document import GalleryTrial, Image, Table
from reports.html import SORT_SCRIPT
from reports.markdown import escape_md, render_markdown
from reports.regression import NOT_BUILT, headline_deltas, lookup
from reports.render import (
    TRIAL_PAGES_DIR,
    build_document,
    distinct_sweeps,
    load_run,
    paper_table_rows,
    parse_sweep_group,
    pose_verdict,
    render_report,
    time_budget,
    trial_page_name,
    trial_score,
    worst_trials,
)
from reports.trial_page import write_trial_page

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
RATES = ("correct_detection_rate", "over_rate", "under_rate", "missed_rate", "noise_rate")
SWEEP_T = (0.51, 0.6, 0.7, 0.8, 0.9, 0.95)


# -- hand-made runs -----------------------------------------------------------------------------------------
def _segmentation(cdr: float) -> dict:
    rates = {"correct_detection_rate": cdr, "over_rate": 0.1, "under_rate": 0.1, "missed_rate": 0.9 - cdr - 0.1,
             "noise_rate": 0.05}
    sweep = [{"tolerance": t, **{k: (v * (1.2 - t) if k == "correct_detection_rate" else v) for k, v in rates.items()}}
             for t in SWEEP_T]
    missed = rates["missed_rate"]
    causes = {"unlabelled": 0.5 * missed, "split": 0.0, "merged": 0.5 * missed}
    by_size = [{"min_pixels": 200, "max_pixels": 500, "n_truth": 4, "n_correct": 1, "n_over": 1, "n_under": 0,
                "n_missed": 2},
               {"min_pixels": 500, "max_pixels": None, "n_truth": 6, "n_correct": 5, "n_over": 0, "n_under": 1,
                "n_missed": 0}]
    return {**rates, "tolerance": 0.8, "min_truth_pixels": 200, "n_truth": 10, "n_machine": 12, "sweep": sweep,
            "missed_causes": causes, "by_size": by_size}


def _patches(n_right: int, n_wrong: int, paper: bool) -> list[dict]:
    out = []
    for i in range(n_right + n_wrong):
        truth = ("PLAN", "CYL", "SPH")[i % 3]
        label = truth if i < n_right else "OTH"
        pl = {"CYL": 0.7 if truth == "CYL" else 0.05, "SPH": 0.6 if truth == "SPH" else 0.0, "CONE": 0.02}
        probs = dict.fromkeys(CLASSES, 0.02)
        probs[label] = 0.92
        out.append({"patch": i, "n_pixels": 300 + 50 * i, "truth": truth, "truth_feature": f"feat{i}",
                    "label": label, "probabilities": probs, "plausibilities": pl if paper else pl,
                    "reason": "", "small": False, "noisy": False})
        if not paper:  # how the core reached the label, and the floor of that path (0.1: 0.92 for a sure label)
            out[-1].update(path="criterion" if i < n_right else "unexplained", floor=0.1)
    return out


def _pose(k: int) -> dict:
    return {"rotation_error_deg": 0.3 + k, "translation_error_mm": 4.0 + 10 * k, "add_mm": 5.0 + k,
            "success": k == 0, "constrained": True,
            "initial": {"rotation_error_deg": 3.0 + k, "translation_error_mm": 40.0 + k, "success": False}}


def _change(k: int) -> dict:
    feats = [{"feature": "pipe", "truth": "moved", "predicted": "moved" if k == 0 else "unchanged"},
             {"feature": "tank", "truth": "missing", "predicted": "missing"},
             {"feature": "box", "truth": "unchanged", "predicted": "unchanged"},
             {"feature": "new1", "truth": "new", "predicted": "new"},
             {"feature": "elbow", "truth": "altered", "predicted": "moved"}]
    return {"features": feats, "objects": [{"truth": "moved", "predicted": "moved"}],
            "displacement_error_mm": [12.0 + k]}


def make_records(*, pose: bool, change: bool, groups: tuple[str, ...] = ("mockup/mockup_laser",),
                 methods: tuple[str, ...] = ("core", "paper"), fail_one: bool = False) -> list[dict]:
    """Trial records in the runner's format (harness.trial.run_trial)."""
    records = []
    for gi, group in enumerate(groups):
        for k in range(2):
            tid = f"{group.replace('/', '-')}-v{k}"
            meths = {}
            for mi, m in enumerate(methods):
                meths[m] = {"segmentation": _segmentation(0.5 + 0.1 * k + 0.05 * gi),
                            "classification": {"patches": _patches(6 - mi - k, 1 + mi, m == "paper")},
                            "pose": _pose(k) if pose else None, "change": _change(k) if change else None,
                            "timing_s": {"segmentation": 1.0 + k, "classification": 0.5, "matching": 0.2 if pose
                                         else None, "icp": 0.3 if pose else None, "change": 0.1 if change else None}}
            records.append({"schema": "harness.trial/1", "trial_id": tid, "status": "ok", "reason": "",
                            "spec": {"trial_id": tid, "index": len(records), "group": group, "scene": "mockup"},
                            "view": {"T_world_sensor": np.eye(4).tolist(), "viewpoint_rejection_rate": 0.1,
                                     "valid_fraction": 0.9, "surfaces_seen": 8},
                            "timing_s": {"sensor": 2.0, "total": 5.0 + k}, "methods": meths})
    if fail_one:
        records.append({"trial_id": "broken-trial", "status": "failed", "reason": "no acceptable viewpoint",
                        "spec": {"trial_id": "broken-trial", "group": groups[0]}, "timing_s": {}, "methods": {}})
    return records


def write_run(root: Path, records: list[dict], suite: str = "handmade", methods: tuple[str, ...] = ("core", "paper"),
              **extra) -> Path:
    """A run directory (summary.json, run.json, trials/) made with the runner's own summarise()."""
    root.mkdir(parents=True, exist_ok=True)
    prov = {"version": "0.1.0", "git_commit": "abc123", "python": "3.11", "libraries": {"numpy": "2"},
            "machine": {"cpus": 2}, "command": f"harness bench --suite {suite} --out {root}"}
    summary = summarise(records, suite=suite, config_hash="cafe", version="0.1.0", methods=list(methods),
                        extra={"complete": True, "n_planned": len(records), "provenance": prov,
                               "run": {"wall_s": 12.0, "workers": 2, "n_run": len(records),
                                       "trials_per_minute": 10.0}, **extra})
    (root / "summary.json").write_text(json.dumps(summary), encoding="utf-8")
    (root / "run.json").write_text(json.dumps({"schema": "harness.run/1", "suite": suite, "source": "x.yaml",
                                               "suite_config": {"name": suite, "methods": {m: {} for m in methods}},
                                               "trials": [r["trial_id"] for r in records], "provenance": prov}),
                                   encoding="utf-8")
    (root / "trials").mkdir(exist_ok=True)
    for r in records:
        (root / "trials" / f"{r['trial_id']}.json").write_text(json.dumps(r), encoding="utf-8")
    return root


def img_alts(html: str) -> list[str]:
    return re.findall(r'<img src="data:image/png;base64,[A-Za-z0-9+/=]+" alt="([^"]*)"', html)


def tiny_png() -> bytes:
    return figures.shaded_picture(np.linspace(0, 1, 48 * 64).reshape(48, 64))


# -- sections -----------------------------------------------------------------------------------------------
PEERS = ("core", "paper", "fpfh_ransac")


def gallery() -> list[GalleryTrial]:
    return [GalleryTrial("mockup-mockup_laser-v1", "mockup/mockup_laser", "score 0.40: worst",
                         (Image(tiny_png(), "Cosine-shaded range image"),),
                         ("Registration before and after ICP: not built yet (pose is null in the record).",))]


@pytest.fixture(scope="module")
def null_report(tmp_path_factory):
    """A run whose pose and change stages are null (as today), rendered once: (run_dir, html, md)."""
    run = write_run(tmp_path_factory.mktemp("null") / "run", make_records(pose=False, change=False))
    html_path, md_path = render_report(run)
    return run, html_path.read_text(), md_path.read_text()


PAGED = "mockup-mockup_laser-v1"  # the trial of the hand-made full report that has a page


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    """Every stage present, a peer method, a failed trial, a gallery and one trial page, rendered once:
    (run_dir, html, md)."""
    records = make_records(pose=True, change=True, methods=PEERS, fail_one=True)
    run = write_run(tmp_path_factory.mktemp("full") / "run", records, methods=PEERS)
    entry = gallery()[0]
    write_trial_page(run / TRIAL_PAGES_DIR / trial_page_name(PAGED), load_run(run),
                     next(r for r in records if r["trial_id"] == PAGED), entry, link_report=True)
    html_path, md_path = render_report(run, gallery=gallery())
    return run, html_path.read_text(), md_path.read_text()


def test_null_pose_and_change_say_not_built_yet(null_report):
    _, html, md = null_report
    for text in (html, md):
        assert "Pose has no figure" in text
        assert "Change has no figure" in text
        assert "Headline" in text and "Segmentation" in text and "Timing" in text
    alts = img_alts(html)
    assert {"Hoover metrics vs tolerance", "confusion matrix", "reliability diagram", "stage times"} <= set(alts)
    assert "pose error CDF" not in alts and "per-label change F1" not in alts
    assert '<table id="headline">' in html
    assert html.count("no figure") >= 4  # headline cells say it too, rather than disappear
    assert 'id="sweeps"' not in html and 'id="oracles"' not in html  # sections that only exist when run


def test_present_pose_and_change_are_tabled_and_plotted(full_report):
    run, html, _ = full_report
    assert "Pose has no figure" not in html and "Change has no figure" not in html
    alts = img_alts(html)
    assert "pose error CDF" in alts and "per-label change F1" in alts
    summary = json.loads((run / "summary.json").read_text())
    assert f"{summary['pose']['success_rate']:.3f}" in html
    assert f"{summary['change']['macro_f1']:.3f}" in html
    assert "core, initial" in html  # before-ICP row of the pose table
    # the missed rate split by cause, from the summary
    causes = summary["segmentation"]["missed_causes"]
    assert sum(causes.values()) == pytest.approx(summary["segmentation"]["missed_rate"])
    table = re.search(r"Missed truth regions by cause.*?</table>", html, re.S).group(0)
    assert f"{causes['merged']:.3f}" in table
    # correct detection per region size, pooled over the images
    small, large = summary["segmentation"]["by_size"]
    assert small["correct_detection_rate"] == pytest.approx(0.25)
    assert large["correct_detection_rate"] == pytest.approx(5 / 6)
    table = re.search(r"Correct detection by truth region size.*?</table>", html, re.S).group(0)
    assert "200-499 px" in table and "500+ px" in table
    assert f"0.250 ({small['n_truth']})" in table and f"0.833 ({large['n_truth']})" in table


def test_sweep_groups_get_a_metric_vs_value_plot(tmp_path):
    groups = tuple(f"factory_bay/factory_scanner[noise_scale={v:g}]" for v in (0.5, 1, 2))
    run = write_run(tmp_path / "run", make_records(pose=False, change=False, groups=groups))
    html = render_report(run)[0].read_text()
    assert 'id="sweeps"' in html and "metrics vs noise_scale" in img_alts(html)
    assert parse_sweep_group("factory_bay/factory_scanner[noise_scale=2]") == ("factory_bay/factory_scanner",
                                                                               {"noise_scale": 2.0})
    assert parse_sweep_group("a/b[noise_scale=0.5][max_range=4]") == ("a/b", {"noise_scale": 0.5, "max_range": 4.0})
    assert parse_sweep_group("mockup/mockup_laser") is None


def test_each_decision_path_of_the_classifier_is_tabled(full_report, null_report):
    """The core's patch records say how each label was reached: the report tables each path's accuracy against
    its stated confidence (the hand-made records: right at 0.92 by the criterion, wrong at 0.92 as unexplained OTH,
    whose Brier-optimal floor is then 1: every class alike)."""
    from reports.render import decision_path_rows, load_run

    for run, html, md in (full_report, null_report):
        assert "How sure each decision path" in html and "How sure each decision path" in md
        data = load_run(run)
        rows = {(r[0].text, r[1].text): [c.text for c in r[2:]] for r in decision_path_rows(data, {"core": {}}, 200)}
        assert rows[("core", "criterion")][1:3] == ["1.000", "0.920"]
        assert rows[("core", "unexplained")][1:3] == ["0.000", "0.920"]
        assert rows[("core", "unexplained")][5] == "1.000"
        assert not decision_path_rows(data, {"paper": {}}, 200)  # the paper's records carry no path


def test_peer_methods_side_by_side(full_report):
    _, html, _ = full_report
    head = re.search(r'<table id="headline">.*?</table>', html, re.S).group(0)
    assert re.findall(r"<th>(core|paper|fpfh_ransac)</th>", head) == list(PEERS)  # core, paper, then peers
    assert 'id="methods"' in html and html.count("fpfh_ransac") >= 4
    assert method_colour("fpfh_ransac", PEERS) != method_colour("paper", PEERS)


def test_oracles_beside_the_end_to_end_core(tmp_path):
    records = make_records(pose=True, change=False)
    for r in records:
        r["oracles"] = {"segmentation": r["methods"]["core"], "pose": {**r["methods"]["core"], "pose": _pose(0)}}
    run = tmp_path / "run"
    write_run(run, records)
    summary = json.loads((run / "summary.json").read_text())
    summary["oracles"] = {o: {"classification": {"accuracy": 0.99}, "segmentation": None, "pose": None,
                              "change": None} for o in ("segmentation", "pose")}
    (run / "summary.json").write_text(json.dumps(summary))
    html = render_report(run)[0].read_text()
    table = re.search(r'<table id="oracles">.*?</table>', html, re.S).group(0)
    assert "<th>oracle: segmentation</th>" in table and "0.990" in table and "core (end to end)" in table


def test_paper_table_from_paper_records(null_report):
    _, html, _ = null_report
    table = re.search(r'<table id="paper-table">.*?</table>', html, re.S).group(0)
    for col in ("region", "P(cyl)", "P(sphere)", "P(cone)", "class"):
        assert f"<th>{col}</th>" in table
    patches = [{"patch": 3, "n_pixels": 500, "truth": "CYL", "label": "CYL", "truth_feature": "pipe",
                "plausibilities": {"CYL": 0.54, "SPH": 0.0, "CONE": 0.1}},
               {"patch": 1, "n_pixels": 900, "truth": "PLAN", "label": "PLAN", "plausibilities": {}},
               {"patch": 2, "n_pixels": 50, "truth": "SPH", "label": "OTH", "plausibilities": {}},
               {"patch": 4, "n_pixels": 400, "truth": "PLAN", "label": "OTH", "plausibilities": {"CONE": 0.04}}]
    rows = paper_table_rows(patches, {3: "CYL", 4: "PLAN"})
    assert [r[0].text for r in rows] == ["3", "4"]  # planar PLAN and small patches are not listed
    assert [c.text for c in rows[0][2:6]] == ["0.54", "0.00", "0.10", "CYL"]
    assert rows[0][5].style == "good" and rows[1][5].style == "bad" and rows[1][-1].style == "good"


def test_failures_listed_and_left_out_of_the_gallery(full_report):
    _, html, _ = full_report
    assert "broken-trial" in html and "no acceptable viewpoint" in html
    records = make_records(pose=False, change=False, fail_one=True)
    assert all(r["trial_id"] != "broken-trial" for r, _, _ in worst_trials(records, 10))


def test_worst_trials_first():
    records = make_records(pose=True, change=True)
    ranked = worst_trials(records, 5)
    scores = [s for _, s, _ in ranked]
    assert scores == sorted(scores) and len(ranked) == len(records) == 2
    assert len(worst_trials(records, 1)) == 1 and worst_trials(records, 0) == []
    worst = ranked[0][0]
    assert worst["trial_id"].endswith("-v1")  # fewer right labels, pose failed, one change label wrong
    score, why = trial_score(worst)
    assert 0 <= score < 1 and "accuracy" in why and "pose success 0.00" in why
    assert trial_score({"status": "failed", "reason": "x"})[0] == -1


def test_gallery_is_rendered_with_its_pictures_and_notes(full_report):
    _, html, md = full_report
    assert 'id="trial-mockup-mockup-laser-v1"' in html and "Cosine-shaded range image" in img_alts(html)
    assert "score 0.40: worst" in md and "1 pictures (see report.html)" in md
    # the paper's table follows the first gallery trial, whose region numbers the gallery shows
    assert "for trial mockup-mockup_laser-v1" in html


def test_regression_section_with_and_without_verdicts(tmp_path):
    from harness.compare import compare_dirs, format_comparison, load_run

    base = write_run(tmp_path / "base", make_records(pose=False, change=False))
    records = make_records(pose=False, change=False)
    for r in records:
        r["methods"]["core"]["classification"]["patches"][0]["label"] = "OTH"  # worse accuracy
    cand = write_run(tmp_path / "cand", records)
    html = render_report(cand, base)[0].read_text()
    assert 'id="regression"' in html and "Deltas only" in html
    worse = compare_dirs(load_run(base), load_run(cand))  # harness compare's verdict, handed in
    html, md = (p.read_text() for p in render_report(cand, base, comparison=worse))
    assert not worse.passed and "**FAIL:**" in md and "REGRESSION" in html
    assert escape_md(f"{worse.verdict_text()} (the rules of harness compare)") in md
    # the same row as harness compare prints (one implementation of the verdicts and their cells)
    cli = format_comparison(worse, "base", "cand", "md")
    row = next(line for line in cli.splitlines() if line.startswith("| core | classification accuracy | all |"))
    assert row.endswith("| -0.154 |  | REGRESSION (tolerance alone) |") and row in md
    html = render_report(cand, base, comparison=compare_dirs(load_run(base), load_run(base)))[0].read_text()
    assert "No regression" in html and 'class="note pass"' in html


def test_headline_deltas_direction_and_missing():
    # the headline metrics and their directions are evaluation.metrics's declarations (missed rate: not headline)
    b = {"segmentation": {"correct_detection_rate": 0.5, "missed_rate": 0.2}, "classification": None,
         "pose": {"rotation_error_deg": {"median": 0.2}}, "timing_s": {"total": {"median": 2.0}}}
    c = {"segmentation": {"correct_detection_rate": 0.6, "missed_rate": 0.3}, "classification": None,
         "pose": {"rotation_error_deg": {"median": 0.3}}, "timing_s": {"total": {"median": 2.0}}}
    d = {r["metric"]: r for r in headline_deltas(b, c)}
    assert d["segmentation.correct_detection_rate"]["better"] is True
    assert d["pose.rotation_error_deg.median"]["better"] is False and "segmentation.missed_rate" not in d
    assert d["classification.accuracy"]["delta"] is None and d["timing_s.total.median"]["better"] is None
    assert lookup(b, ("classification", "accuracy")) is NOT_BUILT
    assert lookup(b, ("pose", "success_rate")).why == "n/a"


# -- escaping and self-containment --------------------------------------------------------------------------
def test_text_is_escaped(tmp_path):
    evil = '<script>alert("x")</script>|*'
    run = write_run(tmp_path / "run", make_records(pose=False, change=False), suite=evil)
    html, md = (p.read_text() for p in render_report(run))
    assert "<script>alert" not in html and "&lt;script&gt;" in html
    prose = re.sub(r"```.*?```", "", md, flags=re.S)  # code blocks show text verbatim, and safely
    assert "<script>" not in prose and "\\<script\\>" in prose and escape_md("a|b") == "a\\|b"
    table = Table(("a|b",), (("c|d",),))
    assert "a\\|b" in render_markdown(SimpleNamespace(title="t", subtitle="s", sections=[
        SimpleNamespace(title="x", blocks=[table], subsections=[])]))


def test_html_is_self_contained(full_report):
    _, html, _ = full_report
    assert not re.search(r'(src|href)="(https?:)?//', html)
    assert "@import" not in html and "url(" not in html
    # the only script: the inline lines that sort the trial index (no source, nothing fetched)
    assert re.findall(r"<script[^>]*>", html) == ["<script>"] and SORT_SCRIPT in html
    srcs = re.findall(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"', html)
    assert len(srcs) >= 6 and all(base64.b64decode(s)[:8] == PNG_MAGIC for s in srcs)
    assert len(re.findall("<img ", html)) == len(srcs)


def test_load_run_rejects_a_directory_without_summary(tmp_path):
    with pytest.raises(FileNotFoundError, match="no summary.json"):
        load_run(tmp_path)
    (tmp_path / "summary.json").write_text("{}")
    with pytest.raises(ValueError, match="not a harness summary"):
        load_run(tmp_path)


def test_document_sections_in_order(null_report):
    run = load_run(null_report[0])
    ids = [s.id for s in build_document(run).sections]
    assert ids[:2] == ["headline", "run"] and ids[-1] == "failures"
    assert ids.index("segmentation") < ids.index("classification") < ids.index("pose") < ids.index("change")


# -- figures ------------------------------------------------------------------------------------------------
FIGURES = {
    "hoover": lambda: figures.hoover_sweep_figure({"core": _segmentation(0.6)["sweep"]}, 0.8),
    "confusion": lambda: figures.confusion_figure({"core": {"classes": list(CLASSES),
                                                            "matrix": np.eye(5, dtype=int).tolist()}}),
    "reliability_empty_bins": lambda: figures.reliability_figure(
        {"core": [{"low": 0.9, "high": 1.0, "confidence": 0.95, "accuracy": 0.9, "count": 10},
                  {"low": 0.0, "high": 0.1, "confidence": 0.0, "accuracy": 0.0, "count": 0}], "paper": []}),
    "per_class": lambda: figures.per_class_figure({"core": {c: {"precision": None, "recall": 0.5, "support": 1}
                                                            for c in CLASSES}}),
    "pose_cdf": lambda: figures.pose_cdf_figure({"core": {"rotation_error_deg": {"after ICP": [0.1, 2.0, np.nan]},
                                                          "translation_error_mm": {"after ICP": [1.0]}}}),
    "change_f1": lambda: figures.change_f1_figure({"core": {lab: {"f1": None if lab == "new" else 0.5,
                                                                  "support": 2} for lab in CHANGE_LABELS}}),
    "sweep": lambda: figures.sweep_figure("noise_scale", {"accuracy": [(0.5, 0.9), (1.0, None), (2.0, 0.6)]}),
    "timing": lambda: figures.timing_figure({"core": {"sensor": {"median": 1.0, "p90": 2.0}, "icp": None}}),
    "regions": lambda: figures.region_picture(np.arange(40 * 60).reshape(40, 60) // 600 - 1),
    "overlay": lambda: figures.class_overlay_picture(np.full((30, 40), 0.5), np.full((30, 40), 1),
                                                     np.eye(30, 40, dtype=bool)),
    "change_map": lambda: figures.change_picture(np.full((30, 40), np.nan), np.full((30, 40), -1), "none"),
    "registration": lambda: figures.registration_picture(None, np.full((30, 40), 0.001), "after only"),
    "range": lambda: figures.range_picture(np.where(np.eye(30, 40) > 0, np.nan,
                                                    np.linspace(1, 3, 1200).reshape(30, 40))),
    "hk": lambda: figures.hk_picture(np.arange(30 * 40).reshape(30, 40) % 5, np.eye(30, 40)),
    "classes": lambda: figures.class_picture(np.arange(30 * 40).reshape(30, 40) % 6 - 1, "c", [(5.0, 5.0, "3")]),
    "time_budget": lambda: figures.time_budget_figure({"sensor": 0.5, "oracles": 0.0, "rest": 0.3, "total": 1.4,
                                                       "n_trials": 4, "methods": {"core": {"segmentation": 0.4,
                                                                                           "icp": 0.1},
                                                                                  "paper": {"matching": 0.1}}}),
    "pose_scatter": lambda: figures.pose_scatter_figure(
        [{"group": g, "range_m": 1.0 + i, "angle_deg": 10.0 * i, "rotation_error_deg": 0.1 * i or None,
          "translation_error_mm": 2.0 * i, "ok": i % 2 == 0} for i, g in enumerate(["a/x", "b/y", "a/x"])],
        ["a/x", "b/y"]),
}


@pytest.mark.parametrize("name", sorted(FIGURES))
def test_figures_are_png(name):
    png = FIGURES[name]()
    assert png[:8] == PNG_MAGIC and len(png) > 2000


def test_patch_centres_lie_on_their_region():
    lab = -np.ones((50, 50), dtype=int)
    lab[5:45, 5:10] = 3
    lab[40:45, 5:45] = 3  # an L: its centroid is off the region
    for x, y, i in figures.patch_centres(lab, min_pixels=10):
        assert lab[int(y), int(x)] == i == 3


# -- gallery helpers (harness side) -------------------------------------------------------------------------
def test_spec_from_record_and_change_index():
    from harness.gallery import predicted_change_index, spec_from_record
    from harness.suite import TrialSpec

    spec = TrialSpec("t", 0, "g", "mockup", "s.yaml", None, 0, 0, "mockup_laser", 0, 7, overrides={"noise_scale": 2})
    back = spec_from_record({"spec": json.loads(json.dumps(spec.to_dict()))})
    assert back == spec and isinstance(back.overrides["noise_scale"], float)
    truth = SimpleNamespace(surfaces=[SimpleNamespace(feature_id="pipe"), SimpleNamespace(feature_id="box")],
                            surface_id=np.array([[0, 1, -1]]))
    idx = predicted_change_index(truth, [{"feature": "pipe", "predicted": "moved"}])
    assert idx.tolist() == [[CHANGE_LABELS.index("moved"), -1, -1]]
    assert predicted_change_index(truth, [{"truth": "moved", "predicted": "moved"}]) is None


def test_registration_residuals_from_recorded_poses():
    from harness.gallery import registration_residuals
    from harness.suite import TrialSpec

    spec = TrialSpec("t", 0, "g", "mockup", "s.yaml", None, 0, 0, "mockup_laser", 0, 7)
    H, W = 480, 640
    predictor = SimpleNamespace(predict=lambda sensor, T: SimpleNamespace(range=np.full((H, W), 2.0 + T[0, 3])))
    r = SimpleNamespace(spec=spec, scan=SimpleNamespace(range=np.full((H, W), 2.0)),
                        prepared=SimpleNamespace(predictor=predictor))
    shifted = np.eye(4)
    shifted[0, 3] = 0.01
    before, after = registration_residuals(r, {"T_world_sensor": np.eye(4).tolist(),
                                               "initial": {"T_world_sensor": shifted.tolist()}})
    assert np.allclose(before, -0.01) and np.allclose(after, 0.0)
    assert figures.registration_picture(before, after, "t")[:8] == PNG_MAGIC


# -- in a browser -------------------------------------------------------------------------------------------
def check_page(html_path: Path, screenshot: Path, min_images: int) -> dict:
    """The page at 1400 px: the layout checks of :func:`_chromium.check_layout` (no horizontal overflow, every
    figure captioned, every local link resolving), the headline table present, and a screenshot that is not
    blank, written to ``screenshot`` (its path printed for the CI log)."""
    from matplotlib.image import imread

    m = _chromium.check_layout(html_path, min_figures=min_images)
    dom = _chromium.dump_dom(html_path)
    assert re.search(r'<table id="headline">.*?<td', dom, re.S), "the headline table is not in the page"
    _chromium.screenshot(html_path, screenshot, height=4000)
    print(f"screenshot of {html_path}: {screenshot}")
    shot = imread(screenshot)[..., :3]
    assert shot.shape[0] >= 1000 and shot.shape[1] == _chromium.WIDTH
    not_white = np.mean(np.any(shot < 0.9, axis=-1))
    assert not_white > 0.03, f"the screenshot looks blank ({not_white:.1%} non-white pixels)"
    assert shot.std() > 0.05
    return m


def test_report_in_headless_chromium(full_report, tmp_path):
    run, html, _ = full_report
    m = check_page(run / "report.html", tmp_path / "report.png", min_images=8)
    assert "no figure" not in re.search(r'<table id="headline">.*?</table>', html, re.S).group(0)
    # the trial index links the one trial that has a page, and the page exists (check_page: every link resolves)
    pages = [h for h in m["hrefs"] if h.startswith(TRIAL_PAGES_DIR + "/")]
    assert set(pages) == {f"{TRIAL_PAGES_DIR}/{trial_page_name(PAGED)}"}
    # its headers sort it: the worst trial first, then the best
    scores = {r["trial_id"]: trial_score(r)[0] for r in load_run(run).records}  # a failed trial scores -1
    assert m["sorted_firsts"] == [min(scores, key=scores.get), max(scores, key=scores.get)]
    # figures stand two to a row at their natural width in a 1400 px window (none shown smaller than 600 px)
    assert all(shown >= min(natural, 600) for natural, shown in m["images"]), m["images"]
    # the trial page: the same checks, and its link back to the report resolves
    page = run / TRIAL_PAGES_DIR / trial_page_name(PAGED)
    pm = _chromium.check_layout(page, min_figures=1)
    assert "../report.html" in pm["hrefs"]


def test_regression_tables_fit_with_their_full_verdicts_in_headless_chromium(tmp_path):
    from harness.compare import compare_dirs
    from harness.compare import load_run as load_compare_run

    base = write_run(tmp_path / "base", make_records(pose=True, change=True, methods=PEERS), methods=PEERS)
    records = make_records(pose=True, change=True, methods=PEERS)
    for r in records:
        r["methods"]["core"]["classification"]["patches"][0]["label"] = "OTH"
    cand = write_run(tmp_path / "cand", records, methods=PEERS)
    html = render_report(cand, base, comparison=compare_dirs(load_compare_run(base), load_compare_run(cand)))[0]
    _chromium.check_layout(html, min_figures=4)  # no table of the regression section runs off the page
    dom = _chromium.dump_dom(html)
    cells = re.findall(r'<td class="bad">([^<]+)</td>', re.search(r'<section id="regression">.*?</section>', dom,
                                                                   re.S).group(0))
    assert "REGRESSION (tolerance alone)" in cells  # the whole word, not cut at the edge of a scrolled table


def test_trial_index_lists_every_trial_and_links_only_pages_that_exist(full_report):
    run, html, md = full_report
    table = re.search(r'<table id="trial-index" class="sortable">.*?</table>', html, re.S).group(0)
    records = load_run(run).records
    for r in records:
        assert f">{r['trial_id']}<" in table
    links = re.findall(r'<a href="([^"]+)">', table)
    assert links == [f"{TRIAL_PAGES_DIR}/{trial_page_name(PAGED)}"]
    assert f"harness report {run} --trials all" in html  # the command that writes the others
    assert "failed: no acceptable viewpoint" in table  # a failed trial is listed, with why
    assert "Trials (" in md and "see the HTML page" in md  # the long table is left out of the Markdown
    assert pose_verdict({"ok": True, "success": False}) == ("WRONG, stated ok", "bad")
    assert pose_verdict({"ok": False, "success": True, "reason": "ambiguous: another pose agrees 0.9 vs 0.8"}
                        )[0] == "not ok: ambiguous, was right"


def test_the_report_is_deterministic(full_report):
    run, html, md = full_report
    again_html, again_md = (p.read_text() for p in render_report(run, gallery=gallery()))
    assert again_html == html and again_md == md


def test_time_budget_accounts_for_the_whole_trial(full_report):
    run, html, _ = full_report
    records = [{**r, "timing_s": {**r["timing_s"], "total": 12.0}} for r in load_run(run).ok_records()]
    records[0]["oracles"] = {"pose": {"timing_s": {"change": 0.25, "icp": None}}}
    budget = time_budget(records)
    parts = budget["sensor"] + budget["oracles"] + budget["rest"] + sum(
        sum(st.values()) for st in budget["methods"].values())
    assert parts == pytest.approx(budget["total"]) == 12.0
    # sensor 2, core and paper 2.1 s each (k = 0) or 3.1 s (k = 1), the peer 2.1 / 3.1, oracles 0.25 / 2
    assert budget["oracles"] == pytest.approx(0.125) and budget["rest"] == pytest.approx(12 - 2 - 3 * 2.6 - 0.125)
    assert "time budget of a trial" in img_alts(html)
    table = re.search(r'<table id="timing">.*?</table>', html, re.S).group(0)
    assert "evaluation + overhead" in table and "no figure" not in table


def test_hoover_plot_draws_each_distinct_segmentation_once():
    same = _segmentation(0.6)["sweep"]
    sweeps, same_as = distinct_sweeps({"core": {"sweep": same}, "paper": {"sweep": _segmentation(0.5)["sweep"]},
                                       "diff_change": {"sweep": list(same)}, "none": None})
    assert list(sweeps) == ["core", "paper"] and same_as == {"core": ["diff_change"], "paper": []}
    assert figures.hoover_sweep_figure(sweeps, 0.8, same_as)[:8] == PNG_MAGIC


@pytest.mark.slow
def test_smoke_suite_report_in_headless_chromium(tmp_path):
    """The smoke suite end to end: bench (report and gallery included), then a report against itself."""
    from harness.cli import main

    assert _chromium.chromium()
    out = tmp_path / "smoke"
    assert main(["bench", "--suite", "smoke", "--out", str(out), "--workers", "2", "--progress", "log"]) == 0
    html = (out / "report.html").read_text()
    assert (out / "report.md").read_text().startswith("# Evaluation report: smoke")
    headline = re.search(r'<table id="headline">.*?</table>', html, re.S).group(0)
    assert "no figure" not in headline  # every stage has landed: no section is null
    assert "Cosine-shaded range image (black: no return)." in html  # the gallery was re-run without --artifacts
    assert "differ from the recorded ones" not in html  # ... and reproduced the recorded patches
    m = check_page(out / "report.html", tmp_path / "smoke.png", min_images=10)
    pages = sorted(p.name for p in (out / TRIAL_PAGES_DIR).glob("*.html"))  # the gallery's trials have pages
    assert pages and all(f"{TRIAL_PAGES_DIR}/{name}" in m["hrefs"] for name in pages)
    _chromium.check_layout(out / TRIAL_PAGES_DIR / pages[0], min_figures=8)
    assert main(["report", str(out), "--baseline", str(out), "--gallery", "1"]) == 0
    html = (out / "report.html").read_text()
    assert 'id="regression"' in html and "No regression" in html


# -- intervals (DESIGN 11.3) --------------------------------------------------------------------------------
def test_intervals_appear_in_the_tables_of_a_many_scene_run(tmp_path):
    records = make_records(pose=True, change=True, groups=("mockup/mockup_laser", "factory_bay/factory_scanner"))
    for i, r in enumerate(records):
        r["spec"]["scene"] = f"scene-s{i}"  # four scenes pooled, two in each group
    run = write_run(tmp_path / "run", records)
    summary = json.loads((run / "summary.json").read_text())
    html, md = (p.read_text() for p in render_report(run))
    lo, hi = summary["classification"]["accuracy_ci95"]
    acc = f"{summary['classification']['accuracy']:.3f} [{lo:.2f}, {hi:.2f}]"
    headline = re.search(r'<table id="headline">.*?</table>', html, re.S).group(0)
    assert acc in headline and f"{summary['pose']['success_rate']:.3f} [" in headline
    assert acc.replace("[", "\\[").replace("]", "\\]") in md  # Markdown escapes the brackets
    lo, hi = summary["pose"]["rotation_error_deg"]["median_ci95"]
    assert f"{summary['pose']['rotation_error_deg']['median']:.3f} [{lo:.2f}, {hi:.2f}]" in html
    lo, hi = summary["groups"]["mockup/mockup_laser"]["segmentation"]["correct_detection_rate_ci95"]
    assert f"{summary['groups']['mockup/mockup_laser']['segmentation']['correct_detection_rate']:.3f} " \
           f"[{lo:.2f}, {hi:.2f}]" in html  # per group
    assert "headline rates per group" in img_alts(html) and "Pooled over 4 scenes" in html


def test_one_scene_run_shows_no_interval(null_report, full_report):
    for run, html, md in (null_report, full_report):
        summary = json.loads((run / "summary.json").read_text())
        assert summary["ci95_bootstrap"]["n_clusters"] == 1 and summary["classification"]["accuracy_ci95"] is None
        tables = "".join(re.findall(r"<table.*?</table>", html, re.S))
        assert not re.search(r"\d \[-?\d", tables)  # no "0.812 [0.76, 0.86]" anywhere
        assert not re.search(r"\d \\\[-?\d", md)
        assert "one scene gives no interval over scenes" in html


def test_error_bars_are_drawn_only_where_there_is_an_interval():
    bars = figures.error_bars([0.5, 0.6, np.nan, 0.2], [(0.4, 0.7), None, (0.1, 0.2), (0.25, 0.3)])
    assert bars[:, 0].tolist() == pytest.approx([0.1, 0.2]) and np.all(np.isnan(bars[:, 1:3]))
    assert bars[:, 3].tolist() == pytest.approx([0.0, 0.1])  # an interval above the value: no negative bar
    png = figures.group_headline_figure({"accuracy": {"a/x": (0.8, (0.7, 0.9)), "b/y": (0.6, None)},
                                         "pose success": {"a/x": (0.5, (0.2, 0.8))}})
    assert png[:8] == PNG_MAGIC
    png = figures.sweep_figure("noise_scale", {"accuracy": [(0.5, 0.9, (0.8, 0.95)), (1.0, None, None),
                                                            (2.0, 0.6, None)]})
    assert png[:8] == PNG_MAGIC
