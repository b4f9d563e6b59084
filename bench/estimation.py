#!/usr/bin/env python3
"""Per-tick cost of ObserverPredictor against the augmented-state Kalman filter.

A tick = add that step's command and the packets arriving at that step, then predict.
Both estimators are fed the same packets in the same run; figures are medians over ticks.

Configurations:
  paper   n=4,  max_delay=12:  camera (2 rows, every 2 steps, delay 10), ranger (1 row, every
          step, delay 12), lead 10 (the paper's example)
  large   n=12, max_delay=50:  3 sensors, delays 5 / 20 / 50, intervals 1 / 2 / 5, lead 10
  window  n=4,  max_delay=200: the paper's sensors; 2% of packets straggle, delayed uniformly
          up to 200 steps
Then ObserverPredictor's µs per tick over steps 5,000-5,300 against steps 0-300 (paper config),
and last one JSON object with the figures ("kernel": the linear backend's arithmetic in C, or
its numpy form under PD_SERVICE_PURE=1 or without a compiled build).

Usage: python bench/estimation.py [--ticks N] [--skip-aug-large]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor
from pd_service.research import AugmentedStateKF
from pd_service.scenarios.paper import paper_model, paper_prior, paper_sensors


def random_system(rng, n, sensor_rows):
    A = rng.standard_normal((n, n))
    A *= 0.98 / max(abs(np.linalg.eigvals(A)))
    B = rng.standard_normal((n, 2))
    L = rng.standard_normal((n, n)) * 0.1
    model = LinearModel(A=A, B=B, Q=L @ L.T + 1e-3 * np.eye(n))
    sensors = []
    for i, m in enumerate(sensor_rows):
        Lr = rng.standard_normal((m, m)) * 0.2
        sensors.append(Sensor(name=f"s{i}", H=rng.standard_normal((m, n)), R=Lr @ Lr.T + 0.01 * np.eye(m)))
    return model, sensors


def make_config(name, rng):
    if name == "paper" or name == "window":
        model, sensors = paper_model(), paper_sensors()
        x0, P0 = paper_prior()
        spec = [(10, 2), (12, 1)]  # (delay, interval) per sensor
        max_delay = 12 if name == "paper" else 200
        straggle = 0.0 if name == "paper" else 0.02
    else:
        model, sensors = random_system(rng, 12, [3, 2, 1])
        x0, P0 = np.zeros(12), np.eye(12)
        spec = [(5, 1), (20, 2), (50, 5)]
        max_delay, straggle = 50, 0.0
    return model, sensors, x0, P0, spec, max_delay, straggle


def schedule(rng, sensors, spec, max_delay, straggle, ticks):
    """arrivals[k] = list of (sensor name, sample step, z) arriving at step k."""
    arrivals: dict[int, list] = {}
    for s, (delay, interval) in zip(sensors, spec, strict=True):
        for step in range(0, ticks, interval):
            d = delay
            if straggle and rng.random() < straggle:
                d = int(rng.integers(delay, max_delay + 1))
            arrivals.setdefault(step + d, []).append((s.name, step, rng.standard_normal(s.m)))
    return arrivals


def run(est, arrivals, nu, ticks, lead, rng):
    times = []
    us = rng.standard_normal((ticks + lead, nu)) * 0.1
    for k in range(ticks):
        t0 = time.perf_counter()
        est.add_command(step=k + lead, u=us[k + lead], now=k)
        for name, step, z in arrivals.get(k, ()):
            est.add_measurement(name, step=step, z=z, now=k)
        est.predict(now=k)
        times.append(time.perf_counter() - t0)
    return np.array(times) * 1e6


def bench_config(name, ticks, with_aug=True):
    rng = np.random.default_rng(7)
    model, sensors, x0, P0, spec, max_delay, straggle = make_config(name, rng)
    arrivals = schedule(rng, sensors, spec, max_delay, straggle, ticks)
    lead = 10
    op = ObserverPredictor(model, sensors, x0, P0, lead=lead, max_delay=max_delay)
    t_op = run(op, arrivals, model.nu, ticks, lead, np.random.default_rng(1))
    row = {"config": name, "n": model.n, "max_delay": max_delay,
           "op_us": statistics.median(t_op[max_delay:]), "op_mean_us": float(np.mean(t_op[max_delay:]))}
    if with_aug:
        aug = AugmentedStateKF(model, sensors, x0, P0, lead=lead, max_delay=max_delay)
        t_aug = run(aug, arrivals, model.nu, ticks, lead, np.random.default_rng(1))
        row["aug_us"] = statistics.median(t_aug[max_delay:])
        pa, pb = op.predict(ticks - 1), aug.predict(ticks - 1)
        row["max_abs_diff"] = float(max(np.max(abs(pa.x - pb.x)), np.max(abs(pa.P - pb.P))))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ticks", type=int, default=1500)
    ap.add_argument("--skip-aug-large", action="store_true",
                    help="skip the (slow) augmented filter at max_delay=200")
    args = ap.parse_args()
    rows = []
    for name in ("paper", "large", "window"):
        ticks = args.ticks if name == "paper" else max(300, args.ticks // 3)
        print(f"... {name}: {ticks} ticks", file=sys.stderr, flush=True)
        rows.append(bench_config(name, ticks, with_aug=not (name == "window" and args.skip_aug_large)))
    print(f"{'config':8} {'n':>3} {'max_delay':>9} {'ObserverPredictor µs':>21} {'mean µs':>8} "
          f"{'AugmentedStateKF µs':>20} {'ratio':>7} {'max |diff|':>10}")
    for r in rows:
        aug = r.get("aug_us")
        ratio = f"{aug / r['op_us']:7.1f}x" if aug else "      -"
        print(f"{r['config']:8} {r['n']:>3} {r['max_delay']:>9} {r['op_us']:>21.1f} {r['op_mean_us']:>8.1f} "
              f"{(f'{aug:.1f}' if aug else '-'):>20} {ratio} {r.get('max_abs_diff', float('nan')):>10.2e}")

    # Growth with elapsed steps: steps 0-300 against 5,000-5,300 (paper config).
    rng = np.random.default_rng(3)
    model, sensors, x0, P0, spec, max_delay, straggle = make_config("paper", rng)
    arrivals = schedule(rng, sensors, spec, max_delay, straggle, 5300)
    op = ObserverPredictor(model, sensors, x0, P0, lead=10, max_delay=max_delay)
    t = run(op, arrivals, model.nu, 5300, 10, np.random.default_rng(1))
    early, late = statistics.median(t[12:300]), statistics.median(t[5000:5300])
    print(f"growth: median µs/tick steps 12-300 {early:.1f}, steps 5000-5300 {late:.1f}, "
          f"ratio {late / early:.2f}")
    from pd_service.estimation.linear import _KALMAN

    print(json.dumps({"kernel": "C" if _KALMAN is not None else "numpy", "configs": [
        {k: (round(v, 3) if k.endswith("_us") else v) for k, v in r.items()} for r in rows],
        "growth_us": [round(early, 3), round(late, 3)]}))


if __name__ == "__main__":
    main()
