"""Tests of the per-decision-path reliability of the classifier's confidence (harness.bench.confidence) and of
the Brier-optimal floor it fits (evaluation.classification.optimal_floor)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from evaluation.classification import CLASSES, brier_score, decision_path_table, optimal_floor
from harness.bench.confidence import main


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 30))
def test_optimal_floor_is_the_minimum_of_the_brier_score(seed, n):
    """The closed form against a fine grid of floors (the Brier score is a parabola in the floor)."""
    g = np.random.default_rng(seed)
    q = g.dirichlet(np.full(5, 0.3), size=n)
    truth = [CLASSES[i] for i in g.integers(0, 5, n)]
    f = optimal_floor(truth, q)
    grid = np.linspace(0, 1, 2001)
    scores = [brier_score(truth, (1 - x) * q + x / 5) for x in grid]
    assert brier_score(truth, (1 - f) * q + f / 5) <= min(scores) + 1e-12
    assert 0.0 <= f <= 1.0


def test_optimal_floor_closed_cases():
    one = np.eye(5)[[0, 1]]  # certain and right: no floor
    assert optimal_floor(["PLAN", "CYL"], one) == 0.0
    assert optimal_floor(["CYL", "PLAN"], one) == 1.0  # certain and always wrong: the uniform distribution
    # certain and right half the time: the Brier sum 20 f² / 25 + (1 - 4f / 5)² + (1 - f / 5)² + 3 f² / 25 has
    # its minimum at f = 5 / 8, where the label's probability is 1 / 2
    f = optimal_floor(["PLAN", "CYL"], np.eye(5)[[0, 0]])
    assert f == pytest.approx(0.625) and (1 - f) + f / 5 == pytest.approx(0.5)
    assert optimal_floor([], np.zeros((0, 5))) is None
    assert optimal_floor(["PLAN"], np.full((1, 5), 0.2)) is None


def _row(path, label, truth, p_label, floor=0.1, n=500):
    raw = {c: (1 - p_label) / 4 for c in CLASSES}
    raw[label] = p_label
    return {"n_pixels": n, "truth": truth, "label": label, "path": path, "floor": floor,
            "probabilities": {c: (1 - floor) * v + floor / 5 for c, v in raw.items()}}


def test_path_table_groups_by_path_and_inverts_the_runs_floor():
    rows = [_row("criterion", "CYL", "CYL", 1.0)] * 9 + [_row("criterion", "CYL", "PLAN", 1.0)] + \
        [_row("rescue", "CYL", "CYL", 0.9, floor=0.3), _row("rescue", "CYL", "CONE", 0.9, floor=0.3)] + \
        [{**_row("x", "OTH", "OTH", 0.4, floor=0.0), "path": None}]
    del rows[-1]["path"]
    t = {r["path"]: r for r in decision_path_table(rows)}
    assert set(t) == {"criterion", "rescue", "none", "all"}
    assert t["criterion"]["count"] == 10 and t["criterion"]["accuracy"] == 0.9
    assert t["criterion"]["confidence"] == pytest.approx(0.92)
    assert t["rescue"]["floor"] == 0.3
    # the optimal floor is fitted on the raw probabilities: the same whatever floor the run applied
    again = [_row("criterion", r["label"], r["truth"], 1.0, floor=0.5) for r in rows[:10]]
    assert decision_path_table(again)[0]["optimal_floor"] == pytest.approx(t["criterion"]["optimal_floor"])
    assert t["all"]["count"] == len(rows)


def test_main_reads_a_results_directory(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    assert "not a results directory" in capsys.readouterr().err
    (tmp_path / "trials").mkdir()
    rows = [_row("criterion", "CYL", "CYL", 1.0), _row("rescue", "CYL", "PLAN", 0.8, n=150)]
    record = {"trial_id": "factory-s1-p0-v0-kinect_like-n0",
              "methods": {"core": {"classification": {"patches": rows}}}}
    (tmp_path / "trials" / "a.json").write_text(json.dumps(record))
    assert main([str(tmp_path), "--group", "mockup"]) == 2
    capsys.readouterr()
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "criterion" in out and "rescue" not in out  # 150 pixels: below the scored size
    assert main([str(tmp_path), "--min-pixels", "100"]) == 0
    assert "rescue" in capsys.readouterr().out
