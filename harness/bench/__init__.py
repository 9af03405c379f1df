"""The benchmarks, one module each, run as ``python -m harness.bench.<name>`` (``--help`` for the options):

- :mod:`harness.bench.sensors`: ray casting and noise of the simulated sensors (time, memory);
- :mod:`harness.bench.segmentation`: the H-K segmentation alone (time per frame, Hoover correct detection);
- :mod:`harness.bench.classification`: both classifiers on synthetic patches (accuracy, radius bias, time);
- :mod:`harness.bench.pose`: localisation (matching, pose, verification, ICP) on scanned viewpoints;
- :mod:`harness.bench.peers`: the peer methods beside the core, stage by stage;
- :mod:`harness.bench.soak`: the runner under many small trials on a Dask cluster (memory, leaks, throughput).

The benchmark suites themselves run through ``harness bench``.
"""
