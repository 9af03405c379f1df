"""Generated results tables: the README's and docs' figures come from committed summaries, never typed."""

import json

import _support
import pytest

from harness.cli import main
from reports.results import BEGIN, END, generated_block, results_markdown, results_table

ROOT = _support.ROOT


def _summary(groups):
    def sec(acc, ci):
        return {"n_trials": 4, "ci95_bootstrap": {"n_clusters": 2}, "segmentation": None,
                "classification": {"accuracy": acc, "accuracy_ci95": ci, "brier": 0.1, "brier_ci95": None},
                "pose": None, "change": None}
    return {"schema": "harness.summary/1", "suite": "s", "n_trials": 8, "n_failed": 0,
            "provenance": {"git_commit": "0123456789abcdef", "machine": {"cpus": 2}},
            **sec(0.9, [0.85, 0.95]), "groups": {g: sec(0.8, [0.7, 0.9]) for g in groups}}


def test_a_table_row_per_group_and_one_for_all_with_intervals():
    table = results_table(_summary(["b/x", "a/y"])).splitlines()
    assert table[0].startswith("| group | trials | scenes | correct detection")
    assert [r.split("|")[1].strip() for r in table[2:]] == ["`a/y`", "`b/x`", "**all**"]
    assert "0.900 [0.85, 0.95]" in table[-1] and "0.100 |" in table[-1]  # no interval: the bare number
    assert "| n/a |" in table[-1]  # a stage with no figure says so


def test_results_into_a_file_replaces_only_its_block(tmp_path):
    summary = tmp_path / "summary.json"
    summary.write_text(json.dumps(_summary(["g"])))
    doc = tmp_path / "doc.md"
    doc.write_text(f"before\n{BEGIN}\nold figures\n{END}\nafter\n")
    assert main(["results", str(summary), "--title", "T", "--into", str(doc)]) == 0
    text = doc.read_text()
    assert text.startswith("before\n") and text.endswith("after\n") and "old figures" not in text
    assert generated_block(text) == results_markdown([("T", json.loads(summary.read_text()))])
    doc.write_text("no markers\n")
    assert main(["results", str(summary), "--into", str(doc)]) == 2


@pytest.mark.parametrize("doc, summaries", [
    ("README.md", ["docs/results/default.summary.json"]),
    ("docs/results.md", ["docs/results/default.summary.json", "docs/results/full.summary.json",
                         "docs/results/classic.summary.json"]),
])
def test_the_shipped_tables_are_what_the_committed_summaries_give(doc, summaries):
    text = (ROOT / doc).read_text(encoding="utf-8")
    titles = [line.removeprefix("#### ") for line in generated_block(text).splitlines() if line.startswith("#### ")]
    expected = results_markdown([(t, json.loads((ROOT / s).read_text())) for t, s in zip(titles, summaries,
                                                                                            strict=True)])
    assert generated_block(text) == expected, f"{doc}: regenerate with `harness results ... --into {doc}`"
