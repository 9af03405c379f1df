"""The soak command on CI-sized runs (6 trials by default, 20 with the slow tests) on a 2-worker Dask
LocalCluster. The full soak is ``python -m harness.bench.soak --trials 1000 --dask-local 2 --out DIR``
(harness/bench/soak.py)."""

from __future__ import annotations

import json

import pytest

from harness.bench.soak import main, soak_suite, throughput


def test_soak_suite_has_exactly_the_requested_trials(tmp_path):
    for n in (1, 20, 999, 1000):
        suite = soak_suite(n, tmp_path / str(n))
        assert len(suite.trials) == n and len({t.trial_id for t in suite.trials}) == n
    assert throughput([0.0, 6.0, 12.0, 18.0, 24.0, 30.0, 36.0, 42.0, 48.0, 54.0, 60.0]) == (10.0, 10.0)
    assert throughput([0.0]) == (None, None)


def _soak(tmp_path, capsys, n: int) -> None:
    pytest.importorskip("distributed")
    out = tmp_path / "soak"
    code = main(["--trials", str(n), "--dask-local", "2", "--out", str(out), "--min-throughput-ratio", "0"])
    report = json.loads((out / "soak.json").read_text())
    assert report["n_written"] == n and report["complete"]
    assert report["children_left"] == [] and report["temp_files_left"] == [] and report["partial_files_left"] == []
    assert len(report["peak_worker_rss_mb"]) == 2
    assert all(0 < mb < 2000 for mb in report["peak_worker_rss_mb"].values()), report["peak_worker_rss_mb"]
    assert report["n_failed"] == 0, report["failures"]
    assert code == 0, report["checks"]
    assert main(["--trials", str(n), "--out", str(out)]) == 2  # a directory that holds a run is refused
    assert "already holds trial records" in capsys.readouterr().err


def test_soak_6_trials(tmp_path, capsys):
    _soak(tmp_path, capsys, 6)


@pytest.mark.slow
def test_soak_20_trials(tmp_path, capsys):
    _soak(tmp_path, capsys, 20)
