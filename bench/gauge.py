#!/usr/bin/env python3
"""Machine gauge: CPU time of a fixed workload that does not depend on pd_service, to tell
how fast the machine was when a benchmark ran.

A shared machine's speed changes between hours, and a figure measured in a fast hour does
not reproduce in a slow one (docs/performance.md, "How to read the figures"). The benchmarks
print this gauge beside their figures: two figures compare only with their gauges.

The workload is the kind of work the daemon does per message: msgpack packing and unpacking
of small maps, dict and list operations, small numpy products. Printed: the median of 5
repetitions in ms of process CPU time (lower is faster).

Usage: python bench/gauge.py
"""

from __future__ import annotations

import statistics
import time

import msgpack
import numpy as np

_MSG = {"v": 1, "session": "s00001", "sensor": "ranger", "seq": 12, "step": 340,
        "z": {"shape": [1], "data": [1.25]}}


def _work() -> float:
    pack, unpack = msgpack.Packer(use_bin_type=True).pack, msgpack.unpackb
    a, x = np.eye(4) * 0.5, np.ones(4)
    d: dict[str, int] = {}
    acc = 0.0
    for i in range(4000):
        m = unpack(pack(_MSG))
        d[m["session"] + str(i % 64)] = m["step"]
        x = a @ x + 1.0
        acc += float(x[0]) + len(d)
    return acc


def gauge_ms(repeat: int = 5) -> float:
    """Median CPU time (ms) of the fixed workload."""
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        _work()
        times.append(1e3 * (time.process_time() - t0))
    return round(statistics.median(times), 2)


if __name__ == "__main__":
    print(f"machine gauge: {gauge_ms():.2f} ms of CPU (fixed workload; lower is faster)")
