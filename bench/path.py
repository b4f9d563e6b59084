#!/usr/bin/env python3
"""Cost of the predicted path (issue 45) per session-step, next to the prediction's own.

One daemon Session (pd_service.service.session) of the paper scenario (n = 4, lead 10,
camera 10 and ranger 12 steps late, max_delay 16) is driven step by step in-process: the
samples that arrive at k are given to its estimator, then

  prediction   what the daemon does per published step without a path: predict(k), the
               health check and the encoded Prediction (Session.pack)
  path         what a spec's ``path`` adds: Session.pack_path (predict_path from the newest
               measured step to k + lead, one point per ``--stride`` steps, the spec's
               components [0, 2], encoded PredictedPath)

CPU time (process_time over a whole run) per session-step: a run without the path, then
the same run with it (the difference is the path's cost); median and spread (min..max) of
``--repeats`` such pairs of ``--steps`` steps each; the path's points and bytes. On a shared
machine the figures move with its load: the machine gauge (bench/gauge.py) is printed beside
them. The last line is one JSON object.

Usage: python bench/path.py [--steps 400] [--repeats 5] [--stride 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
from gauge import gauge_ms
from stamps import cpu_model

from pd_service.backends import build
from pd_service.scenarios import get_scenario
from pd_service.scenarios.paper import simulate_paper
from pd_service.service.health import inspect_packed
from pd_service.service.session import Session
from pd_service.wire import decode
from pd_service.wire.messages import PathSpec
from pd_service.wire.path import PredictedPath


def run(steps: int, stride: int, seed: int, with_path: bool) -> tuple[float, int, int]:
    """(CPU µs per step of the whole loop; mean points, mean bytes of a path)."""
    spec = get_scenario("paper").spec("s1", 0).model_copy(
        update={"path": PathSpec(indices=[0, 2], stride=stride)})
    sess = Session(spec, build(spec), "active", "created", 0, 10.0, 10)
    arrivals: dict[int, list] = {}
    for smp in simulate_paper(steps, np.random.default_rng(seed)).samples:
        if smp.arrival is not None:
            arrivals.setdefault(smp.arrival, []).append(smp)
    out: list[bytes] = []
    t0 = time.process_time_ns()  # one window: a clock read costs more than a step here
    for k in range(steps):
        for smp in arrivals.get(k, []):
            sess.est.add_measurement(smp.sensor, smp.step, smp.z, now=k)
        pred = sess.predict(k)
        _, xb, pb = inspect_packed(pred.x, pred.P)
        sess.pack(pred, xb, pb, k, 0)
        if with_path:
            out.append(sess.pack_path(k, 0))
    us = (time.process_time_ns() - t0) / steps / 1e3
    points = sum(len(decode(d, PredictedPath).steps) for d in out) // max(len(out), 1)
    return us, points, sum(map(len, out)) // max(len(out), 1)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--stride", type=int, default=1)
    args = ap.parse_args()
    pred, path = [], []
    for seed in range(args.repeats):  # alternated: a load change hits both alike
        a = run(args.steps, args.stride, seed, False)[0]
        b, points, size = run(args.steps, args.stride, seed, True)
        pred.append(a)
        path.append(b - a)
    g = gauge_ms()
    print(f"cpu: {cpu_model()}   gauge: {g:.1f} ms (bench/gauge.py; shared machine)")
    print(f"{'per session-step':<18}{'median µs':>10}{'min':>9}{'max':>9}")
    for name, v in (("prediction", pred), ("path (added)", path)):
        print(f"{name:<18}{statistics.median(v):>10.1f}{min(v):>9.1f}{max(v):>9.1f}")
    print(f"path: {points} points, {size} bytes on average (stride {args.stride}, lead 10)")
    print(json.dumps({"bench": "path", "stride": args.stride, "steps": args.steps,
                      "prediction_us_median": statistics.median(pred),
                      "path_us_median": statistics.median(path),
                      "path_us_min": min(path), "path_us_max": max(path),
                      "points": points, "bytes": size, "gauge_ms": g}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
