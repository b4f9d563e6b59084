#!/usr/bin/env python3
"""IMM of unscented information filters: the UIF-IMM paper's table, honestly reproduced.

Scenario: speed 0.3 m/s, T = 0.1 s, straight / +4.5 deg/s / straight / -3 deg/s /
straight; three range-bearing stations (0.3 m, 3.5 deg); CV + CT modes, p_stay 0.995.
Monte-Carlo runs share their random numbers across methods (same initial estimate, same
measurement noise), and the runs are vectorised (one numpy batch per method).

Methods:
  single        IMM-UIF on station 1 only
  centralised   all stations stacked: contributions summed on one prior, joint likelihood
  UIF-IMM 1     one IMM per station node, contributions shared, local likelihood only
                (node 1 = station 1 reported; all nodes printed)
  UIF-IMM 2     contributions shared and mode likelihoods multiplied across stations

Prints the table in the paper's format (RMS position m, RMS heading deg, mean probability of
the wrong mode), the paper's and the issue's numbers beside it, the bars, writes a PNG (track,
errors over time, mode probabilities; needs matplotlib, skipped without it) and ends with one
JSON line. Progress goes to stderr.

Also: RMS of the single-sensor IMM on the other stations, and the per-tick cost of the
ImmObserverPredictor (exact replay) for each variant.

Usage: python bench/imm.py [--runs 100] [--seed 1] [--turn-noise step|accel_deg|accel_rad]
                           [--png out/imm.png] [--sensitivity RUNS]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from pd_service.scenarios.filter_runs import monte_carlo
from pd_service.scenarios.tracking import STATIONS, TURN_NOISE, tracking_scenario

METHODS = (  # key (scenario.METHODS), label, variant, node
    ("single", "single", "single", 0),
    ("centralised", "centralised", "centralised", 0),
    ("imm1", "UIF-IMM 1", "imm1", 0),
    ("imm2", "UIF-IMM 2", "imm2", 0),
)
PAPER = {"pos": (0.158, 0.059, 0.068, 0.047), "head": (2.1, 1.2, 1.2, 0.9)}
ISSUE_EXPECTED_POS = (0.158, 0.059, 0.065, 0.059)
#: Line styles: centralised dashed on top, since UIF-IMM 2 lies on it.
STYLE = {"single": "-", "centralised": "--", "imm1": "-", "imm2": "-"}
ZORDER = {"single": 2, "centralised": 4, "imm1": 2, "imm2": 3}


def run(scn, runs: int, seed: int, label: str = "", extra_singles: bool = False) -> dict:
    """Run every method over the same random numbers; summaries and per-step series."""
    t0 = time.perf_counter()

    def progress(k, K):
        print(f"  {label}step {k}/{K}  {time.perf_counter() - t0:.1f} s", file=sys.stderr)

    methods = {key: (variant, node) for key, _, variant, node in METHODS}
    if extra_singles:
        methods.update({f"single_st{i + 1}": ("single", i) for i in range(1, len(scn.sensors))})
    mc = monte_carlo(scn, runs, seed, methods=methods, progress=progress)
    keys = [key for key, _, _, _ in METHODS]
    return {
        "other_singles": {key: mc.rms_position(key) for key in methods if key.startswith("single_")},
        "pos": {key: mc.rms_position(key) for key in keys},
        "head": {key: mc.rms_heading_deg(key) for key in keys},
        "wrong": {key: mc.p_wrong(key) for key in keys},
        "imm1_nodes": [float(v) for v in np.sqrt(mc.imm1_nodes_pos2.mean(axis=(0, 2)))],
        "paired": paired(mc),
        "series": {
            "pos": {key: np.sqrt(mc.pos2[key].mean(axis=0)) for key in keys},
            "head": {key: np.degrees(np.sqrt(mc.head2[key].mean(axis=0))) for key in keys},
            "p_ct": {key: mc.p_ct[key].mean(axis=0) for key in keys},
        },
        "track": mc.track,
        "seconds": time.perf_counter() - t0,
    }


def paired(mc) -> dict:
    """Per-run differences UIF-IMM 2 - centralised (same random numbers): RMS position (m)
    and mean wrong-mode probability, as mean and standard error over runs."""
    runs = mc.pos2["imm2"].shape[0]
    d = np.sqrt(mc.pos2["imm2"].mean(1)) - np.sqrt(mc.pos2["centralised"].mean(1))
    w = mc.wrong["imm2"].mean(1) - mc.wrong["centralised"].mean(1)

    def se(v: np.ndarray) -> float:
        return float(v.std(ddof=1) / np.sqrt(runs)) if runs > 1 else float("nan")

    return {"rms_diff_m": float(d.mean()), "rms_diff_se_m": se(d),
            "imm2_better_fraction": float((d < 0).mean()),
            "wrong_diff": float(w.mean()), "wrong_diff_se": se(w)}


def print_table(res: dict, runs: int, turn_noise: str) -> None:
    labels = [lab for _, lab, _, _ in METHODS]
    keys = [key for key, _, _, _ in METHODS]
    w = 13
    print(f"IMM-UIF, {runs} Monte-Carlo runs (common random numbers), turn noise '{turn_noise}'")
    print(f"{'Error':<26}" + "".join(f"{lab:>{w}}" for lab in labels))
    print(f"{'RMS position (m)':<26}" + "".join(f"{res['pos'][k]:>{w}.4f}" for k in keys))
    print(f"{'RMS heading (deg)':<26}" + "".join(f"{res['head'][k]:>{w}.2f}" for k in keys))
    print(f"{'P(wrong mode), mean':<26}" + "".join(f"{res['wrong'][k]:>{w}.3f}" for k in keys))
    print(f"{'paper: RMS position':<26}" + "".join(f"{v:>{w}.3f}" for v in PAPER["pos"]))
    print(f"{'paper: RMS heading':<26}" + "".join(f"{v:>{w}.1f}" for v in PAPER["head"]))
    print(f"{'issue: expected position':<26}" + "".join(f"{v:>{w}.3f}" for v in ISSUE_EXPECTED_POS))
    nodes = ", ".join(f"node {i + 1} {v:.4f}" for i, v in enumerate(res["imm1_nodes"]))
    print(f"UIF-IMM 1 per node (station i's node, RMS position m): {nodes}; table = node 1")
    pr = res["paired"]
    print(f"UIF-IMM 2 - centralised, per run: RMS position {pr['rms_diff_m']:+.2e} "
          f"+- {pr['rms_diff_se_m']:.1e} m (imm2 better in {pr['imm2_better_fraction']:.0%} of "
          f"runs); P(wrong mode) {pr['wrong_diff']:+.4f} +- {pr['wrong_diff_se']:.4f}")
    if res["other_singles"]:
        others = ", ".join(f"{k[7:]} {v:.4f}" for k, v in res["other_singles"].items())
        print(f"single sensor, other stations (RMS position m): {others}; table = st1")


def bars(res: dict) -> dict:
    p = res["pos"]
    r_cs = p["centralised"] / p["single"]
    r_1c = p["imm1"] / p["centralised"]
    r_2c = p["imm2"] / p["centralised"]
    return {
        "centralised/single": (r_cs, "0.34-0.40", 0.34 <= r_cs <= 0.40),
        "UIF-IMM 1/centralised": (r_1c, "> 1", r_1c > 1.0),
        "UIF-IMM 2/centralised": (r_2c, "0.998-1.002", 0.998 <= r_2c <= 1.002),
    }


def plot(res: dict, scn, path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no PNG (pip install matplotlib)", file=sys.stderr)
        return False
    t = np.arange(1, scn.steps + 1) * scn.period_s
    fig, ax = plt.subplots(2, 2, figsize=(12, 8.5))
    a = ax[0, 0]
    a.plot(scn.truth[:, 0], scn.truth[:, 2], "k-", lw=2, label="truth")
    for key, lab, _, _ in METHODS:
        if key in ("single", "imm2"):
            a.plot(res["track"][key][:, 0], res["track"][key][:, 1], lw=0.8, label=f"{lab} (run 1)")
    st = np.array(STATIONS)
    a.plot(st[:, 0], st[:, 1], "r^", ms=9, label="stations")
    a.set_aspect("equal")
    a.set_xlabel("xi (m)")
    a.set_ylabel("eta (m)")
    a.set_title("track")
    a.legend(fontsize=8)
    for a, what, ylab in ((ax[0, 1], "pos", "RMS position error (m)"),
                          (ax[1, 0], "head", "RMS heading error (deg)")):
        for key, lab, _, _ in METHODS:
            a.plot(t, res["series"][what][key], STYLE[key], lw=0.9, label=lab, zorder=ZORDER[key])
        a.set_xlabel("t (s)")
        a.set_ylabel(ylab)
        a.legend(fontsize=8)
        if what == "head":
            a.set_ylim(0, min(40.0, float(max(np.max(v) for v in res["series"]["head"].values()))))
    a = ax[1, 1]
    a.fill_between(np.arange(scn.steps + 1) * scn.period_s, 0, scn.turning.astype(float),
                   color="0.85", label="true mode CT")
    for key, lab, _, _ in METHODS:
        a.plot(t, res["series"]["p_ct"][key], STYLE[key], lw=0.9, label=lab, zorder=ZORDER[key])
    a.set_xlabel("t (s)")
    a.set_ylabel("mean P(CT)")
    a.set_title("mode probability (mean over runs)")
    a.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return True


def replay_cost(scn, ticks: int = 600) -> dict:
    """Median ms per tick of ImmObserverPredictor (add the tick's packets, then predict):
    3 stations every step, delays uniform 0..5 steps, max_delay 10, lead 5."""
    from pd_service.estimation.imm.factory import make_imm
    from pd_service.scenarios.tracking import simulate

    x0, Z = simulate(scn, 1, 3)
    rng = np.random.default_rng(0)
    arrivals: dict[int, list] = {}
    for s in range(1, ticks + 1):
        for i in range(len(scn.sensors)):
            arrivals.setdefault(s + int(rng.integers(0, 6)), []).append((i, s))
    out = {}
    for key, _, variant, node in METHODS:
        op = make_imm(scn.modes, scn.transition, scn.sensors, variant, x0[0], scn.P0,
                      lead=5, max_delay=10, node=node)
        times = []
        for now in range(1, ticks + 1):
            t = time.perf_counter()
            for i, s in arrivals.get(now, []):
                op.add_measurement(scn.sensors[i].name, s, Z[0, s, i], now=now)
            op.predict(now)
            times.append(time.perf_counter() - t)
        out[key] = float(np.median(times) * 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--turn-noise", default="step", choices=sorted(TURN_NOISE))
    ap.add_argument("--png", default="out/imm.png")
    ap.add_argument("--sensitivity", type=int, default=0, metavar="RUNS",
                    help="also run the other turn-noise readings with RUNS runs")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error("--runs must be >= 1")

    scn = tracking_scenario(args.turn_noise)
    print(f"running {args.runs} runs x {scn.steps} steps, 4 methods ...", file=sys.stderr)
    res = run(scn, args.runs, args.seed, extra_singles=True)
    print_table(res, args.runs, args.turn_noise)
    b = bars(res)
    print("bars:")
    for name, (val, want, ok) in b.items():
        print(f"  {name:<24} {val:8.4f}   want {want:<12} {'PASS' if ok else 'FAIL'}")

    sens = {}
    if args.sensitivity:
        print(f"sensitivity to the reading of the CT turn noise ({args.sensitivity} runs):")
        for tn in sorted(TURN_NOISE):
            if tn == args.turn_noise:
                continue
            r = run(tracking_scenario(tn), args.sensitivity, args.seed, label=f"{tn}: ")
            sens[tn] = {k: round(v, 4) for k, v in r["pos"].items()}
            p = r["pos"]
            print(f"  {tn:<10} position single {p['single']:.4f}"
                  f"  centralised {p['centralised']:.4f}"
                  f"  UIF-IMM 1 {p['imm1']:.4f}  UIF-IMM 2 {p['imm2']:.4f}"
                  f"  c/s {p['centralised'] / p['single']:.3f}"
                  f"  1/c {p['imm1'] / p['centralised']:.4f}"
                  f"  2/c {p['imm2'] / p['centralised']:.4f}")

    cost = replay_cost(scn)
    print("replay cost, ImmObserverPredictor (delays 0-5 steps, max_delay 10, lead 5): "
          + ", ".join(f"{k} {v:.2f} ms" for k, v in cost.items()) + " median per tick")

    png = Path(args.png)
    wrote = plot(res, scn, png)
    print(f"PNG: {png if wrote else 'not written'}   ({res['seconds']:.1f} s for the main runs)")
    summary = {
        "bench": "imm",
        "runs": args.runs,
        "seed": args.seed,
        "turn_noise": args.turn_noise,
        "rms_position_m": {k: round(v, 5) for k, v in res["pos"].items()},
        "rms_heading_deg": {k: round(v, 3) for k, v in res["head"].items()},
        "p_wrong_mode": {k: round(v, 4) for k, v in res["wrong"].items()},
        "imm1_nodes_rms_position_m": [round(v, 5) for v in res["imm1_nodes"]],
        "single_other_stations_rms_position_m": {
            k: round(v, 5) for k, v in res["other_singles"].items()},
        "replay_ms_per_tick": {k: round(v, 3) for k, v in cost.items()},
        "imm2_minus_centralised_per_run": {k: float(f"{v:.3g}") for k, v in res["paired"].items()},
        "ratios": {k: round(v[0], 5) for k, v in b.items()},
        "bars_pass": all(v[2] for v in b.values()),
        "sensitivity_rms_position_m": sens,
        "png": str(png) if wrote else None,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
