"""Moved to :mod:`harness.bench.peers` (``python -m harness.bench.peers``); this alias keeps
``python -m harness.bench_peers`` working."""

from harness.bench.peers import main

if __name__ == "__main__":
    raise SystemExit(main())
