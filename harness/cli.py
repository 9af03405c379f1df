"""The ``harness`` command line: ``harness <command> [options]``.

Each module in :mod:`harness.commands` listed in :data:`COMMANDS` provides ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args) -> int``. Configuration errors, a results directory locked by
another run or holding another run become one line on stderr and exit code 2 (no traceback); an I/O
error such as a full disk exits 1 with one line; Ctrl-C exits 130.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

from scenes.config import ConfigError

DESCRIPTION = ("Simulate range scans of a partially correct factory model, run the recognition core of Fillatreau "
               "& Fisher on them and score every stage against the truth.")
COMMANDS = ("scene", "sense", "bench", "show", "compare", "report", "results", "describe")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="harness", description=DESCRIPTION,
                                     epilog="Run 'harness COMMAND --help' for a command's options.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"harness.commands.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"harness.commands.{name}":
                continue  # command not built yet
            raise
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:
        print("harness: interrupted", file=sys.stderr)
        return 130
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    from harness.store import RunLockedError

    try:
        return int(args._run(args) or 0)
    except (ConfigError, ValueError, FileNotFoundError, FileExistsError, RunLockedError) as exc:
        print(f"harness: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # e.g. a full disk: finished trials are kept, --resume completes the run
        print(f"harness: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("harness: interrupted", file=sys.stderr)
        return 130


def entry() -> None:
    """The program's entry point: run :func:`main`, then exit with its code. A Ctrl-C that arrives once
    the work is done (while the interpreter tears down its threads and modules) has nothing left to
    interrupt: it is ignored, so the exit code stays the command's own."""
    code = main()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sys.exit(code)


if __name__ == "__main__":
    entry()
