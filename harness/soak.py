"""Moved to :mod:`harness.bench.soak` (``python -m harness.bench.soak``); this alias keeps
``python -m harness.soak`` working."""

from harness.bench.soak import main

if __name__ == "__main__":
    raise SystemExit(main())
