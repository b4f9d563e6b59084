#!/usr/bin/env python3
"""The stacked engine alone: N paper sessions' estimators fed the load of bench/service.py
(per step a command, a range-finder sample, a camera sample every second step), predicted
and resolved together once per step, with no service around them (no decoding, dispatch,
publication, Zenoh).

Prints the CPU per session-step of the three parts (µs, wall time of a single thread on an
otherwise quiet machine) and, last, one JSON object: what the daemon's worker spends in the
estimators themselves, to set against bench/worker.py (the whole worker).

Usage: python bench/stacked.py [--sessions 20] [--steps 400] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from pd_service import native
from pd_service.backends import build_estimator
from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario, simulate_paper
from pd_service.service.stacked import StackedObserverPredictor, resolve

WARMUP = 100


def one_run(n: int, steps: int) -> dict[str, float]:
    spec = paper_scenario().spec("s", 0, max_delay=RANGER_DELAY)
    ests = [build_estimator(spec, StackedObserverPredictor) for _ in range(n)]
    run = simulate_paper(max(steps, 400), np.random.default_rng(1))
    cam = {smp.step: smp.z for smp in run.samples if smp.sensor == "camera"}
    x = run.truth
    t = {"intake": 0.0, "predict": 0.0, "resolve": 0.0}
    count = 0
    for k in range(20, steps):
        u = np.array([0.5 if 0 < (k + 10) % 400 <= 80 else 0.0])
        z_r = np.array([x[k - 12, 2] - x[k - 12, 0]])
        z_c = cam.get(k - 10) if (k - 10) % 2 == 0 else None
        t0 = time.perf_counter()
        for e in ests:
            e.add_command(k + 10, u, now=k)
            e.add_measurement("ranger", k - 12, z_r, now=k)
            if z_c is not None:
                e.add_measurement("camera", k - 10, z_c, now=k)
        t1 = time.perf_counter()
        preds = [e.predict(k) for e in ests]
        t2 = time.perf_counter()
        resolve([p.x for p in preds])
        t3 = time.perf_counter()
        if k >= WARMUP:
            t["intake"] += t1 - t0
            t["predict"] += t2 - t1
            t["resolve"] += t3 - t2
            count += n
    return {name: 1e6 * v / count for name, v in t.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", type=int, default=20, help="sessions resolved together per step")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"stacked engine alone: {args.sessions} paper sessions, {args.steps} steps, "
          f"hot path {native.STATUS}")
    runs = []
    for i in range(args.repeat):
        r = one_run(args.sessions, args.steps)
        r["total"] = sum(r.values())
        runs.append(r)
        print(f"  run {i + 1}: " + ", ".join(f"{k} {v:.2f}" for k, v in r.items())
              + " µs per session-step", flush=True)
    med = {k: round(statistics.median(r[k] for r in runs), 2) for k in runs[0]}
    print(f"{'part':>8} {'µs / session-step (median)':>28}")
    for k, v in med.items():
        print(f"{k:>8} {v:28.2f}")
    print(json.dumps({"sessions": args.sessions, "hot_path": native.STATUS, **med,
                      "runs": runs}))


if __name__ == "__main__":
    main()
