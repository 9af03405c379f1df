"""Pages per trial and the one colour language, on a tiny real run (two trials of a 160 x 120 sensor):
``harness report --trials`` and ``harness show`` write trial pages that the report's index links, the pages pass
the browser checks at 1400 px, the report is the same bytes when rendered again, and ``harness describe``'s
pictures carry their legend and region numbers in the report's colours (the same palette object)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: the shared browser helpers
import _chromium  # noqa: E402

from harness.cli import main  # noqa: E402
from reports import colours, figures  # noqa: E402
from reports.render import TRIAL_PAGES_DIR, find_trial_pages, load_run, trial_page_name  # noqa: E402

SENSOR = """
schema: sensor/1
name: tiny
pinhole: {width: 160, height: 120, fov_deg: 40.0, min_range: 0.3, max_range: 2.5}
noise: {range: {model: ray, s0_m: 1.0e-4, s2_per_m: 1.0e-4}}
"""
SUITE = """
schema: suite/1
name: tiny
seed: 3
methods: {core: {}, paper: {}}
groups:
  - scene: mockup
    perturbation: mockup_perturbation
    sensor: tiny_sensor.yaml
    viewpoints: 2
    min_view_pixels: 50
    min_view_surfaces: 3
"""
BOX = Path(__file__).resolve().parents[3] / "shared" / "data" / "real" / "pyransac3d" / "caixa2.ply"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A two-trial run, then its report with a page for every trial: (run_dir, trial ids, report bytes)."""
    d = tmp_path_factory.mktemp("tiny")
    (d / "tiny_sensor.yaml").write_text(SENSOR)
    (d / "tiny.yaml").write_text(SUITE)
    run = d / "run"
    assert main(["bench", "--suite", str(d / "tiny.yaml"), "--out", str(run), "--workers", "1", "--no-report",
                 "--progress", "log"]) == 0
    assert main(["report", str(run), "--gallery", "1", "--trials", "all"]) == 0
    ids = [str(r["trial_id"]) for r in load_run(run).records]
    return run, ids, (run / "report.html").read_bytes()


def test_report_trials_all_writes_a_linked_page_per_trial(tiny, tmp_path):
    run, ids, html = tiny
    assert len(ids) == 2
    for tid in ids:
        assert (run / TRIAL_PAGES_DIR / trial_page_name(tid)).is_file()
    text = html.decode()
    links = re.findall(r'<a href="(trials_html/[^"]+)">', re.search(r'<table id="trial-index".*?</table>', text,
                                                                     re.S).group(0))
    assert links == [f"{TRIAL_PAGES_DIR}/{trial_page_name(t)}" for t in ids]
    m = _chromium.check_layout(run / "report.html", min_figures=10)
    assert {f"{TRIAL_PAGES_DIR}/{trial_page_name(t)}" for t in ids} <= set(m["hrefs"])
    page = run / TRIAL_PAGES_DIR / trial_page_name(ids[0])
    pm = _chromium.check_layout(page, min_figures=9)
    assert "../report.html" in pm["hrefs"] and "../report.html#trials" in pm["hrefs"]
    shot = _chromium.screenshot(page, tmp_path / "trial.png", height=3000)
    print(f"screenshot of {page}: {shot}")
    page_text = page.read_text()
    for caption in ("The range image", "H-K curvature classes", "Registration", "The scene in 3D",
                    "in the colour of the truth surface"):
        assert caption in page_text, caption
    assert '<img src="data:image/png;base64,' in page_text  # the report's pages embed their pictures


def test_the_same_run_renders_the_same_report_bytes(tiny):
    run, _, html = tiny
    assert main(["report", str(run), "--gallery", "1", "--trials", "none"]) == 0
    assert (run / "report.html").read_bytes() == html


def test_show_writes_a_trial_page_beside_its_pictures(tiny, capsys):
    run, ids, _ = tiny
    out = run / "show" / ids[1]
    assert main(["show", str(run), ids[1]]) == 0
    assert "page -> " in capsys.readouterr().out
    page = out / "trial.html"
    text = page.read_text()
    srcs = re.findall(r'<img src="([^"]+)"', text)
    files = [s for s in srcs if not s.startswith("data:")]
    assert len(files) >= 9 and len(srcs) == len(files) + 1  # the pictures beside it; the page's timing embedded
    assert sorted(files) == sorted(p.name for p in out.glob("*.png"))
    assert all(s in (out / "index.md").read_text() for s in files)
    _chromium.check_layout(page, min_figures=9)
    # the report's index prefers trials_html/ and falls back to the page harness show wrote
    pages = find_trial_pages(run, ids)
    assert pages[ids[1]] == f"{TRIAL_PAGES_DIR}/{trial_page_name(ids[1])}"
    (run / TRIAL_PAGES_DIR / trial_page_name(ids[1])).rename(run / "moved.html")
    try:
        assert find_trial_pages(run, ids)[ids[1]] == f"show/{ids[1]}/trial.html"
    finally:
        (run / "moved.html").rename(run / TRIAL_PAGES_DIR / trial_page_name(ids[1]))


def test_trials_selection_words_and_unknown_ids(tiny, capsys):
    from harness.commands.report import select_trials

    run, ids, _ = tiny
    records = load_run(run).records
    assert select_trials(records, ["all"], []) == ids
    assert select_trials(records, ["none"], ids) == []
    assert select_trials(records, ["gallery", ids[0]], [ids[1]]) == [ids[1], ids[0]]
    assert len(select_trials(records, ["worst:1"], [])) == 1
    with pytest.raises(ValueError, match="closest"):
        select_trials(records, [ids[0][:-1] + "9"], [])
    assert main(["report", str(run), "--gallery", "0", "--trials", "worst:x"]) == 2
    assert "worst:N" in capsys.readouterr().err


# -- one colour language ------------------------------------------------------------------------------------
def test_describe_uses_the_reports_palette_object():
    from harness.commands import describe

    assert describe.CLASS_COLOURS is colours.CLASS_COLOURS
    assert set(colours.HK_COLOURS) == {"NONE", "PLANAR", "CYLINDRICAL", "ELLIPTIC", "HYPERBOLIC"}
    # the H-K classes take the colour of the class they lead to
    assert colours.HK_COLOURS["PLANAR"] == colours.CLASS_COLOURS["PLAN"]
    assert colours.HK_COLOURS["CYLINDRICAL"] == colours.CLASS_COLOURS["CYL"]


def _band_colours(png: bytes) -> np.ndarray:
    """The distinct colours (0-255) of the legend band of a picture (its bottom LEGEND_IN inches)."""
    from io import BytesIO

    from matplotlib.image import imread

    img = (imread(BytesIO(png))[..., :3] * 255).round().astype(int)
    band = img[-int(figures.LEGEND_IN * figures.DPI):]
    return np.unique(band.reshape(-1, 3), axis=0)


def _has(colours_found: np.ndarray, hex_colour: str) -> bool:
    want = np.round(colours.rgb(hex_colour) * 255).astype(int)
    return bool(np.any(np.all(np.abs(colours_found - want) <= 1, axis=1)))


@pytest.mark.skipif(not BOX.is_file(), reason=f"real scan {BOX} not available")
def test_describe_pictures_carry_their_legend_and_region_numbers(tmp_path):
    from matplotlib.image import imread

    from harness.commands.describe import NUMBERED_MIN_PIXELS
    from recognition.describe import describe
    from sensors.readers import load_scan

    out = tmp_path / "out"
    assert main(["describe", str(BOX), "--out", str(out)]) == 0
    band = _band_colours((out / "classes.png").read_bytes())
    assert all(_has(band, c) for c in colours.CLASS_COLOURS.values()), "classes.png: no legend in the report's colours"
    table = (out / "table.md").read_text()
    head = next(line for line in table.splitlines() if line.startswith("| region |"))
    for c in colours.CLASSES:
        assert f"P({c})" in head
    # regions.png numbers its regions with table.md's ids, on the region: a white box at each region's centre
    desc = describe(load_scan(BOX).scan)
    centres = figures.patch_centres(desc.labels, NUMBERED_MIN_PIXELS)
    ids = {int(line.split("|")[1]) for line in table.splitlines() if re.match(r"\| \d+ \|", line)}
    assert centres and {i for _, _, i in centres} <= ids
    img = imread(out / "regions.png")[..., :3]
    h, w = desc.labels.shape
    fig_h = img.shape[0] / figures.DPI
    scale = (figures.WIDTH_IN - 2 * figures.PAD_IN) / w
    for x, y, _ in centres:
        px = int(round((figures.PAD_IN + (x + 0.5) * scale) * figures.DPI))
        py = int(round((fig_h - figures.LEGEND_IN - (h - y - 0.5) * scale) * figures.DPI))
        patch = img[py - 3:py + 4, px - 12:px + 13]
        assert np.mean(np.all(patch > 0.8, axis=-1)) > 0.3, f"no number box at region centre ({x}, {y})"


def test_region_colours_follow_the_truth_surface_they_cover():
    truth = np.full((20, 30), -1)
    truth[:, :10], truth[:, 10:20], truth[:, 20:] = 0, 1, 2
    labels = np.full((20, 30), -1)
    labels[:, :10] = 0  # exactly surface 0
    labels[:, 10:16], labels[:, 16:20] = 1, 2  # surface 1 split in two: the larger piece takes its colour
    labels[:, 20:] = 3
    labels[:5, :] = 4  # across every surface, dominated by none
    palette = colours.region_colours(3)
    got = colours.matched_region_colours(labels, truth)
    assert np.allclose(got[0], palette[0]) and np.allclose(got[1], palette[1]) and np.allclose(got[3], palette[2])
    assert not np.allclose(got[2], palette[1]) and np.allclose(got[2], colours.shade_variant(palette[1], 1))
    assert not any(np.allclose(got[4], c) for c in palette)
    with pytest.raises(ValueError, match="expected truth ids"):
        colours.matched_region_colours(labels, truth[:, :5])


def test_every_picture_has_a_legend_band_of_the_same_height():
    shape = (48, 64)
    hk = np.arange(48 * 64).reshape(shape) % 5
    pictures = {
        "hk": figures.hk_picture(hk, np.eye(*shape)),
        "range": figures.range_picture(np.linspace(1, 2, 48 * 64).reshape(shape)),
        "regions": figures.region_picture(np.arange(48 * 64).reshape(shape) // 700),
        "classes": figures.class_overlay_picture(np.full(shape, 0.5), hk - 1),
    }
    sizes = {k: _png_size(v) for k, v in pictures.items()}
    assert len(set(sizes.values())) == 1, sizes  # a row of pictures of one scan lines up
    band = _band_colours(pictures["hk"])
    assert all(_has(band, colours.HK_COLOURS[k]) for k in ("PLANAR", "CYLINDRICAL", "ELLIPTIC", "HYPERBOLIC"))


def _png_size(png: bytes) -> tuple[int, int]:
    return int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
