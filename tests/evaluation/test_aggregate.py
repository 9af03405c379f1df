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


def test_correct_detection_by_size_counts_hand_made_regions():
    import numpy as np

    from evaluation.hoover import hoover_score
    from evaluation.patches import counts_by_size

    truth = np.full((100, 100), -1)
    truth[:10, :30] = 0   # 300 px: found whole
    truth[20:30, :80] = 1  # 800 px: not labelled at all
    truth[40:100, :] = 2  # 6000 px: cut in two halves
    truth[:5, 90:] = 3    # 50 px: below the scored size
    machine = np.full_like(truth, -1)
    machine[:10, :30] = 0
    machine[40:70, :] = 1
    machine[70:100, :] = 2
    machine[:5, 90:] = 3
    rows = counts_by_size(truth, hoover_score(machine, truth, 0.8, min_truth_pixels=200))
    assert [(r["min_pixels"], r["max_pixels"]) for r in rows] == [(200, 500), (500, 1000), (1000, 5000),
                                                                  (5000, None)]
    assert [(r["n_truth"], r["n_correct"], r["n_over"], r["n_under"], r["n_missed"]) for r in rows] == [
        (1, 1, 0, 0, 0), (1, 0, 0, 0, 1), (0, 0, 0, 0, 0), (1, 0, 1, 0, 0)]


def test_size_classes_are_pooled_over_images():
    from evaluation.aggregate import aggregate_segmentation

    def image(counts):
        by_size = [{"min_pixels": 200, "max_pixels": 500, "n_truth": sum(counts), "n_correct": counts[0],
                    "n_over": 0, "n_under": 0, "n_missed": counts[1]}]
        return {"correct_detection_rate": None, "over_rate": None, "under_rate": None, "missed_rate": None,
                "noise_rate": None, "tolerance": 0.8, "n_truth": sum(counts), "by_size": by_size}

    # one image with 3 of 4 regions found, one with 0 of 1: pooled 3 / 5 (a mean over images would say 0.375)
    (row,) = aggregate_segmentation([image((3, 1)), image((0, 1)), image((0, 0))])["by_size"]
    assert row["n_truth"] == 5 and row["correct_detection_rate"] == pytest.approx(0.6)
    assert row["missed_rate"] == pytest.approx(0.4) and row["over_rate"] == 0.0
    (empty,) = aggregate_segmentation([image((0, 0))])["by_size"]
    assert empty["correct_detection_rate"] is None
