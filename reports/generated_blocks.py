"""Generated blocks of the project's Markdown files: the lines between a begin and an end marker, written by a
command from a committed summary or JSON (never typed) and held to it by a test. One home for the replacing and
the reading; each generator names its own markers."""

from __future__ import annotations

__all__ = ["generated_block", "replace_block"]


def replace_block(text: str, block: str, begin: str, end: str, source: str = "<text>") -> str:
    """``text`` with what lies between the marker lines ``begin`` and ``end`` replaced by ``block``.

    Raises
    ------
    ValueError
        Naming ``source`` when either marker is missing.
    """
    if begin not in text or end not in text:
        raise ValueError(f"{source}: no generated block (the lines {begin!r} and {end!r})")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{block}{end}{tail}"


def generated_block(text: str, begin: str, end: str) -> str:
    """What lies between the markers of ``text`` (the part :func:`replace_block` writes)."""
    return text.split(begin, 1)[1].split(end, 1)[0].removeprefix("\n")
