"""``harness results SUMMARY...``: the headline tables of committed summaries, with their intervals.

Prints Markdown, or with ``--into FILE`` writes it between the results markers of that file (the README and
``docs/results.md`` hold such a block: their figures are generated, never typed).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

NAME = "results"
HELP = "write the headline tables (with intervals) of one or more summary.json files as Markdown"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("summaries", nargs="+", type=Path, metavar="SUMMARY",
                        help="a summary.json, or a run directory holding one")
    parser.add_argument("--title", action="append", default=[],
                        help="heading of each table, in order (default: the suite's name)")
    parser.add_argument("--into", type=Path, metavar="FILE",
                        help="replace the generated results block of FILE instead of printing")


def load(path: Path) -> dict:
    p = path / "summary.json" if path.is_dir() else path
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such summary")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{p}: not JSON ({exc.msg}, line {exc.lineno})") from None
    if not isinstance(data, dict) or data.get("schema") != "harness.summary/1":
        raise ValueError(f"{p}: schema: not a harness summary (expected harness.summary/1)")
    return data


def run(args: argparse.Namespace) -> int:
    from reports.results import replace_block, results_markdown

    if len(args.title) > len(args.summaries):
        raise ValueError(f"--title given {len(args.title)} times for {len(args.summaries)} summaries")
    summaries = [load(p) for p in args.summaries]
    titles = args.title + [f"`{s.get('suite')}` suite" for s in summaries[len(args.title):]]
    block = results_markdown(list(zip(titles, summaries, strict=True)))
    if args.into is None:
        print(block, end="")
        return 0
    text = args.into.read_text(encoding="utf-8")
    args.into.write_text(replace_block(text, block, str(args.into)), encoding="utf-8")
    print(f"{args.into}: results block written from {len(summaries)} summary(ies)")
    return 0
