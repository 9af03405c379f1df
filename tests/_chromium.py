"""Pages as a person sees them: headless Chromium at 1400 px, a screenshot, and what the page measures in the
browser (its width, its links, its figures' captions, which tables or figures overflow, a click on a sortable
table's header: the trial index where the page has one, else its first sortable table).

Shared by the report tests (``tests/test_reports.py``) and the trial page tests (``tests/reports/``). Chromium is
Debian's ``chromium`` (``scripts/system-deps.sh --browser``); without it the tests that need it are skipped.
"""

from __future__ import annotations

import html
import json
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

WIDTH = 1400
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars")

#: Run in the page after it loaded: what the tests check, written into the page as JSON (``<pre id=probe>``).
PROBE = """
<script>
window.addEventListener("load", function () {
  var doc = document.documentElement, out = {};
  out.scrollWidth = doc.scrollWidth;
  out.clientWidth = doc.clientWidth;
  out.hrefs = Array.prototype.map.call(document.querySelectorAll("a[href]"), function (a) {
    return a.getAttribute("href"); });
  out.figures = document.querySelectorAll("figure").length;
  out.uncaptioned = Array.prototype.filter.call(document.querySelectorAll("figure"), function (f) {
    var c = f.querySelector("figcaption"); return !c || !c.textContent.trim(); }).length;
  out.images = Array.prototype.map.call(document.querySelectorAll("figure img"), function (i) {
    return [i.naturalWidth, Math.round(i.getBoundingClientRect().width)]; });
  out.overflowing = Array.prototype.filter.call(document.querySelectorAll(".tablewrap, table, pre, figure"),
    function (e) { return e.scrollWidth > e.clientWidth + 1 || e.getBoundingClientRect().right > doc.clientWidth + 1; }
  ).map(function (e) { return e.tagName + "#" + (e.id || e.className || ""); });
  var table = document.querySelector("table#trial-index") || document.querySelector("table.sortable");
  if (table) {
    var heads = table.tHead.rows[0].cells, firsts = [];
    for (var k = 0; k < heads.length; k++) {
      if (/score/.test(heads[k].textContent)) {
        heads[k].click(); firsts.push(table.tBodies[0].rows[0].cells[0].textContent);
        heads[k].click(); firsts.push(table.tBodies[0].rows[0].cells[0].textContent);
      }
    }
    out.sorted_firsts = firsts;
  }
  var pre = document.createElement("pre"); pre.id = "probe"; pre.textContent = JSON.stringify(out);
  document.body.appendChild(pre);
});
</script>
"""


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("headless Chromium is missing: install Debian's 'chromium' (apt-get install -y chromium, "
                    "or scripts/system-deps.sh --browser) to run the report screenshot tests")
    return exe


def screenshot(html_path: Path, out: Path, height: int = 2400) -> Path:
    """A screenshot of the page at :data:`WIDTH` px (a fresh profile), written to ``out``."""
    exe = chromium()
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={WIDTH},{height}",
                        f"--screenshot={out}", html_path.resolve().as_uri()], check=True, capture_output=True,
                       timeout=120)
    return out


def dump_dom(html_path: Path) -> str:
    """The page's DOM as Chromium built it (scripts run), at :data:`WIDTH` px."""
    exe = chromium()
    with tempfile.TemporaryDirectory() as profile:
        return subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={WIDTH},1200",
                               "--virtual-time-budget=15000", "--dump-dom", html_path.resolve().as_uri()],
                              check=True, capture_output=True, text=True, timeout=180).stdout


def measure(html_path: Path) -> dict:
    """What :data:`PROBE` measures in the page, read from a copy of it beside the original (so its relative links
    resolve the same)."""
    probe = html_path.with_name(f".probe-{html_path.name}")
    text = html_path.read_text(encoding="utf-8")
    probe.write_text(text.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    try:
        dom = dump_dom(probe)
    finally:
        probe.unlink(missing_ok=True)
    found = re.search(r'<pre id="probe">(.*?)</pre>', dom, re.S)
    assert found, "the probe did not run in the page"
    return json.loads(html.unescape(found.group(1)))


def local_targets(html_path: Path, hrefs: list[str]) -> list[Path]:
    """The local files the page's links point to (anchors within the page are left out)."""
    out = []
    for href in hrefs:
        url = urlparse(href)
        assert url.scheme in ("", "file"), f"a link out of the page's folder: {href}"
        if not url.path:
            continue  # "#section"
        out.append((html_path.parent / unquote(url.path)).resolve())
    return out


def check_layout(html_path: Path, min_figures: int = 1) -> dict:
    """The checks every page must pass at 1400 px: no horizontal overflow (of the page, a table, a figure or a
    code block), every figure captioned, every link to a local file resolving. Returns the measurements."""
    m = measure(html_path)
    assert m["scrollWidth"] <= WIDTH, f"the page is {m['scrollWidth']} px wide at {WIDTH} px"
    assert not m["overflowing"], f"overflowing at {WIDTH} px: {m['overflowing']}"
    assert m["figures"] >= min_figures and m["uncaptioned"] == 0, m
    missing = [str(p) for p in local_targets(html_path, m["hrefs"]) if not p.is_file()]
    assert not missing, f"links to files that do not exist: {missing}"
    return m
