#!/usr/bin/env python3
"""Could sessions share covariances (gains cached by arrival pattern)? Only if their
covariances are bit for bit equal: this measures how far apart they stay.

Two paper sessions (ObserverPredictor, the same spec, the same commands and measurement
values) differ only in which samples arrived: session B loses its samples at a few steps.
Printed: the relative distance max|P_A - P_B| / max|P_A| of their predictions' covariances
over time, whether they are ever equal again, then one JSON line.

Usage: python bench/shared_covariance.py [--steps 1500] [--lost 50,51,300,301,302]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from pd_service.backends import build
from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--lost", default="50,51,300,301,302", help="steps whose samples B loses")
    args = ap.parse_args()
    lost = {int(k) for k in args.lost.split(",") if k}
    spec = paper_scenario().spec("s", 0, max_delay=RANGER_DELAY)
    a, b = build(spec).est, build(spec).est
    rows, equal_from, equal_steps = [], None, 0
    for k in range(args.steps):
        for est, loses in ((a, False), (b, k in lost)):
            est.add_command(k + spec.lead, np.array([0.1]), now=k)
            if k >= RANGER_DELAY and not loses:
                est.add_measurement("ranger", k - RANGER_DELAY, np.array([1.0]), now=k)
            if k >= 10 and k % 2 == 0 and not loses:
                est.add_measurement("camera", k - 10, np.array([0.0, 5.0]), now=k)
        pa, pb = a.predict(k), b.predict(k)
        eq = bool(np.array_equal(pa.P, pb.P))
        equal_steps += eq and k > min(lost, default=0)
        if eq and equal_from is None and k > max(lost, default=-1):
            equal_from = k
        if k % 50 == 0 or k == args.steps - 1:
            rows.append((k, float(np.max(np.abs(pa.P - pb.P)) / np.max(np.abs(pa.P))), eq))
    print(f"paper scenario, session B loses its samples at steps {sorted(lost)}")
    print(f"{'step':>6} {'max|dP|/max|P|':>15} {'equal':>6}")
    for k, d, eq in rows:
        print(f"{k:>6} {d:>15.2e} {str(eq):>6}")
    print(f"equal again after the last loss: {'never' if equal_from is None else f'from step {equal_from}'}")
    print(json.dumps({"steps": args.steps, "lost": sorted(lost), "final_rel_distance": rows[-1][1],
                      "equal_steps_after_first_loss": equal_steps, "equal_again_from": equal_from}))


if __name__ == "__main__":
    main()
