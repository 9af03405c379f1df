"""Aggregation of per-trial sections into the summary: hand-made records with known answers."""

from __future__ import annotations

import pytest

from evaluation.aggregate import aggregate_classification, radius_errors


def _patch(label, truth, est=None, true=None, sigma=None, n=500):
    p = {"label": label, "truth": truth, "n_pixels": n, "probabilities": {label: 1.0}}
    if est is not None:
        p["radius"] = {"estimate_m": est, "truth_m": true, "sigma_m": sigma}
    return p


def test_radius_errors_of_correctly_labelled_patches():
    patches = [_patch("CYL", "CYL", 0.101, 0.1, 0.002),   # +1 %, within 2 sigma
               _patch("CYL", "CYL", 0.097, 0.1, 0.001),   # -3 %, 3 sigma off
               _patch("CYL", "CYL", 0.1005, 0.1, 0.001),  # +0.5 %, within
               _patch("CYL", "CONE", 0.5, 0.1, 0.001),    # truth is another class: left out
               _patch("SPH", "SPH", 0.2, 0.2, 0.001)]
    cyl = radius_errors(patches, "CYL")
    assert cyl["n"] == 3
    assert cyl["median_abs_rel_error"] == pytest.approx(0.01)
    assert cyl["median_rel_error"] == pytest.approx(0.005)
    assert cyl["within_2_sigma"] == pytest.approx(2 / 3)
    assert radius_errors(patches, "SPH")["median_abs_rel_error"] == pytest.approx(0.0)
    assert radius_errors([_patch("PLAN", "PLAN")], "CYL") is None


def test_classification_summary_carries_the_radius_figures():
    trial = {"patches": [_patch("CYL", "CYL", 0.101, 0.1, 0.002), _patch("CYL", "CYL", 0.2, 0.1, 0.001, n=50)]}
    agg = aggregate_classification([trial])
    assert agg["radius"]["CYL"]["n"] == 1  # the 50-pixel patch is below the size the scores count
    assert agg["radius"]["SPH"] is None


def test_missed_causes_are_averaged_over_images_like_the_rates():
    from evaluation.aggregate import aggregate_segmentation

    def image(missed, causes):
        rates = {"correct_detection_rate": None if missed is None else 1.0 - missed, "over_rate": 0.0,
                 "under_rate": 0.0, "missed_rate": missed, "noise_rate": 0.0}
        return {**rates, "tolerance": 0.8, "n_truth": 4, "missed_causes": causes}

    a = image(0.5, {"unlabelled": 0.25, "split": 0.0, "merged": 0.25})
    b = image(0.25, {"unlabelled": 0.0, "split": 0.25, "merged": 0.0})
    c = image(None, {"unlabelled": None, "split": None, "merged": None})  # nothing to count
    out = aggregate_segmentation([a, b, c])
    assert out["missed_causes"] == {"unlabelled": 0.125, "split": 0.125, "merged": 0.125}
    assert sum(out["missed_causes"].values()) == out["missed_rate"]
