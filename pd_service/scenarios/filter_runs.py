"""Estimators driven through simulated runs, scored against the truth: the adaptive-UKF
runs of the omni robot (:func:`run_filter`), the IMM Monte Carlo of the tracking
scenario (:func:`monte_carlo`) and the asynchronous robot's predictions under each way of
stamping its samples (:func:`drive_async`). The simulators are :mod:`.omni`,
:mod:`.tracking` and :mod:`.asynchronous`; the estimators are :mod:`pd_service.estimation`'s."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from pd_service.estimation.imm.filter import ImmFilter, ImmState
from pd_service.estimation.imm.models import heading
from pd_service.estimation.nonlinear import UnscentedObserverPredictor, wrap_angle

from .asynchronous import AsyncRun
from .omni import OmniRun
from .tracking import TrackingScenario, Variant, simulate

# --- the omni robot: one unscented observer-predictor over one run ----------------------


@dataclass
class Track:
    """Per-step results of one filter over one run: ``pos_err2`` (K+1,) squared position error
    of the filtered x(k) (m^2); ``theta_err`` (K+1,) wrapped heading error (rad); ``q`` (K+1, p)
    the adapted entries of Q after step k (the fixed ones for a plain UKF)."""

    pos_err2: np.ndarray
    theta_err: np.ndarray
    q: np.ndarray


def run_filter(op: UnscentedObserverPredictor, run: OmniRun,
               indices: Sequence[int] = (3, 4, 5)) -> Track:
    """Drive an unscented observer-predictor (lead 0) through ``run``: at each step k the
    command u(k), the packets arriving at k, then ``predict(k)``."""
    K = run.steps
    by_arrival: dict[int, list[int]] = {}
    for s, a in enumerate(run.arrival):
        if a >= 0:
            by_arrival.setdefault(int(a), []).append(s)
    err2 = np.empty(K + 1)
    th = np.empty(K + 1)
    qs = np.empty((K + 1, len(indices)))
    idx = list(indices)
    for k in range(K + 1):
        op.add_command(k, run.u[k], now=k)
        for s in by_arrival.get(k, ()):
            op.add_measurement("pose", s, run.z[s], now=k)
        p = op.predict(k)
        err2[k] = float(np.sum((p.x[:2] - run.truth[k, :2]) ** 2))
        th[k] = float(wrap_angle(p.x[2] - run.truth[k, 2]))
        qs[k] = np.diag(op.Q)[idx]
    return Track(err2, th, qs)


# --- the tracking scenario: IMM variants over many runs ---------------------------------

#: The compared methods: key -> (variant, node). "single" uses station 1; UIF-IMM 1 reports
#: node 1 (station 1's node).
METHODS: dict[str, tuple[Variant, int]] = {
    "single": ("single", 0),
    "centralised": ("centralised", 0),
    "imm1": ("imm1", 0),
    "imm2": ("imm2", 0),
}


@dataclass(frozen=True, eq=False)
class MonteCarlo:
    """Per-run, per-step results of :func:`monte_carlo` (steps 1..K, shape (runs, K) unless
    said otherwise): squared position error ``pos2`` (m^2), squared heading error ``head2``
    (rad^2), probability of the wrong mode ``wrong``, P(CT) ``p_ct``; ``imm1_nodes_pos2``
    (runs, S, K) for every UIF-IMM 1 node; ``track`` (K+1, 2) run 0's position estimate."""

    pos2: dict[str, np.ndarray]
    head2: dict[str, np.ndarray]
    wrong: dict[str, np.ndarray]
    p_ct: dict[str, np.ndarray]
    imm1_nodes_pos2: np.ndarray | None
    track: dict[str, np.ndarray]

    def rms_position(self, key: str) -> float:
        return float(np.sqrt(self.pos2[key].mean()))

    def rms_heading_deg(self, key: str) -> float:
        return float(np.degrees(np.sqrt(self.head2[key].mean())))

    def p_wrong(self, key: str) -> float:
        return float(self.wrong[key].mean())


def monte_carlo(scn: TrackingScenario, runs: int, seed: int,
                methods: dict[str, tuple[Variant, int]] | None = None,
                steps: int | None = None,
                progress: Callable[[int, int], object] | None = None) -> MonteCarlo:
    """Run each method over the same random numbers (:func:`.tracking.simulate`, vectorised
    over runs).

    ``steps`` truncates the scenario; ``progress(k, K)`` is called every 500 steps.
    """
    methods = METHODS if methods is None else methods
    x0, Z = simulate(scn, runs, seed)
    K = scn.steps if steps is None else min(int(steps), scn.steps)
    S = len(scn.sensors)
    filters = {key: ImmFilter(scn.modes, scn.transition, scn.sensors, variant, node=node)
               for key, (variant, node) in methods.items()}
    states: dict[str, ImmState] = {key: f.initial_state(x0, scn.P0, batch=(runs,))
                                   for key, f in filters.items()}
    pos2 = {key: np.zeros((runs, K)) for key in filters}
    head2 = {key: np.zeros((runs, K)) for key in filters}
    wrong = {key: np.zeros((runs, K)) for key in filters}
    p_ct = {key: np.zeros((runs, K)) for key in filters}
    track = {key: np.zeros((K + 1, 2)) for key in filters}
    nodes = np.zeros((runs, S, K)) if "imm1" in filters else None
    for key in filters:
        track[key][0] = x0[0, [0, 2]]
    for k in range(K):
        truth = scn.truth[k + 1]
        obs = [(s, Z[:, k + 1, s], None) for s in range(S)]
        for key, f in filters.items():
            st = f.update(f.predict(states[key], k), obs)
            states[key] = st
            x, _ = f.output(st)
            pos2[key][:, k] = (x[:, 0] - truth[0]) ** 2 + (x[:, 2] - truth[2]) ** 2
            head2[key][:, k] = wrap_angle(heading(x) - heading(truth)) ** 2
            mu = f.probabilities(st)
            wrong[key][:, k] = mu[:, 0] if scn.turning[k + 1] else mu[:, 1]
            p_ct[key][:, k] = mu[:, 1]
            track[key][k + 1] = x[0, [0, 2]]
            if key == "imm1" and nodes is not None:
                for nd in range(f.n_nodes):
                    xn, _ = f.output(st, nd)
                    nodes[:, nd, k] = (xn[:, 0] - truth[0]) ** 2 + (xn[:, 2] - truth[2]) ** 2
        if progress is not None and (k + 1) % 500 == 0:
            progress(k + 1, K)
    return MonteCarlo(pos2, head2, wrong, p_ct, nodes, track)


# --- the asynchronous robot: where each sample is applied ------------------------------

#: How a sample taken at t (s after the epoch) is stamped: "exact" step floor(t / T) and
#: the offset t - step T inside it; "floor" the step floor(t / T) (offset 0: how stamps were
#: applied before issue 42); "nearest" the step round(t / T); "fine" the filter's step is
#: T / sub and the sample its nearest fine step (the continuous limit as sub grows).
STAMP_MODES = ("exact", "floor", "nearest", "fine")


def stamp(t_s: float, period_s: float, mode: str) -> tuple[int, float]:
    """(step, offset s) of a sample taken at ``t_s`` for a filter of step ``period_s``."""
    if mode == "exact":
        k = math.floor(t_s / period_s)
        return k, max(0.0, t_s - k * period_s)
    if mode in ("floor",):
        return math.floor(t_s / period_s), 0.0
    if mode in ("nearest", "fine"):
        return math.floor(t_s / period_s + 0.5), 0.0
    raise ValueError(f"mode: expected one of {STAMP_MODES}, got {mode!r}")


@dataclass(frozen=True, eq=False)
class AsyncTrack:
    """Per-tick results of :func:`drive_async` (ticks k = 0..K-1): ``pred`` (K, n) the
    prediction of x((k + lead) T) made at k T, ``truth`` (K, n) that true state, ``target``
    (K,) the steps k + lead, ``counters`` the estimator's counters at the end, ``offered``
    the number of samples offered to it (those that arrived by the last tick)."""

    pred: np.ndarray
    truth: np.ndarray
    target: np.ndarray
    counters: dict[str, int]
    offered: int


def drive_async(op: UnscentedObserverPredictor, run: AsyncRun, mode: str, period_s: float,
                lead: int, sub: int = 1) -> AsyncTrack:
    """Drive ``op`` (step ``period_s`` / ``sub``, lead ``lead`` * ``sub``) through ``run``:
    at each tick k (time k T, T = ``period_s``): the command u(k + lead) (the one sent now,
    acting at the predicted step; u(0..lead-1) before the first tick), the samples that
    arrived in ((k-1) T, k T], stamped by ``mode``, then the prediction of x((k + lead) T).
    Ticks run while k + lead <= the run's steps."""
    K = run.steps - lead + 1
    samples = run.samples
    i = 0
    fine_T = period_s / sub
    preds, truths = [], []
    for j in range(lead):
        op.add_command(j * sub, run.u[j], now=0)
    for k in range(K):
        now = k * sub
        if k + lead < run.steps:
            op.add_command((k + lead) * sub, run.u[k + lead], now=now)
        while i < len(samples) and samples[i].arrival_s <= k * period_s + 1e-12:
            smp = samples[i]
            i += 1
            step, off = stamp(smp.t_s, fine_T, mode)
            if off:
                op.add_measurement(smp.sensor, step, smp.z, now=now, offset=off)
            else:
                op.add_measurement(smp.sensor, step, smp.z, now=now)
        p = op.predict(now)
        preds.append(np.array(p.x))
        truths.append(run.truth[k + lead])
    return AsyncTrack(np.array(preds), np.array(truths), np.arange(K) + lead, op.counters, i)
