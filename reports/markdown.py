"""A :class:`reports.document.Document` as GitHub-flavoured Markdown, for CI logs and pull-request comments.

Tables and notes are kept; figures are replaced by a one-line pointer to ``report.html`` (a CI comment
cannot embed them), so the Markdown stays short and plain.
"""

from __future__ import annotations

from reports.document import Block, Cell, Code, Document, Grid, Image, Links, Note, Para, Section, Table

NOTE_PREFIX = {"fail": "**FAIL:** ", "pass": "**PASS:** ", "warn": "**Warning:** "}


def escape_md(text: str) -> str:
    """Escape the characters that would break a table cell or start markup."""
    out = str(text).replace("\\", "\\\\").replace("|", "\\|").replace("\n", " ")
    for ch in ("*", "_", "`", "<", ">", "[", "]"):
        out = out.replace(ch, "\\" + ch)
    return out


def render_markdown(doc: Document) -> str:
    """The whole summary."""
    lines = [f"# {escape_md(doc.title)}", "", f"_{escape_md(doc.subtitle)}_", ""]
    for b in getattr(doc, "header", ()):
        lines += [block_md(b), ""]
    for s in doc.sections:
        lines += _section(s, 2)
    return "\n".join(lines).rstrip() + "\n"


def _section(s: Section, level: int) -> list[str]:
    lines = [f"{'#' * min(level, 6)} {escape_md(s.title)}", ""]
    for b in s.blocks:
        text = block_md(b)
        if text:
            lines += [text, ""]
    for sub in s.subsections:
        lines += _section(sub, level + 1)
    return lines


def block_md(b: Block) -> str:
    """One block as Markdown ("" for blocks that are only for the HTML page)."""
    if isinstance(b, Para):
        return escape_md(b.text)
    if isinstance(b, Note):
        return "> " + NOTE_PREFIX.get(b.kind, "") + escape_md(b.text)
    if isinstance(b, Code):
        fence = "````" if "```" in b.text else "```"
        return f"{fence}\n{b.text}\n{fence}"
    if isinstance(b, Table):
        if not b.markdown:
            return f"_{escape_md(b.caption or 'A table')} ({len(b.rows)} rows): see the HTML page._"
        return _table(b)
    if isinstance(b, Links):
        return escape_md(b.prefix) + (" " if b.prefix else "") + " ".join(
            f"[{escape_md(text)}]({href})" for text, href in b.links)
    if isinstance(b, Image):
        return f"_Figure (see report.html): {escape_md(b.caption)}_"
    if isinstance(b, Grid):
        return f"_{len(b.images)} pictures (see report.html)_" if b.images else ""
    raise TypeError(f"not a report block: {type(b).__name__}")


def _table(t: Table) -> str:
    def text(c: Cell | str) -> str:
        if isinstance(c, Cell) and c.href:
            return f"[{escape_md(c.text)}]({c.href})"
        return escape_md(c.text if isinstance(c, Cell) else str(c))

    lines = [f"**{escape_md(t.caption)}**", ""] if t.caption else []
    lines.append("| " + " | ".join(escape_md(h) for h in t.header) + " |")
    lines.append("|" + "|".join("---" for _ in t.header) + "|")
    lines += ["| " + " | ".join(text(c) for c in row) + " |" for row in t.rows]
    return "\n".join(lines)
