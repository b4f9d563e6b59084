"""Calibrate the CPU model of pd_service.service.admission: time the estimators' unit
operations on this machine and print the per-operation costs (µs).

    .venv/bin/python bench/admission_calibrate.py

Linear: one propagate (multi-step, from the tables) + one Kalman update, n = 4, 16, 64,
fitted as a + b n^3 (µs). Unscented (omni3, n = 6): one propagated step of the sigma points
and one update. IMM (imm_cv / imm_ct, r = 2): one predicted step. Then the model's price of the paper's
session and how many the default cpu_budget admits; the linear constants in
pd_service/backends.py follow the worker's measured cost per session-step
(docs/performance.md, "Admission's cost model"). A final JSON line holds every figure.
"""

from __future__ import annotations

import time

import numpy as np

from pd_service.estimation import LinearModel, ObserverPredictor, Sensor


def per_call(fn, reps: int) -> float:
    fn()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    return (time.perf_counter() - t0) / reps * 1e6


def linear(n: int) -> float:
    """µs for one step of a linear session: a measurement at now, then predict(now)."""
    A = np.eye(n) + 0.01 * np.eye(n, k=1)
    est = ObserverPredictor(LinearModel(A=A, B=np.ones((n, 1)), Q=1e-3 * np.eye(n)),
                            [Sensor("s", np.eye(1, n), np.eye(1))], np.zeros(n), np.eye(n),
                            lead=5, max_delay=5)
    k = [0]

    def step() -> None:
        k[0] += 1
        est.add_measurement("s", k[0], [1.0], now=k[0])
        est.predict(k[0])
    return per_call(step, 2000 if n < 32 else 300)


def unscented(lead: int) -> float:
    from pd_service.estimation.nonlinear.factory import make_unscented
    p = {"period_s": 0.05, "mass": 10, "Q": [1e-10, 1e-10, 1e-10, 4e-6, 4e-6, 2.5e-5]}
    est = make_unscented("omni3", p, x0=np.zeros(6), P0=1e-3 * np.eye(6), lead=lead,
                         max_delay=2, sensors=["pose"], sensor_R={"pose": 1e-6 * np.eye(3)})
    k = [0]

    def step() -> None:
        k[0] += 1
        est.add_measurement("pose", k[0], [0.0, 0.0, 0.0], now=k[0])
        est.predict(k[0])
    return per_call(step, 200)


def model_paper() -> tuple[float, int]:
    """The cost model's price of the paper's session (µs per step) and how many of them
    the default ``cpu_budget`` admits (no timing: the model's figures)."""
    from pd_service.backends import command_dim, spec_cost
    from pd_service.scenarios.paper import paper_scenario
    from pd_service.service import Settings

    spec = paper_scenario().spec("paper", 0, lead=10, max_delay=12)
    cost = spec_cost(spec, command_dim(spec))
    return cost.cpu_us, int(Settings(instance="bench").cpu_budget / cost.cpu_share)


if __name__ == "__main__":
    import json

    out: dict[str, float] = {}
    for n in (4, 16, 64):
        out[f"linear_n{n}_us"] = us = linear(n)
        print(f"linear n={n:3d}: {us:8.1f} µs/step (1 update + 1 predict)")
    for lead in (0, 50, 200):
        out[f"unscented_omni3_lead{lead}_us"] = us = unscented(lead)
        print(f"unscented omni3 lead={lead:4d}: {us:8.1f} µs/step")
    price, admitted = model_paper()
    out["model_paper_us"], out["model_paper_admitted"] = price, admitted
    print(f"model: the paper's session {price:.1f} µs per step; the default cpu_budget "
          f"admits {admitted} (compare with the worker's measured µs per session-step: "
          "bench/worker.py)")
    print(json.dumps(out))
