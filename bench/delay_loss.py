"""Linear coding vs exact timestamped replay under random delay and packet loss.

Two profiles, each 200 seeded runs x 300 steps (change with --runs / --steps):

* ``cv``: constant-velocity target in 2-D (4 states, dt = 1, white-noise acceleration with
  spectral density q = 0.1), position measured with R = I; unstable plant (eigenvalue 1).
* ``stable``: damped oscillator A = 0.95 Rot(0.3 rad), C = [1 0], Q = 0.5 I, R = 0.1,
  E[w v] = S = [0.1; 0.1] (S != 0).

Delay: P(delay = 0..3) = (0.5, 0.25, 0.15, 0.05), the remaining 5% lost (d = 3).

Every estimator gives x^(k|k), the estimate of x(k) from the packets received by step k, and
is scored by MSE = mean over runs and steps k >= 20 of |x(k) - x^(k|k)|² (all states; the
figure over the measured states only, position for cv, is printed too). Reported: MSE above
the exact estimator in %, the same ratio predicted from each estimator's own covariance (mean
trace P), and median µs per step.

Exact reference: ``pd_service.estimation.ObserverPredictor`` (lead 0, max_delay d, every
packet added at its arrival step, then ``predict(now=k)``) when it is importable and the
plant has S = 0; otherwise ``TimestampReplayKF`` (same quantity; it also handles S != 0).
When both run, their largest difference is printed as a cross-check.

Tuned beta: compass search on beta_1..beta_d (beta_0 = 1; only ratios matter online) that
minimises the expected MSE (mean trace P over 8 arrival sequences drawn from seeds disjoint
from the evaluation seeds). Offline tuned beta (stable profile only) minimises the trace of
the stationary offline covariance.

Progress goes to stderr; the last stdout line is one JSON object with all numbers.
Usage: .venv/bin/python bench/delay_loss.py [--runs 200] [--steps 300] [--exact auto|own]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pd_service.research.delay_model import DelayModel, arrivals_by_step
from pd_service.research.linear_coding import (
    CodedOnlineEstimator,
    CorrelatedPlant,
    NewestPacketEstimator,
    OfflineCodedEstimator,
    TimestampReplayKF,
    is_stationary,
)

D = 3
DELAY = DelayModel.from_probabilities([0.5, 0.25, 0.15, 0.05])  # remainder 5% lost
BURN = 20
EVAL_SEED = 1_000
TUNE_SEED = 900_000


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------- profiles
@dataclass
class Profile:
    name: str
    plant: CorrelatedPlant
    x0: np.ndarray
    P0: np.ndarray
    position: list[int]
    tuned: dict[str, np.ndarray] = field(default_factory=dict)


def cv_profile() -> Profile:
    dt, q = 1.0, 0.1
    A = np.eye(4)
    A[0, 2] = A[1, 3] = dt
    Q = np.kron(q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]]), np.eye(2))
    plant = CorrelatedPlant(A=A, C=np.eye(2, 4), Q=Q, R=np.eye(2))
    return Profile("cv", plant, np.array([0.0, 0.0, 1.0, 0.5]), np.diag([10.0, 10.0, 1.0, 1.0]), [0, 1])


def stable_profile() -> Profile:
    th = 0.3
    A = 0.95 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    plant = CorrelatedPlant(A=A, C=[[1.0, 0.0]], Q=0.5 * np.eye(2), R=[[0.1]], S=[[0.1], [0.1]])
    return Profile("stable", plant, np.zeros(2), np.eye(2), [0])


# ---------------------------------------------------------------------------- estimators
class ObserverPredictorAdapter:
    """Wraps the core's ObserverPredictor (lead 0) behind the ``update(now, packets)`` call."""

    def __init__(self, mod, plant: CorrelatedPlant, x0: np.ndarray, P0: np.ndarray) -> None:
        model = mod.LinearModel(A=plant.A, B=np.zeros((plant.n, 1)), Q=plant.Q)
        sensor = mod.Sensor(name="pos", H=plant.C, R=plant.R)
        self.op = mod.ObserverPredictor(model, [sensor], x0=x0, P0=P0, lead=0, max_delay=D)

    def update(self, now: int, packets):
        for s, y in packets:
            if not self.op.add_measurement("pos", step=s, z=y, now=now):
                raise RuntimeError(f"ObserverPredictor refused packet {s} at {now}")
        return self.op.predict(now=now)


def load_observer_predictor(mode: str):
    if mode == "own":
        return None
    try:
        import pd_service.estimation as mod

        _ = (mod.LinearModel, mod.Sensor, mod.ObserverPredictor)
        return mod
    except (ImportError, AttributeError) as exc:
        log(f"ObserverPredictor not available ({exc}); exact reference = TimestampReplayKF")
        return None


def make_estimators(prof: Profile, op_mod) -> dict[str, Callable[[], object]]:
    pl, x0, P0 = prof.plant, prof.x0, prof.P0
    geo = 2.0 ** -np.arange(D + 1)
    est: dict[str, Callable[[], object]] = {}
    if op_mod is not None and not np.any(pl.S):
        est["exact (ObserverPredictor)"] = lambda: ObserverPredictorAdapter(op_mod, pl, x0, P0)
    est["exact (replay KF)"] = lambda: TimestampReplayKF(pl, D, x0, P0)
    est["one newest packet"] = lambda: NewestPacketEstimator(pl, D, x0, P0)
    est["coded beta=1"] = lambda: CodedOnlineEstimator(pl, D, np.ones(D + 1), x0, P0)
    est["coded beta=2^-i"] = lambda: CodedOnlineEstimator(pl, D, geo, x0, P0)
    bt = prof.tuned["online"]
    est["coded tuned beta"] = lambda: CodedOnlineEstimator(pl, D, bt, x0, P0)
    est["offline beta=1"] = lambda: OfflineCodedEstimator(pl, DELAY, np.ones(D + 1), x0, P0)
    est["offline beta=2^-i"] = lambda: OfflineCodedEstimator(pl, DELAY, geo, x0, P0)
    if "offline" in prof.tuned:
        bo = prof.tuned["offline"]
        est["offline tuned beta"] = lambda: OfflineCodedEstimator(pl, DELAY, bo, x0, P0)
    return est


# ---------------------------------------------------------------------------- tuning
def expected_mse(prof: Profile, beta: np.ndarray, patterns: list[list[list[int]]], T: int) -> float:
    """Mean trace P(k|k) over the patterns: the online estimator's exact expected MSE."""
    total = 0.0
    zero = np.zeros(prof.plant.m)
    for arr in patterns:
        e = CodedOnlineEstimator(prof.plant, D, beta, prof.x0, prof.P0)
        for k in range(T):
            P = e.update(k, [(s, zero) for s in arr[k]]).P
            if k >= BURN:
                total += float(np.trace(P))
    return total / (len(patterns) * (T - BURN))


def compass_search(f: Callable[[np.ndarray], float], beta0: np.ndarray, step: float, min_step: float):
    """Minimise f over beta[1:] (beta[0] fixed) by compass search; returns (beta, f, evals)."""
    best, fbest, evals = beta0.copy(), f(beta0), 1
    while step >= min_step:
        improved = False
        for i in range(1, beta0.size):
            for sgn in (1.0, -1.0):
                cand = best.copy()
                cand[i] += sgn * step
                fc = f(cand)
                evals += 1
                if fc < fbest - 1e-12:
                    best, fbest, improved = cand, fc, True
                    break
        if not improved:
            step /= 2.0
    return best, fbest, evals


def tune(prof: Profile, T: int) -> None:
    rng = np.random.default_rng(TUNE_SEED)
    patterns = [arrivals_by_step(DELAY.sample(rng, T), T) for _ in range(8)]
    t0 = time.perf_counter()
    b, fb, ev = compass_search(
        lambda b: expected_mse(prof, b, patterns, T), 2.0 ** -np.arange(D + 1), 0.25, 1 / 64
    )
    prof.tuned["online"] = b
    log(
        f"[{prof.name}] tuned online beta {np.round(b, 4).tolist()} "
        f"({ev} evals, {time.perf_counter() - t0:.1f} s)"
    )
    if is_stationary(prof.plant):

        def f_off(b: np.ndarray) -> float:
            return float(np.trace(OfflineCodedEstimator.steady_state(prof.plant, DELAY, b, tol=1e-9)))

        b, fb, ev = compass_search(f_off, 2.0 ** -np.arange(D + 1), 0.25, 1 / 64)
        prof.tuned["offline"] = b
        log(f"[{prof.name}] tuned offline beta {np.round(b, 4).tolist()} ({ev} evals)")


# ---------------------------------------------------------------------------- Monte Carlo
def simulate(prof: Profile, rng: np.random.Generator, T: int):
    """Truth x (T, n), outputs y (T, m), arrivals per step (same law for every estimator)."""
    pl = prof.plant
    n, m = pl.n, pl.m
    J = np.block([[pl.Q, pl.S], [pl.S.T, pl.R]])
    w, V = np.linalg.eigh(J)
    root = V * np.sqrt(np.clip(w, 0.0, None))
    w0, V0 = np.linalg.eigh(prof.P0)
    x = prof.x0 + (V0 * np.sqrt(np.clip(w0, 0, None))) @ rng.normal(size=n)
    noise = rng.normal(size=(T, n + m)) @ root.T  # [w̄(k); v(k)] with Cov J
    xs, ys = np.empty((T, n)), np.empty((T, m))
    for k in range(T):
        xs[k] = x
        ys[k] = pl.C @ x + noise[k, n:]
        x = pl.A @ x + noise[k, :n]
    return xs, ys, arrivals_by_step(DELAY.sample(rng, T), T)


def run_profile(prof: Profile, runs: int, T: int, op_mod) -> dict:
    tune(prof, T)
    makers = make_estimators(prof, op_mod)
    names = list(makers)
    se = {k: 0.0 for k in names}
    se_pos = {k: 0.0 for k in names}
    trP = {k: 0.0 for k in names}
    us = {k: [] for k in names}
    cross = 0.0
    t_start = time.perf_counter()
    for r in range(runs):
        rng = np.random.default_rng(EVAL_SEED + r)
        xs, ys, arr = simulate(prof, rng, T)
        packets = [[(s, ys[s]) for s in arr[k]] for k in range(T)]
        outs = {}
        for name in names:
            e = makers[name]()
            if isinstance(e, OfflineCodedEstimator):
                e.precompute(T)  # data-independent gains: computed before the run
            xh = np.empty_like(xs)
            tr = 0.0
            t0 = time.perf_counter()
            for k in range(T):
                o = e.update(k, packets[k])
                xh[k] = o.x
                if k >= BURN:
                    tr += float(np.trace(o.P))
            us[name].append((time.perf_counter() - t0) / T * 1e6)
            err = (xs - xh)[BURN:]
            se[name] += float(np.sum(err**2))
            se_pos[name] += float(np.sum(err[:, prof.position] ** 2))
            trP[name] += tr
            outs[name] = xh
        if "exact (ObserverPredictor)" in outs:
            cross = max(
                cross,
                float(np.max(np.abs(outs["exact (ObserverPredictor)"] - outs["exact (replay KF)"]))),
            )
        if (r + 1) % max(1, runs // 10) == 0:
            log(f"[{prof.name}] run {r + 1}/{runs}  {time.perf_counter() - t_start:.0f} s")
    cnt = runs * (T - BURN)
    ref = names[0]
    mse = {k: se[k] / cnt for k in names}
    res = {
        "plant_stable": is_stationary(prof.plant),
        "exact_reference": ref,
        "mse_exact": mse[ref],
        "excess_mse_pct": {k: 100.0 * (mse[k] / mse[ref] - 1.0) for k in names if k != ref},
        "excess_mse_pos_pct": {k: 100.0 * (se_pos[k] / se_pos[ref] - 1.0) for k in names if k != ref},
        "predicted_excess_pct": {k: 100.0 * (trP[k] / trP[ref] - 1.0) for k in names if k != ref},
        "us_per_step": {k: float(np.median(us[k])) for k in names},
        "beta_tuned_online": prof.tuned["online"].tolist(),
    }
    if "offline" in prof.tuned:
        res["beta_tuned_offline"] = prof.tuned["offline"].tolist()
    if "exact (ObserverPredictor)" in names:
        res["observer_vs_replay_max_abs_diff"] = cross
    if not is_stationary(prof.plant):
        # divergence of the offline estimator: its own covariance at the end vs at step 100
        e = OfflineCodedEstimator(prof.plant, DELAY, np.ones(D + 1), prof.x0, prof.P0)
        tr = [float(np.trace(e.update(k).P)) for k in range(T)]
        res["offline_trP_growth_100_to_end"] = tr[-1] / tr[min(100, T - 1)]
    return res


def offline_sensitivity(T: int) -> list[dict]:
    """Expected excess of the stationary offline estimator over exact, for damped oscillators.

    Covariance only (no Monte Carlo): exact = mean trace P of the replay filter over 8 arrival
    sequences (its P is the conditional MSE given the arrivals); offline = trace of its
    stationary covariance with beta = 2^-i. C = [1 0], Q = 0.5 I, S = [0.1; 0.1].
    """
    rng = np.random.default_rng(TUNE_SEED + 1)
    patterns = [arrivals_by_step(DELAY.sample(rng, T), T) for _ in range(8)]
    rows = []
    for radius in (0.9, 0.95, 0.98):
        for theta in (0.1, 0.3):
            for r in (0.1, 0.5):
                c, s_ = np.cos(theta), np.sin(theta)
                pl = CorrelatedPlant(
                    A=radius * np.array([[c, -s_], [s_, c]]),
                    C=[[1.0, 0.0]],
                    Q=0.5 * np.eye(2),
                    R=[[r]],
                    S=[[0.1], [0.1]],
                )
                tot = 0.0
                for arr in patterns:
                    e = TimestampReplayKF(pl, D, np.zeros(2), np.eye(2))
                    for k in range(T):
                        P = e.update(k, [(s, np.zeros(1)) for s in arr[k]]).P
                        if k >= BURN:
                            tot += float(np.trace(P))
                exact = tot / (len(patterns) * (T - BURN))
                off = float(np.trace(OfflineCodedEstimator.steady_state(pl, DELAY, 2.0 ** -np.arange(D + 1))))
                rows.append(
                    {"radius": radius, "theta": theta, "R": r, "offline_excess_pct": 100 * (off / exact - 1)}
                )
    return rows


def print_table(name: str, res: dict) -> None:
    ref = res["exact_reference"]
    print(
        f"\n== profile {name}: exact = {ref}, MSE {res['mse_exact']:.4g} (all states), "
        f"plant stable: {res['plant_stable']}"
    )
    print(f"{'estimator':28s} {'MSE vs exact':>13s} {'measured':>10s} {'predicted':>10s} {'us/step':>9s}")
    print(f"{ref:28s} {'—':>13s} {'—':>10s} {'—':>10s} {res['us_per_step'][ref]:9.1f}")
    for k, v in res["excess_mse_pct"].items():
        print(
            f"{k:28s} {v:+12.1f}% {res['excess_mse_pos_pct'][k]:+9.1f}% "
            f"{res['predicted_excess_pct'][k]:+9.1f}% {res['us_per_step'][k]:9.1f}"
        )
    print(f"tuned beta online: {np.round(res['beta_tuned_online'], 4).tolist()}")
    if "beta_tuned_offline" in res:
        print(f"tuned beta offline: {np.round(res['beta_tuned_offline'], 4).tolist()}")
    if "observer_vs_replay_max_abs_diff" in res:
        print(f"ObserverPredictor vs replay KF, max |dx|: {res['observer_vs_replay_max_abs_diff']:.2e}")
    if "offline_trP_growth_100_to_end" in res:
        print(
            "offline covariance trace, end / step 100: "
            f"{res['offline_trP_growth_100_to_end']:.1f}x (diverges)"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--exact", choices=["auto", "own"], default="auto")
    args = ap.parse_args()
    if args.runs < 1 or args.steps <= BURN:
        ap.error(f"need --runs >= 1 and --steps > {BURN}")
    op_mod = load_observer_predictor(args.exact)
    out = {
        "runs": args.runs,
        "steps": args.steps,
        "burn_in": BURN,
        "max_delay": D,
        "delay_pmf": DELAY.delay_pmf.tolist(),
        "loss": DELAY.loss_probability,
    }
    for prof in (cv_profile(), stable_profile()):
        res = run_profile(prof, args.runs, args.steps, op_mod)
        print_table(prof.name, res)
        out[prof.name] = res
    log("offline sensitivity sweep (covariance only)")
    sens = offline_sensitivity(args.steps)
    print("\n== stationary offline (beta=2^-i) vs exact: expected MSE excess, A = radius Rot(theta)")
    print(f"{'radius':>7s} {'theta':>6s} {'R':>5s} {'offline':>9s}")
    for x in sens:
        print(f"{x['radius']:7.2f} {x['theta']:6.2f} {x['R']:5.2f} {x['offline_excess_pct']:+8.0f}%")
    out["offline_sensitivity"] = sens
    print(json.dumps(out))


if __name__ == "__main__":
    main()
