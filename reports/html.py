"""A :class:`reports.document.Document` as one self-contained HTML page: inline CSS, figures as base64 PNG (or,
for pages that may reference files, a PNG beside the page), no fonts or links to anything outside the file
(it opens offline). The only script is a few inline lines that sort a table by the column whose header is
clicked, written only into pages that have a sortable table.

Layout at a 1400 px window: the text column is 1344 px wide; figures stand two to a row at their natural
660 px (a wide one, ``span=2``, takes the row), scaled down on narrower screens; tables wrap their text and
never scroll sideways.
"""

from __future__ import annotations

import base64
import re
from html import escape

from reports.document import Block, Cell, Code, Document, Grid, Image, Links, Note, Para, Section, Table

CSS = """
:root { --fg: #1f2937; --muted: #6b7280; --line: #e5e7eb; --head: #f3f4f6; --accent: #0b5fa5; }
* { box-sizing: border-box; }
body { margin: 0; color: var(--fg); background: #fff; font: 15px/1.5 system-ui, -apple-system, "Segoe UI", Roboto,
       "Helvetica Neue", Arial, sans-serif; }
main { max-width: 1400px; margin: 0 auto; padding: 24px 28px 64px; }
h1 { font-size: 1.7em; margin: 0 0 4px; }
h2 { font-size: 1.3em; margin: 36px 0 10px; padding-bottom: 4px; border-bottom: 2px solid var(--line); }
h3 { font-size: 1.08em; margin: 22px 0 8px; }
a { color: var(--accent); }
p { max-width: 1100px; }
.subtitle { color: var(--muted); margin: 0 0 18px; }
.links { margin: 0 0 14px; }
.links a { margin-right: 14px; }
nav.toc { background: #f9fafb; border: 1px solid var(--line); border-radius: 6px; padding: 10px 18px; }
nav.toc ol { margin: 4px 0; padding-left: 22px; }
nav.toc li { margin: 1px 0; }
table { border-collapse: collapse; margin: 8px 0 14px; font-size: 0.9em; font-variant-numeric: tabular-nums;
        max-width: 100%; }
caption { caption-side: top; text-align: left; color: var(--muted); font-size: 0.92em; padding: 0 0 4px; }
th, td { border-bottom: 1px solid var(--line); padding: 4px 9px; text-align: left; vertical-align: top;
         overflow-wrap: normal; }
th { background: var(--head); font-weight: 600; }
tbody tr:nth-child(even) { background: #fafafa; }
td.num { text-align: right; white-space: nowrap; }
td.good { color: #15803d; font-weight: 600; }
td.bad { color: #b91c1c; font-weight: 600; }
td.num.good, td.num.bad { white-space: nowrap; }
td.na, td.missing { color: var(--muted); font-style: italic; }
td.id, .nw { white-space: nowrap; }
.swatch { display: inline-block; width: 0.8em; height: 0.8em; border-radius: 2px; margin-right: 5px;
          vertical-align: -1px; }
.tablewrap { max-width: 100%; }
table.sortable th { cursor: pointer; user-select: none; }
table.sortable th::after { content: " \\2195"; color: #9ca3af; font-weight: 400; }
table.sortable th[aria-sort="ascending"]::after { content: " \\2191"; color: var(--fg); }
table.sortable th[aria-sort="descending"]::after { content: " \\2193"; color: var(--fg); }
.note { border-left: 4px solid #93c5fd; background: #eff6ff; padding: 6px 12px; margin: 8px 0; }
.note.missing { border-color: #d1d5db; background: #f9fafb; color: #4b5563; }
.note.warn { border-color: #f59e0b; background: #fffbeb; }
.note.fail { border-color: #dc2626; background: #fef2f2; color: #7f1d1d; font-weight: 600; }
.note.pass { border-color: #16a34a; background: #f0fdf4; color: #14532d; font-weight: 600; }
pre { background: #111827; color: #f9fafb; padding: 10px 14px; border-radius: 6px; overflow-x: auto;
      font: 13px/1.45 ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; white-space: pre-wrap;
      overflow-wrap: anywhere; }
code { font: 0.92em ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; }
figure { margin: 0; min-width: 0; }
figure img { display: block; width: 100%; height: auto; border: 1px solid var(--line); border-radius: 4px; }
figcaption { color: var(--muted); font-size: 0.88em; margin-top: 3px; }
.figs { display: grid; grid-template-columns: repeat(2, minmax(0, 1fr)); gap: 14px 24px; align-items: start;
        margin: 10px 0 18px; }
.figs figure.span2 { grid-column: 1 / -1; }
@media (max-width: 900px) { .figs { grid-template-columns: minmax(0, 1fr); } }
footer { color: var(--muted); font-size: 0.85em; margin-top: 48px; border-top: 1px solid var(--line);
         padding-top: 8px; }
"""

#: Sorts a ``table.sortable`` by the clicked column: numbers (the cell's ``data-sort`` or its leading number)
#: before text, text alphabetically; a second click reverses. Inline, so the page still opens offline.
SORT_SCRIPT = """
document.querySelectorAll("table.sortable").forEach(function (table) {
  var heads = table.tHead.rows[0].cells;
  Array.prototype.forEach.call(heads, function (th, col) {
    th.title = "sort by this column";
    th.addEventListener("click", function () {
      var up = th.getAttribute("aria-sort") !== "ascending";
      Array.prototype.forEach.call(heads, function (h) { h.removeAttribute("aria-sort"); });
      th.setAttribute("aria-sort", up ? "ascending" : "descending");
      var key = function (row) {
        var cell = row.cells[col], text = cell.getAttribute("data-sort") || cell.textContent.trim();
        var x = parseFloat(text);
        return isNaN(x) ? [1, text.toLowerCase()] : [0, x];
      };
      var body = table.tBodies[0];
      var rows = Array.prototype.slice.call(body.rows).map(function (r, i) { return [key(r), i, r]; });
      rows.sort(function (a, b) {
        if (a[0][0] !== b[0][0]) { return a[0][0] - b[0][0]; }
        var c = a[0][1] < b[0][1] ? -1 : a[0][1] > b[0][1] ? 1 : 0;
        return (up ? c : -c) || a[1] - b[1];
      });
      rows.forEach(function (r) { body.appendChild(r[2]); });
    });
  });
});
"""

NUMERIC = re.compile(r"^[-+]?(\d[\d,]*\.?\d*|\.\d+)([eE][-+]?\d+)?\s*(%|s|ms|mm|deg)?$")


def render_html(doc: Document) -> str:
    """The whole page."""
    toc = _toc(doc.sections)
    body = "\n".join(_section(s, 2) for s in doc.sections)
    header = "\n".join(block_html(b) for b in doc.header)
    script = f"<script>{SORT_SCRIPT}</script>\n" if 'class="sortable"' in body else ""
    return (
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
        "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n"
        f"<title>{escape(doc.title)}</title>\n<style>{CSS}</style>\n</head>\n<body>\n<main>\n"
        f"<h1>{escape(doc.title)}</h1>\n<p class=\"subtitle\">{escape(doc.subtitle)}</p>\n"
        f"{header}\n{toc}\n{body}\n"
        f"<footer>{escape(doc.footer)}</footer>\n"
        f"</main>\n{script}</body>\n</html>\n"
    )


def _toc(sections: list[Section]) -> str:
    def items(secs: list[Section]) -> str:
        out = []
        for s in secs:
            sub = f"<ol>{items(s.subsections)}</ol>" if s.subsections else ""
            out.append(f"<li><a href=\"#{escape(s.id)}\">{escape(s.title)}</a>{sub}</li>")
        return "".join(out)

    return f"<nav class=\"toc\" id=\"contents\"><strong>Contents</strong><ol>{items(sections)}</ol></nav>"


def _section(s: Section, level: int) -> str:
    h = min(level, 6)
    parts = [f"<section id=\"{escape(s.id)}\">", f"<h{h}>{escape(s.title)}</h{h}>"]
    parts += _blocks(s.blocks)
    parts += [_section(sub, level + 1) for sub in s.subsections]
    parts.append("</section>")
    return "\n".join(parts)


def _blocks(blocks: list[Block]) -> list[str]:
    """The blocks of a section; consecutive figures share one two-column grid."""
    out: list[str] = []
    run: list[Image] = []
    for b in [*blocks, None]:
        if isinstance(b, Image):
            run.append(b)
            continue
        if run:
            out.append(_figs(run))
            run = []
        if b is not None:
            out.append(block_html(b))
    return out


def block_html(b: Block) -> str:
    """One block as HTML (all text escaped)."""
    if isinstance(b, Para):
        return f"<p>{escape(b.text)}</p>"
    if isinstance(b, Note):
        return f"<div class=\"note {escape(b.kind)}\">{escape(b.text)}</div>"
    if isinstance(b, Code):
        return f"<pre>{escape(b.text)}</pre>"
    if isinstance(b, Table):
        return _table(b)
    if isinstance(b, Image):
        return _figs([b])
    if isinstance(b, Grid):
        return _figs(list(b.images))
    if isinstance(b, Links):
        links = " ".join(f"<a href=\"{escape(href)}\">{escape(text)}</a>" for text, href in b.links)
        return f"<p class=\"links\">{escape(b.prefix)}{' ' if b.prefix else ''}{links}</p>"
    raise TypeError(f"not a report block: {type(b).__name__}")


def _figs(images: list[Image]) -> str:
    return "<div class=\"figs\">" + "".join(_image(i) for i in images) + "</div>"


def _image(i: Image) -> str:
    src = escape(i.src) if i.src else "data:image/png;base64," + base64.b64encode(i.png).decode("ascii")
    alt = i.alt or i.caption
    cls = " class=\"span2\"" if i.span > 1 else ""
    return (f"<figure{cls}><img src=\"{src}\" alt=\"{escape(alt)}\" style=\"max-width:{int(i.width_px)}px\">"
            f"<figcaption>{escape(i.caption)}</figcaption></figure>")


def _cell(c: Cell | str) -> str:
    # a plain string that looks numeric is right-aligned; a Cell says its own style
    cell = c if isinstance(c, Cell) else Cell(str(c), "num" if NUMERIC.match(str(c).strip()) else "")
    style = cell.style
    swatch = f"<span class=\"swatch\" style=\"background:{escape(cell.colour)}\"></span>" if cell.colour else ""
    cls = f" class=\"{escape(style)}\"" if style else ""
    sort = f" data-sort=\"{escape(cell.sort)}\"" if cell.sort else ""
    text = escape(cell.text)
    if cell.href:
        text = f"<a href=\"{escape(cell.href)}\">{text}</a>"
    if swatch:
        text = f"<span class=\"nw\">{swatch}{text}</span>"  # a swatch stays beside its word
    return f"<td{cls}{sort}>{text}</td>"


def _table(t: Table) -> str:
    tid = f" id=\"{escape(t.id)}\"" if t.id else ""
    cls = " class=\"sortable\"" if t.sortable else ""
    cap = f"<caption>{escape(t.caption)}</caption>" if t.caption else ""
    head = "".join(f"<th>{escape(h)}</th>" for h in t.header)
    rows = "".join("<tr>" + "".join(_cell(c) for c in row) + "</tr>" for row in t.rows)
    return (f"<div class=\"tablewrap\"><table{tid}{cls}>{cap}<thead><tr>{head}</tr></thead>"
            f"<tbody>{rows}</tbody></table></div>")
