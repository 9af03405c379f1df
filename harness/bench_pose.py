"""Moved to :mod:`harness.bench.pose` (``python -m harness.bench.pose``); this alias keeps
``python -m harness.bench_pose`` working."""

from harness.bench.pose import main

if __name__ == "__main__":
    raise SystemExit(main())
