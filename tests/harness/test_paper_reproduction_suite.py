"""The paper_reproduction suite (issue 37): it loads, expands into its conditions, reaches the options of
PaperParams, and uses scene seeds that no other shipped suite holds."""

from __future__ import annotations

from harness.suite import load_suite, shipped_suites
from harness.trial import viewpoint_spec
from recognition import PaperParams, SelectParams


def test_paper_reproduction_expands_into_noise_and_distance_groups_with_the_options_as_methods():
    suite = load_suite("paper_reproduction")
    groups = {t.group for t in suite.trials}
    assert groups == {f"mockup/mockup_laser[noise_scale={n}][view_distance={d}]"
                      for n in ("0.25", "0.5", "1", "2") for d in ("0.6", "1.2")}
    assert len(suite.trials) == 40 and all(t.family == "mockup" for t in suite.trials)
    for t in suite.trials:
        lo, hi = viewpoint_spec(t).distance_m
        assert (lo, hi) == (0.9 * t.overrides["view_distance"], 1.1 * t.overrides["view_distance"])
    classify = {m: s.params.describe.classifier_params for m, s in suite.specs.items()}
    assert classify["core"] is None or isinstance(classify["core"], SelectParams)
    assert suite.specs["core"].params.describe.classifier == "select"
    assert classify["paper"] in (None, PaperParams())
    assert classify["paper_soft"] == PaperParams(zero_rule="soft")
    assert classify["paper_first_order"] == PaperParams(sigma_mode="first_order")
    assert classify["paper_n300"] == PaperParams(max_points=300)
    assert classify["paper_n300_random"] == PaperParams(max_points=300, subsample="random")


def test_paper_reproduction_scenes_are_in_no_other_shipped_suite():
    mine = {t.scene for t in load_suite("paper_reproduction").trials}
    for name in shipped_suites():
        if name != "paper_reproduction":
            assert not mine & {t.scene for t in load_suite(name).trials}, name


def test_planar_hint_block_counts_and_the_docs_block_is_what_the_committed_json_gives():
    import json

    import _support

    from harness.bench import planar_hint as ph

    row = {"truth": "CYL", "label": "PLAN", "planar_hint": True, "plane_within_noise": False, "planar_share": 0.9,
           "median_abs_H": 5.0, "median_zero_bound": 20.0}
    data = {"schema": ph.SCHEMA, "suite": "s", "zero_k": 3.0,
            "groups": {"g": [row, {**row, "truth": "PLAN", "plane_within_noise": True, "planar_share": 1.0}]}}
    assert "| `g` | 2 (1) | 2 (1) | 1 (0) | 2 (1) | 0.90 | 5.00 | 20.00 |" in ph.markdown(data)
    text = (_support.ROOT / "docs" / "paper_reproduction.md").read_text(encoding="utf-8")
    committed = json.loads((_support.ROOT / "docs" / "results" / "planar_hint.json").read_text(encoding="utf-8"))
    assert ph.generated_block(text) == ph.markdown(committed), (
        "regenerate with `python -m harness.bench.planar_hint --from docs/results/planar_hint.json "
        "--into docs/paper_reproduction.md`")
