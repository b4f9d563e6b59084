#!/usr/bin/env python3
"""Which rounding a discrete spec's t_ns stamps get by default (SessionSpec.stamp_rounding).

The issue-42 case: 1-D constant velocity (~1 m/s, white acceleration noise), one position
sensor (20 mm std) at 10 Hz with its own phase and 2 ms jitter, delivered 100 ms late, a
50 ms step. The discrete model (A, B, Q of one step) applies a sample at a step's start:
"floor" (the step containing the stamp, what the daemon did before) or "nearest" (the nearest
step start, never past the current step), as the intake does it. "exact": the same model in
continuous time, every sample at its own time. Printed: RMS and mean (bias) of the position
error of x(now) against the truth at now, over Monte-Carlo runs (median and spread over
runs), then a JSON line. CPU only, a few seconds: an accuracy figure, not a timing one.

Usage: python bench/stamp_rounding.py [--runs 20] [--steps 400]
"""

from __future__ import annotations

import argparse
import json
import statistics

import numpy as np

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor

T_NS = 50_000_000  # the step, ns
RATE_NS = 100_000_000  # the sensor's period, ns
DELAY_NS = 100_000_000
STD = 0.02  # m
QC = 0.05  # acceleration noise density, m^2 / s^3
F = np.array([[0.0, 1.0], [0.0, 0.0]])
G = np.zeros((2, 0))
QCM = np.diag([0.0, QC])


def truth(rng: np.random.Generator, t_end: float, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """(times (k,), states (k, 2)) of the constant-velocity truth sampled every dt."""
    k = int(t_end / dt) + 1
    acc = rng.normal(0.0, np.sqrt(QC / dt), size=k)
    v = 1.0 + np.cumsum(acc) * dt
    p = np.cumsum(v) * dt
    return np.arange(k) * dt, np.stack([p, v], axis=1)


def run(mode: str, seed: int, steps: int) -> list[float]:
    rng = np.random.default_rng(seed)
    T = T_NS / 1e9
    times, xs = truth(rng, (steps + 2) * T)
    cont = LinearModel.continuous(F, G, QCM, T)
    model = cont if mode == "exact" else LinearModel(A=cont.A, B=cont.B, Q=cont.Q)
    op = ObserverPredictor(model, [Sensor("pos", np.array([[1.0, 0.0]]), np.eye(1) * STD**2)],
                           x0=xs[0], P0=np.diag([0.01, 0.01]), lead=0, max_delay=6)
    phase = int(rng.integers(0, RATE_NS))
    stamps = [phase + i * RATE_NS + int(rng.normal(0, 2e6)) for i in range(steps * T_NS // RATE_NS)]
    errors = []
    j = 0
    for k in range(steps):
        now_ns = k * T_NS
        while j < len(stamps) and stamps[j] + DELAY_NS <= now_ns:
            t = max(stamps[j], 0)
            z = xs[round(t / 1e6), 0] + rng.normal(0, STD)
            if mode == "exact":
                s = t // T_NS
                op.add_measurement("pos", s, [z], k, offset=(t - s * T_NS) / 1e9)
            else:
                s = t // T_NS if mode == "floor" else min((t + T_NS // 2) // T_NS, k)
                op.add_measurement("pos", s, [z], k)
            j += 1
        if k >= 40:  # after the start-up transient
            errors.append(float(op.predict(k).x[0] - xs[round(now_ns / 1e6), 0]))
    return errors


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--steps", type=int, default=400)
    args = ap.parse_args()
    out = {}
    print(f"{'mode':8} {'RMS mm':>10} {'spread':>14} {'bias mm':>9}")
    for mode in ("floor", "nearest", "exact"):
        rms, bias = [], []
        for seed in range(args.runs):
            e = np.array(run(mode, seed, args.steps))
            rms.append(float(np.sqrt(np.mean(e**2))) * 1e3)
            bias.append(float(np.mean(e)) * 1e3)
        med = statistics.median(rms)
        out[mode] = {"rms_mm": round(med, 2), "rms_min": round(min(rms), 2),
                     "rms_max": round(max(rms), 2), "bias_mm": round(statistics.mean(bias), 2)}
        print(f"{mode:8} {med:10.2f} {min(rms):6.2f}..{max(rms):6.2f} "
              f"{statistics.mean(bias):9.2f}")
    print(json.dumps({"bench": "stamp_rounding", "runs": args.runs, "steps": args.steps, **out}))


if __name__ == "__main__":
    main()
