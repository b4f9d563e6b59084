"""Wire-layer micro-benchmark: median µs per call (bar: <= 10 µs for the first two rows).

    .venv/bin/python bench/wire.py

Each row times batches of calls and prints the median over batches of the mean µs per call.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

import numpy as np

from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario
from pd_service.service.health import inspect_packed
from pd_service.wire import (
    Command,
    Measurement,
    Prediction,
    SessionSpec,
    decode,
    encode,
)
from pd_service.wire.convert import (
    PredictionEncoder,
    check_measurement,
    measurement_step,
    prediction_from,
)

BATCH = 1000
REPEATS = 41


def median_us(fn: Callable[[], object]) -> float:
    for _ in range(BATCH):  # warm up
        fn()
    means = []
    for _ in range(REPEATS):
        t0 = time.perf_counter_ns()
        for _ in range(BATCH):
            fn()
        means.append((time.perf_counter_ns() - t0) / BATCH / 1000.0)
    return statistics.median(means)


def main() -> None:
    rng = np.random.default_rng(0)
    spec = paper_scenario().spec("s1", 0, max_delay=RANGER_DELAY)
    meas = Measurement(session="s1", sensor="camera", seq=12345, step=100_000,
                       z=rng.normal(size=2))
    meas_r = Measurement(session="s1", sensor="camera", seq=12345, step=100_000,
                         z=rng.normal(size=2), R=0.3 * np.eye(2))
    cmd = Command(session="s1", seq=77, step=100_010, u=np.array([0.5]))
    L = rng.normal(size=(4, 4))
    P = 0.5 * (L @ L.T + (L @ L.T).T)
    counters = {"accepted": 1000, "late": 3, "future": 0, "duplicate": 1,
                "commands_accepted": 500, "commands_late": 0, "commands_future": 0,
                "commands_duplicate": 0}
    pred = Prediction(session="s1", seq=99, step=100_010, t_ns=5_000_500_000_000,
                      x=rng.normal(size=4), P=P, newest_step=99_990,
                      made_ns=1_700_000_000_123_456_789, counters=counters)
    est = type("Est", (), {"step": 100_010, "x": pred.x, "P": pred.P, "newest_step": 99_990})()

    b_meas, b_meas_r, b_cmd, b_pred = encode(meas), encode(meas_r), encode(cmd), encode(pred)
    b_spec = encode(spec)

    def daemon_in() -> None:
        m = decode(b_meas, Measurement)
        check_measurement(m, spec)
        measurement_step(m, spec)

    def daemon_out() -> None:
        encode(prediction_from(est, spec, "s1", 99, 1_700_000_000_123_456_789, counters))

    encoder = PredictionEncoder(spec, "s1")

    def daemon_fast_out() -> None:
        _, xb, pb = inspect_packed(est.x, est.P)
        encoder.encode_packed(est, xb, pb, 99, 1_700_000_000_123_456_789, counters)

    rows = [
        ("decode+validate Measurement (m=2)       [bar 10]", lambda: decode(b_meas, Measurement)),
        ("encode Prediction (n=4)                 [bar 10]", lambda: encode(pred)),
        ("decode+validate Measurement with R (2x2)", lambda: decode(b_meas_r, Measurement)),
        ("decode+validate Command (r=1)", lambda: decode(b_cmd, Command)),
        ("decode+validate Prediction (n=4, PSD)", lambda: decode(b_pred, Prediction)),
        ("daemon in: decode + check + step", daemon_in),
        ("daemon out: prediction_from + encode", daemon_out),
        ("daemon out: inspect_packed + encode_packed", daemon_fast_out),
        ("decode+validate SessionSpec (paper)", lambda: decode(b_spec, SessionSpec)),
    ]
    print(f"wire benchmark: median of {REPEATS} batches x {BATCH} calls, µs per call")
    print(f"{'operation':50s} {'µs':>8s}   bytes")
    sizes = [len(b_meas), len(b_pred), len(b_meas_r), len(b_cmd), len(b_pred), len(b_meas),
             len(b_pred), len(b_pred), len(b_spec)]
    for (name, fn), size in zip(rows, sizes, strict=True):
        print(f"{name:50s} {median_us(fn):8.2f}   {size}")


if __name__ == "__main__":
    main()
