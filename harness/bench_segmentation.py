"""Moved to :mod:`harness.bench.segmentation` (``python -m harness.bench.segmentation``); this alias keeps
``python -m harness.bench_segmentation`` working."""

from harness.bench.segmentation import main

if __name__ == "__main__":
    raise SystemExit(main())
