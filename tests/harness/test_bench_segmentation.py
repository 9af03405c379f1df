"""The segmentation benchmark's ``--against REV``: the same frames segmented by another commit's segmenter."""

from __future__ import annotations

import json
import subprocess

import _support
import pytest

from harness.bench.segmentation import WorkerError, _Worker, main

SUITE = """
schema: suite/1
name: tiny
seed: 3
timeout_s: 60
methods: {core: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    perturbation_seeds: [0]
    sensor: tiny_sensor.yaml
    viewpoints: 1
    noise_seeds: [0]
    min_view_pixels: 50
    min_view_surfaces: 3
"""


def _segmenter_is_committed() -> bool:
    """Whether the code ``segment`` runs is the same in the working tree and at HEAD (other work in progress
    in the same checkout may change it: then the two sides' labels may differ, rightly)."""
    out = subprocess.run(["git", "-C", str(_support.ROOT), "status", "--porcelain", "--",
                          "recognition/segmentation", "recognition/fitting"], capture_output=True, text=True)
    return out.returncode == 0 and not out.stdout.strip()


# about 15 s of CPU (three processes import the core; a scene is prepared), but over a minute of wall time on a
# shared 2-core machine
@pytest.mark.slow
def test_against_head_reports_both_times_their_ratio_and_equal_labels(tmp_path, tiny_sensor, capsys):
    suite = tmp_path / "tiny.yaml"
    suite.write_text(SUITE)
    out = tmp_path / "bench.json"
    before = subprocess.run(["git", "-C", str(_support.ROOT), "worktree", "list"], capture_output=True,
                            text=True).stdout
    assert main(["--suite", str(suite), "--limit", "1", "--repeat", "1", "--against", "HEAD",
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "against HEAD: this tree" in printed and "ratio" in printed
    assert "labels sha1 this tree" in printed
    result = json.loads(out.read_text())["against"]
    (frame,) = result["frames"]
    assert frame["cpu_s"] > 0 and frame["cpu_s_against"] > 0
    assert frame["ratio"] == pytest.approx(frame["cpu_s"] / frame["cpu_s_against"])
    assert result["groups"]["all"]["n"] == 1 and result["groups"]["all"]["ratio_of_medians"] > 0
    assert result["segmenter"]["segmenter"] == result["segmenter_against"]["segmenter"] == \
        "recognition.segmentation.segment"
    assert len(result["labels_sha1"]) == len(result["labels_sha1_against"]) == 40
    # this tree's worker segments what the benchmark segmented in its own process
    assert frame["labels_sha1"] == json.loads(out.read_text())["frames"][0]["labels_sha1"]
    if _segmenter_is_committed():
        assert frame["labels_sha1_against"] == frame["labels_sha1"]
        assert result["labels_sha1_against"] == result["labels_sha1"]
    # the temporary worktree is gone
    after = subprocess.run(["git", "-C", str(_support.ROOT), "worktree", "list"], capture_output=True,
                           text=True).stdout
    assert result["commit"][:12] not in after.replace(before, "") and "bench-against-" not in after


def test_a_worker_refuses_a_tree_whose_modules_resolve_elsewhere(tmp_path):
    """A package missing from the other tree resolves to the installed project (the editable install): the
    worker says so rather than time a mixture."""
    pkg = tmp_path / "recognition"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    # ``scenes`` is not in tmp_path: it comes from the installed project
    (pkg / "segmentation.py").write_text("import scenes\n\ndef segment(points, sigma):\n    raise AssertionError\n")
    with pytest.raises(WorkerError, match=r"modules from outside .*scenes \("):
        _ = _Worker(tmp_path, "fake").ready
    # so does a module missing from a package the tree has: the editable install serves a package's children
    (pkg / "segmentation.py").unlink()
    with pytest.raises(WorkerError, match=r"modules from outside .*recognition\.segmentation \("):
        _ = _Worker(tmp_path, "fake").ready


def test_a_worker_without_a_segmenter_says_where_it_looked(tmp_path):
    (tmp_path / "recognition").mkdir()
    (tmp_path / "recognition" / "__init__.py").write_text("")
    (tmp_path / "recognition" / "segmentation.py").write_text("def other(points, sigma):\n    pass\n")
    with pytest.raises(WorkerError, match=r"no segmenter in .*recognition\.segmentation\.segment"):
        _ = _Worker(tmp_path, "fake").ready


def _run_json(commit: str, rev: str, ratios: list[float]) -> dict:
    frames = [{"ratio": r, "cpu_s": r, "cpu_s_against": 1.0} for r in ratios]
    groups = {"mockup/mockup_laser": {"n": len(ratios), "cpu_median_s": 0.25, "cpu_median_s_against": 0.5,
                                      "ratio_of_medians": 0.5, "identical_labels": len(ratios)},
              "all": {"n": len(ratios), "cpu_median_s": 0.25, "cpu_median_s_against": 0.5, "ratio_of_medians": 0.5,
                      "identical_labels": len(ratios) - 1}}
    return {"suite": "default", "commit": commit, "against": {
        "rev": rev, "commit": "b" * 40, "repeat": 1, "labels_sha1": "c" * 40, "labels_sha1_against": "d" * 40,
        "groups": groups, "frames": frames}}


def test_against_tables_render_from_json_into_a_markdown_block(tmp_path, capsys):
    from harness.bench.segmentation import BEGIN, END, against_markdown

    run = _run_json("a" * 40, "0b5908a", [0.4, 0.5, 0.6])
    block = against_markdown([run])
    assert "This tree `aaaaaaaaaaaa` against `bbbbbbbbbbbb` (`0b5908a`), suite `default`: 3 frames" in block
    assert "per-frame ratios median 0.50" in block
    assert "| `mockup/mockup_laser` | 3 | 0.250 | 0.500 | 0.50 | 3 / 3 |" in block
    assert "| all | 3 | 0.250 | 0.500 | 0.50 | 2 / 3 |" in block
    assert "by step" not in block  # a run without --steps has no step table
    steps = {**run, "frames": [{"steps_s": {"edges": 0.01, "merging": 0.03}},
                               {"steps_s": {"edges": 0.03, "merging": 0.01}}]}
    assert "| edges | 20.0 | 20.0 | 50.0% |\n| merging | 20.0 | 20.0 | 50.0% |\n| total | 40.0 | 40.0 |  |" in \
        against_markdown([steps])
    src = tmp_path / "run.json"
    src.write_text(json.dumps(run))
    doc = tmp_path / "doc.md"
    doc.write_text(f"before\n{BEGIN}\nold\n{END}\nafter\n")
    assert main(["--from", str(src), "--into", str(doc)]) == 0
    assert doc.read_text() == f"before\n{BEGIN}\n{block}{END}\nafter\n"
    # bad input: one line naming the file, and a non-zero exit
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"suite": "default"}))
    assert main(["--from", str(bad)]) == 2
    assert "bad.json: no 'against' and 'commit' fields" in capsys.readouterr().err
    (tmp_path / "plain.md").write_text("no markers\n")
    assert main(["--from", str(src), "--into", str(tmp_path / "plain.md")]) == 2
    assert "plain.md: no generated block" in capsys.readouterr().err



#: the --against runs behind docs/performance.md's tables, in the order they are shown
AGAINST_RUNS = ("segmentation-against-0b5908a.json", "segmentation-against-8353850.json",
                "segmentation-against-445e44a.json", "segmentation-against-0b5908a-elbow-joins.json")


def test_performance_doc_holds_the_committed_against_tables():
    from harness.bench.segmentation import BEGIN, END, against_markdown
    from reports.generated_blocks import generated_block

    runs = [json.loads((_support.ROOT / "docs" / "results" / name).read_text(encoding="utf-8"))
            for name in AGAINST_RUNS]
    text = (_support.ROOT / "docs" / "performance.md").read_text(encoding="utf-8")
    assert generated_block(text, BEGIN, END) == against_markdown(runs), (
        "regenerate with `python -m harness.bench_segmentation --from "
        + " ".join(f"docs/results/{n}" for n in AGAINST_RUNS) + " --into docs/performance.md`")
