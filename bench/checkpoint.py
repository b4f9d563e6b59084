"""Cost of checkpoints and replicas per session: encoded SessionState size, CPU to export +
encode it, and the resulting bytes/s at one state per ``--interval-s`` per session.

Cases: the paper's scenario (n=4, 2 sensors, max_delay 12) and a linear n=12 system with
3 sensors (6, 3, 3 rows) sampled every step, nu=6, max_delay 50. The window is full (every
sample of the last max_delay steps present, a command every step).

    python bench/checkpoint.py [--reps 200] [--interval-s 1.0]

Prints a table, then one JSON line. CPU is process time (time.process_time) per state,
averaged over ``--reps``, with the daemon's encoder (``checkpoint.encode_state``) and, side
by side, through the validated models (``encode(to_message(...))``: the same bytes); the
disk write is not included (it depends on the disk; checkpoints are not fsynced).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from pd_service.backends import build
from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.scenarios.paper import paper_scenario
from pd_service.service.handover.checkpoint import encode_state, to_message
from pd_service.wire import encode, spec_fingerprint


def paper_case():
    spec = paper_scenario("journal").spec("bench", 0, lead=10, max_delay=12)
    est = build(spec).est
    rng = np.random.default_rng(0)
    for k in range(200):
        est.add_command(k + spec.lead, rng.standard_normal(1), now=k)
        for s in spec.sensors:
            est.add_measurement(s.name, k, rng.standard_normal(s.m), now=k)
    return "paper (n=4, max_delay 12)", est, spec_fingerprint(spec)


def big_case():
    rng = np.random.default_rng(1)
    n, nu = 12, 6
    A = np.eye(n) + 0.01 * rng.standard_normal((n, n))
    model = LinearModel(A=A, B=rng.standard_normal((n, nu)), Q=0.01 * np.eye(n))
    sensors = [Sensor(name=f"s{i}", H=rng.standard_normal((m, n)), R=np.eye(m))
               for i, m in enumerate((6, 3, 3))]
    est = ObserverPredictor(model, sensors, np.zeros(n), np.eye(n), lead=10, max_delay=50)
    for k in range(300):
        est.add_command(k + 10, rng.standard_normal(nu), now=k)
        for s in sensors:
            est.add_measurement(s.name, k, rng.standard_normal(s.m), now=k)
    return "n=12, nu=6, 3 sensors, max_delay 50", est, "0" * 64


def measure(est, fp, reps):
    """(bytes, CPU s per state with the daemon's encoder, CPU s with the validated models)."""
    est.predict(est.now)
    kw = dict(session="bench", instance="bench", fingerprint=fp, made_ns=0)
    t0 = time.process_time()
    for _ in range(reps):
        data = encode_state(est.export_state(), **kw)
    fast = (time.process_time() - t0) / reps
    t0 = time.process_time()
    for _ in range(reps):
        slow = encode(to_message(est.export_state(), **kw))
    models = (time.process_time() - t0) / reps
    assert slow == data  # the same bytes either way
    return len(data), fast, models


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--interval-s", type=float, default=1.0)
    args = ap.parse_args()
    rows = []
    for name, est, fp in (paper_case(), big_case()):
        size, cpu, models = measure(est, fp, args.reps)
        rows.append({"case": name, "bytes": size, "cpu_us": cpu * 1e6,
                     "cpu_us_models": models * 1e6,
                     "bytes_per_s": size / args.interval_s,
                     "cpu_fraction": cpu / args.interval_s})
    print(f"{'case':40s} {'bytes/state':>11s} {'CPU us/state':>12s} {'via models':>10s} "
          f"{'bytes/s':>9s} {'CPU %/session':>13s}   (one state per {args.interval_s:g} s; "
          "x2 bytes with a replica)")
    for r in rows:
        print(f"{r['case']:40s} {r['bytes']:11d} {r['cpu_us']:12.1f} "
              f"{r['cpu_us_models']:10.1f} {r['bytes_per_s']:9.0f} "
              f"{100 * r['cpu_fraction']:13.4f}")
    print(json.dumps({"interval_s": args.interval_s, "cases": rows}))


if __name__ == "__main__":
    main()
