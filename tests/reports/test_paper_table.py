"""The paper's table against a run's conditions (reports.paper_table, issue 37): the logic on small synthetic
records, the command, and the generated block of docs/paper_reproduction.md against its committed JSON."""

from __future__ import annotations

import json

import _support
import pytest

from reports import paper_table as pt

ROOT = _support.ROOT


def _patch(i, n, truth, label, p_cyl):
    return {"patch": i, "n_pixels": n, "truth": truth, "label": label,
            "plausibilities": {"CYL": p_cyl, "SPH": 0.0, "CONE": 0.0}}


def _record(tid, group, methods, status="ok"):
    return {"trial_id": tid, "status": status, "spec": {"group": group},
            "methods": {m: {"classification": {"patches": ps}} for m, ps in methods.items()}}


def _paper_like():
    """Patches as the paper's table: its 7 cylinders at its P(cyl), 2 OTH and 5 planar patches labelled OTH."""
    return [_patch(r.region, 6000, r.truth, r.label, r.p_cyl) for r in pt.PAPER_ROWS]


def test_the_papers_table_is_typed_as_published():
    assert len(pt.PAPER_ROWS) == 14 and [r.region for r in pt.PAPER_ROWS] == [5, 6, 7, 9, 11, 12, 13, 15, 16, 18,
                                                                              19, 21, 22, 23]
    cyl = [r for r in pt.PAPER_ROWS if r.truth == "CYL"]
    assert len(cyl) == 7 and all(r.label == "CYL" for r in cyl)
    assert min(r.p_cyl for r in cyl) == 0.21 and max(r.p_cyl for r in cyl) == 0.55
    assert all(r.label == "OTH" for r in pt.PAPER_ROWS if r.truth != "CYL")
    assert sum(r.truth == "PLAN" for r in pt.PAPER_ROWS) == 5
    assert "Fillatreau" in pt.CITATION and "section 6" in pt.CITATION


def test_the_papers_own_table_is_at_distance_zero_and_its_claim_holds():
    data = pt.compact([_record("t", "g", {"paper": _paper_like(), "core": _paper_like()})])
    (c,) = [c for c in pt.conditions(data) if c.size == pt.SIZE_CLASSES[0]]
    assert c.stats.n_cyl == 7 and c.stats.recall == 1.0 and c.stats.cyl_in_band == 7
    assert (c.stats.n_oth, c.stats.oth_labelled, c.stats.n_planar, c.stats.planar_oth) == (2, 2, 5, 5)
    assert c.distance == 0.0 and c.stats.ks == 0.0
    assert pt.verdict(c.stats).startswith("Holds: 7 of 7 cylinders CYL, 7 of them at P(cyl) 0.2-0.55")
    assert pt.summary_sentences(data)[0].startswith("The paper's claim holds in g, paper, >= 200 px")


def test_conditions_count_recall_band_quartiles_and_the_core_beside():
    rows = [(300, "CYL", "CYL", 0.3), (400, "CYL", "CYL", 0.9), (2000, "CYL", "OTH", 0.0), (6000, "CYL", "CYL", 0.5),
            (6000, "CYL", "PLAN", 0.0), (300, "PLAN", "CYL", 0.4), (300, "PLAN", "PLAN", 0.0), (800, "OTH", "OTH", 0.0),
            (150, "CYL", "CYL", 0.3), (300, "SPH", "SPH", 0.0), (20, "PLAN", "OTH", 0.0), (40, "PLAN", "OTH", 0.0)]
    paper = [_patch(i, *r) for i, r in enumerate(rows)]
    paper[-1]["reason"] = "too small to classify (40 pixels)"  # OTH without a fit: not the quadric test's
    core = [_patch(i, p["n_pixels"], p["truth"], p["truth"], 0.9) for i, p in enumerate(paper)]
    records = [_record("a", "m/s[noise_scale=2][view_distance=0.6]", {"paper": paper, "core": core}),
               _record("b", "m/s[noise_scale=2][view_distance=0.6]", {"paper": []}, status="failed")]
    data = pt.compact(records, "s", "abc")
    g = data["groups"]["m/s[noise_scale=2][view_distance=0.6]"]
    # planar PLAN, SPH, under 30 px and unfitted ones left out; the 150 px one is in the small class only
    assert g["n_trials"] == 1 and len(g["methods"]["paper"]) == 8
    by = {(c.method, c.size): c for c in pt.conditions(data)}
    s = by["paper", pt.SIZE_CLASSES[0]].stats
    assert (s.n_cyl, s.cyl_labelled, s.cyl_in_band, s.cyl_plan) == (5, 3, 2, 1)  # 0.3 and 0.5 in band, 0.9 not
    assert s.quartiles == pytest.approx((0.0, 0.3, 0.5))
    assert (s.n_oth, s.oth_labelled, s.n_planar, s.planar_oth) == (1, 1, 1, 0)
    assert by["paper", pt.SIZE_CLASSES[0]].core.recall == 1.0
    # distance: KS to the paper's 7 values + 2/5 cylinders missed + 1/2 other quadric patches not OTH
    assert by["paper", pt.SIZE_CLASSES[0]].distance == pytest.approx(
        pt.ks_distance([0.0, 0.0, 0.3, 0.5, 0.9], pt.paper_cylinder_values()) + 0.4 + 0.5)
    assert pt.verdict(s) == ("Holds only for the elbows/junctions: 3 of 5 cylinders CYL, 2 of them at P(cyl) "
                             "0.2-0.55; 1 of 1 elbows/junctions OTH; 0 of 1 planar patches that reached the quadric "
                             "test OTH.")
    small = by["paper", (200, 1000)].stats
    assert small.n_cyl == 2 and pt.verdict(small) == "Too few cylinder patches to tell (2)."
    assert by["paper", (30, 200)].stats.n_cyl == 1
    assert pt.group_label("m/s[noise_scale=2][view_distance=0.6]") == "noise x2, 0.6 m"
    assert pt.closest(pt.conditions(data)) == [by["paper", pt.SIZE_CLASSES[0]]]
    (all_groups,) = pt.pooled(data)
    assert all_groups.stats == s and all_groups.group == pt.POOLED
    text = pt.markdown(data)
    assert ("| noise x2, 0.6 m | paper | >= 200 px | 0.60 (3/5) | 0.00 / 0.30 / 0.50 | 2/5 | 1 | 1/1 | 0/1 | "
            "1.00 (5/5) |") in text
    assert "No condition of this run reproduces the paper's table" in text
    sec = pt.paper_reproduction_section(records, "s")
    assert sec is not None and sec.id == "paper-reproduction"
    assert pt.paper_reproduction_section([_record("c", "g", {"core": core})]) is None  # no paper method


def test_ks_distance():
    assert pt.ks_distance([0.0, 1.0], [0.5]) == 0.5
    assert pt.ks_distance([0.1, 0.2], [0.1, 0.2]) == 0.0
    assert pt.ks_distance([0.0], [1.0]) == 1.0
    assert pt.ks_distance([], [1.0]) is None


def test_the_command_writes_json_and_regenerates_a_block(tmp_path, capsys):
    run = tmp_path / "run"
    (run / "trials").mkdir(parents=True)
    (run / "trials" / "t.json").write_text(json.dumps(_record("t", "g", {"paper": _paper_like()})))
    (run / "run.json").write_text(json.dumps({"suite": "s", "code": {"commit": "0123456789abcdef",
                                                                      "diff_sha256": None}}))
    out = tmp_path / "data.json"
    assert pt.main([str(run), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("Suite `s`, 1 trials, commit `0123456789ab`.")
    doc = tmp_path / "doc.md"
    doc.write_text(f"before\n{pt.BEGIN}\nold\n{pt.END}\nafter\n")
    assert pt.main([str(out), "--into", str(doc)]) == 0
    text = doc.read_text()
    assert pt.generated_block(text) == printed and text.startswith("before\n") and text.endswith("after\n")
    assert pt.main([str(tmp_path / "missing.json")]) == 2
    doc.write_text("no markers\n")
    assert pt.main([str(out), "--into", str(doc)]) == 2


def test_the_docs_block_is_what_the_committed_json_gives():
    text = (ROOT / "docs" / "paper_reproduction.md").read_text(encoding="utf-8")
    data = pt.load_compact(ROOT / "docs" / "results" / "paper_reproduction.json")
    assert pt.generated_block(text) == pt.markdown(data), (
        "regenerate with `python -m reports.paper_table docs/results/paper_reproduction.json "
        "--into docs/paper_reproduction.md`")
