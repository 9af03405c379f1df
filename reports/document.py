"""The report as a small document tree (sections of paragraphs, notes, tables, images), rendered to HTML by
:mod:`reports.html` and to Markdown by :mod:`reports.markdown`.

All text is plain text: the renderers escape it. Nothing here knows about HTML or Markdown.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Cell:
    """A table cell: its text and a style hint (``num``, ``good``, ``bad``, ``na``, ``missing`` or ``""``)."""

    text: str
    style: str = ""
    colour: str = ""  # an optional swatch colour (#rrggbb) shown before the text in HTML


@dataclass(frozen=True)
class Table:
    """A table; ``rows`` hold :class:`Cell` or plain strings (strings that look numeric are right-aligned)."""

    header: tuple[str, ...]
    rows: tuple[tuple[Cell | str, ...], ...]
    caption: str = ""
    id: str = ""


@dataclass(frozen=True)
class Para:
    text: str


@dataclass(frozen=True)
class Note:
    """A highlighted line: ``kind`` is ``missing`` (stage not built yet), ``info``, ``warn``, ``pass`` or ``fail``."""

    text: str
    kind: str = "info"


@dataclass(frozen=True)
class Code:
    """A block of monospaced text (e.g. the command that reproduces the run)."""

    text: str


@dataclass(frozen=True)
class Image:
    """A PNG figure with its caption; ``alt`` is the text shown without images (and in the Markdown)."""

    png: bytes
    caption: str
    alt: str = ""
    width_px: int = 640


@dataclass(frozen=True)
class Grid:
    """Images side by side (wrapping on narrow screens)."""

    images: tuple[Image, ...]


Block = Para | Note | Code | Table | Image | Grid


@dataclass
class Section:
    """A titled section; ``id`` is its anchor in the table of contents."""

    id: str
    title: str
    blocks: list[Block] = field(default_factory=list)
    subsections: list[Section] = field(default_factory=list)


@dataclass
class Document:
    title: str
    subtitle: str
    sections: list[Section]


@dataclass(frozen=True)
class GalleryTrial:
    """One trial of the gallery: why it was chosen, its pictures and notes (e.g. a stage not built yet).

    Built by the caller of :func:`reports.render.render_report` (``harness report`` re-runs the trial to draw
    the pictures, DESIGN 10.14) and passed in, so that ``reports`` never runs the simulator itself.
    """

    trial_id: str
    group: str
    why: str
    panels: tuple[Image, ...] = ()
    notes: tuple[str, ...] = ()
