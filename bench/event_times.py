#!/usr/bin/env python3
"""CPU per session-step of the linear estimator with samples and commands at their own times
(a continuous-time model, exact offsets) against the same traffic floored to the step grid
(the discrete model of the same A, B, Q), in-process, no network.

N sessions of a planar constant-velocity robot (x, y, vx, vy; acceleration commands), 50 ms
step: odometry (velocity) at 25 Hz 20 ms late, a velocity sensor every IMU_NS ns (default
10 ms: 100 Hz) 5 ms late, a pose fix at 5 Hz 300 ms late, each with its own phase and 1 ms
jitter, and one command per step issued at a random instant for step + 4 (CMD_OFF=0: the
exact model takes commands on the grid). Floored stamps put several samples of one sensor
into one step: the later ones are refused as duplicates (counted). Each configuration runs
twice, alternating; then a JSON line. CPU by process_time around the estimator calls only.
On a shared machine: quote bench/gauge.py beside the figures.

Usage: python bench/event_times.py [sessions] [steps]     (default 1000 40)
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor

T_NS = 50_000_000
T = T_NS / 1e9
IMU_NS = int(os.environ.get("IMU_NS", "10000000"))
CMD_OFF = os.environ.get("CMD_OFF", "1") == "1"
F = np.zeros((4, 4))
F[0, 2] = F[1, 3] = 1.0
G = np.zeros((4, 2))
G[2, 0] = G[3, 1] = 1.0
CONT = LinearModel.continuous(F, G, np.diag([0.0, 0.0, 0.05, 0.05]), T)
DISC = LinearModel(A=CONT.A, B=CONT.B, Q=CONT.Q)
SENSORS = [Sensor("odom", np.eye(4)[2:], np.eye(2) * 0.01),
           Sensor("imu", np.eye(4)[2:], np.eye(2) * 0.04),
           Sensor("pose", np.eye(4)[:2], np.eye(2) * 0.0025)]
#: (sensor, period ns, delay ns)
STREAMS = [("odom", 40_000_000, 20_000_000), ("imu", IMU_NS, 5_000_000),
           ("pose", 200_000_000, 300_000_000)]


def traffic(rng: np.random.Generator, steps: int) -> list[tuple[int, int, str, int]]:
    """(arrival ns, 0 sample / 1 command, sensor, stamp ns), by arrival."""
    ev: list[tuple[int, int, str, int]] = []
    for name, per, delay in STREAMS:
        t = int(rng.integers(0, per))
        while t < steps * T_NS:
            ts = t + int(rng.normal(0, 1e6))
            if ts > 0:
                ev.append((ts + delay, 0, name, ts))
            t += per
    for k in range(steps):
        ts = k * T_NS + int(rng.integers(0, T_NS))
        ev.append((ts, 1, "", ts))
    ev.sort()
    return ev


def run(model: LinearModel, exact: bool, n: int, steps: int) -> tuple[float, dict[str, int]]:
    rng = np.random.default_rng(0)
    ests = [ObserverPredictor(model, SENSORS, np.zeros(4), np.eye(4), lead=4, max_delay=9)
            for _ in range(n)]
    evs = [traffic(rng, steps) for _ in range(n)]
    ptr = [0] * n
    z, u = np.array([0.1, 0.2]), np.array([0.1, 0.0])
    cpu = 0.0
    for k in range(steps):
        now_ns = (k + 1) * T_NS
        t0 = time.process_time()
        for i in range(n):
            est, ev, j = ests[i], evs[i], ptr[i]
            while j < len(ev) and ev[j][0] < now_ns:
                _, kind, name, ts = ev[j]
                s = ts // T_NS
                off = (ts - s * T_NS) / 1e9 if exact else 0.0
                if kind == 0:
                    est.add_checked_measurement(name, s, z.copy(), k, off)
                else:
                    est.add_checked_command(s + 4, u, k, off if CMD_OFF else 0.0)
                j += 1
            ptr[i] = j
            est.predict(k)
        cpu += time.process_time() - t0
    return cpu / (n * steps) * 1e6, ests[0].counters


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    steps = int(sys.argv[2]) if len(sys.argv) > 2 else 40
    out: dict[str, list[float]] = {}
    for label, model, exact in (("floored", DISC, False), ("exact", CONT, True),
                                ("floored", DISC, False), ("exact", CONT, True)):
        us, c = run(model, exact, n, steps)
        out.setdefault(label, []).append(round(us, 2))
        print(f"{label:8} {us:7.1f} us/session-step  (session 0: accepted {c['accepted']}, "
              f"duplicate {c['duplicate']}, late {c['late']})")
    print(json.dumps({"bench": "event_times", "sessions": n, "steps": steps,
                      "imu_ns": IMU_NS, "cmd_offsets": CMD_OFF, **out}))


if __name__ == "__main__":
    main()
