"""Baselines with the same API as :class:`~pd_service.estimation.ObserverPredictor`.

* :class:`AugmentedStateKF`: the classical augmented-state Kalman filter, with the state
  stacked with its last ``max_delay`` values and dense augmented matrices, as in textbooks.
  Exact too, but its cost grows with (n * max_delay)^3.
* :class:`ConventionalPredictor`: the conventional predictive display the paper compares
  against (its Figs. 9-11): one sensor group with one delay; a Kalman filter that takes that
  sensor's samples in order, then an open-loop predictor over delay + uplink. It cannot use
  other sensors, and a sample that arrives out of order is dropped as late.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pd_service.estimation.checks import as_covariance, as_step, as_vector
from pd_service.estimation.inputs import InputBuffer
from pd_service.estimation.linear import LinearState, PropagationTables, tables_for
from pd_service.estimation.model import LinearModel, Sensor, check_sensors
from pd_service.estimation.replay import COUNTER_NAMES, PredictedState
from pd_service.estimation.tally import Tally


def propagate(tables: PropagationTables, nu: int, x: np.ndarray, P: np.ndarray,
              U: np.ndarray) -> LinearState:
    """Roll (x, P) forward len(U) steps with inputs U (m, nu); m may exceed the table (the
    baselines' textbook form; the daemon's estimator runs LinearBackend's step)."""
    m = U.shape[0]
    M = tables.M
    while m > M:  # a jump longer than the tables: in table-sized chunks
        x, P = propagate(tables, nu, x, P, U[:M])
        U = U[M:]
        m -= M
    Am = tables.Apow[m]
    x = Am @ x
    if nu:
        # [A^{m-1}B ... B] is the last m*nu columns of the full stacked matrix.
        x = x + tables.Gfull[:, (M - m) * nu :] @ U.reshape(-1)
    P = Am @ P @ Am.T + tables.Qsum[m]
    return x, P


def kalman_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, R: np.ndarray,
                  z: np.ndarray) -> LinearState:
    """Condition N(x, P) on z = H x + v, v ~ N(0, R).

        S = H P H^T + R,   K = P H^T S^{-1}
        x+ = x + K (z - H x),   P+ = P - K H P   (symmetrised)

    A singular S (zero R on a direction P already knows exactly) uses the pseudo-inverse,
    which is still the LMMSE gain.
    """
    PHt = P @ H.T
    S = H @ PHt + R
    if S.shape[0] == 1:
        s = S[0, 0]
        K = PHt / s if s > 0.0 else PHt * 0.0
    else:
        try:
            K = np.linalg.solve(S, PHt.T).T
        except np.linalg.LinAlgError:
            K = PHt @ np.linalg.pinv(S)
    x = x + K @ (z - H @ x)
    P = P - K @ PHt.T
    return x, 0.5 * (P + P.T)


class _InputsMixin:
    """Command window shared by the baselines: commands for steps >= the filter's step."""

    model: LinearModel
    _now: int  # the filter's step

    def _advance(self, now: int) -> None:
        """Run the filter up to step ``now`` (each baseline's own)."""
        raise NotImplementedError

    def _init_inputs(self, model: LinearModel, lead: int, max_delay: int, hold: str) -> None:
        if hold not in ("hold", "zero"):
            raise ValueError(f"command_hold: must be 'hold' or 'zero', got {hold!r}")
        self._ahead = lead + max_delay + 1
        self._inputs = InputBuffer(model.nu, 2 * (lead + max_delay) + 4, hold=hold == "hold")
        self._tables = tables_for(model, self._inputs.capacity)
        self._counters = Tally({k: 0 for k in COUNTER_NAMES})

    @property
    def counters(self) -> dict[str, int]:
        return dict(self._counters)

    def add_command(self, step: int, u: object, now: int | None = None) -> bool:
        step = as_step(step, "step")
        uv = as_vector(u, "u", self.model.nu)
        if now is not None:
            self._advance(as_step(now, "now"))
        return self._inputs.admit(step, uv, self._inputs.origin, self._now + self._ahead,
                                  self._counters)


class AugmentedStateKF(_InputsMixin):
    """Augmented-state Kalman filter over X(T) = [x(T); x(T-1); ...; x(T-D)], D = max_delay.

        X(T+1) = F X(T) + G u(T) + W,   F = [[A, 0 .. 0], [I, 0 .. 0], ..., [0 .. I, 0]]
        z_i(s) = H_i x(s) + v = [0 .. H_i (block T-s) .. 0] X(T) + v

    Packets are applied in arrival order; T follows ``now``. Commands for steps before T are
    refused as late (the filter has already moved past them).
    """

    def __init__(
        self,
        model: LinearModel,
        sensors: Sequence[Sensor],
        x0: object,
        P0: object,
        lead: int,
        max_delay: int,
        command_hold: str = "hold",
    ) -> None:
        self.model, self.sensors = model, check_sensors(model, sensors)
        self.lead, self.max_delay = as_step(lead, "lead"), as_step(max_delay, "max_delay")
        n, D = model.n, self.max_delay
        N = n * (D + 1)
        self._index = {s.name: i for i, s in enumerate(self.sensors)}
        self._init_inputs(model, self.lead, D, command_hold)
        x0v, P0m = as_vector(x0, "x0", n), as_covariance(P0, "P0", n)
        # Blocks for steps before 0 are placeholders: no packet can refer to them.
        self._X = np.tile(x0v, D + 1)
        self._P = np.kron(np.eye(D + 1), P0m)
        self._F = np.zeros((N, N))
        self._F[:n, :n] = model.A
        self._F[n:, :-n] = np.eye(N - n)
        self._G = np.zeros((N, model.nu))
        self._G[:n] = model.B
        self._Qa = np.zeros((N, N))
        self._Qa[:n, :n] = model.Q
        self._now = 0
        self._seen: set[tuple[int, int]] = set()
        self._newest: int | None = None

    def _advance(self, now: int) -> None:
        if now < self._now:
            raise ValueError(f"now: went backwards ({now} < {self._now})")
        while self._now < now:
            u = self._inputs.slice(self._now, 1)[0]
            self._X = self._F @ self._X + self._G @ u
            self._P = self._F @ self._P @ self._F.T + self._Qa
            self._now += 1
            self._inputs.advance(self._now)
        lo = self._now - self.max_delay
        self._seen = {k for k in self._seen if k[1] >= lo}

    def add_measurement(self, sensor: str, step: int, z: object, now: int,
                        R: object | None = None) -> bool:
        idx = self._index.get(sensor)
        if idx is None:
            raise ValueError(f"sensor: unknown sensor {sensor!r}")
        s = self.sensors[idx]
        step, now = as_step(step, "step"), as_step(now, "now")
        zv = as_vector(z, "z", s.m)
        Rm = s.R if R is None else as_covariance(R, "R", s.m)
        self._advance(now)
        if step > now:
            self._counters["future"] += 1
            return False
        if step < now - self.max_delay or step < 0:
            self._counters["late"] += 1
            return False
        if (idx, step) in self._seen:
            self._counters["duplicate"] += 1
            return False
        n = self.model.n
        b = now - step
        Ha = np.zeros((s.m, self._X.shape[0]))
        Ha[:, b * n : (b + 1) * n] = s.H
        self._X, self._P = kalman_update(self._X, self._P, Ha, Rm, zv)
        self._seen.add((idx, step))
        self._newest = step if self._newest is None else max(self._newest, step)
        self._counters["accepted"] += 1
        return True

    def predict(self, now: int) -> PredictedState:
        self._advance(as_step(now, "now"))
        n = self.model.n
        x, P = self._X[:n], self._P[:n, :n]
        if self.lead:
            x, P = propagate(self._tables, self.model.nu, x, P,
                             self._inputs.slice(self._now, self.lead))
        return PredictedState(self._now + self.lead, x.copy(), P.copy(), self._newest)


class ConventionalPredictor(_InputsMixin):
    """Conventional predictive display: one sensor, one delay, samples taken in order.

        filter:    x(s | s) by a Kalman filter over the sensor's samples in arrival order
        predictor: x(now + lead | s) = roll forward over the delay and the uplink (eq. 34)

    Other sensors raise ValueError as unknown; a sample stamped at or before the newest one
    already used is refused as late (the conventional scheme cannot re-order).
    """

    def __init__(self, model: LinearModel, sensor: Sensor, x0: object, P0: object,
                 lead: int, max_delay: int, command_hold: str = "hold") -> None:
        self.model, self.sensor = model, check_sensors(model, [sensor])[0]
        self.lead, self.max_delay = as_step(lead, "lead"), as_step(max_delay, "max_delay")
        self._init_inputs(model, self.lead, self.max_delay, command_hold)
        self._x = as_vector(x0, "x0", model.n)
        self._P = as_covariance(P0, "P0", model.n)
        self._t = 0  # the filter holds x(_t | samples stamped < _t ... or <= _t if _used)
        self._used = False
        self._now = 0

    def _advance(self, now: int) -> None:
        if now < self._now:
            raise ValueError(f"now: went backwards ({now} < {self._now})")
        self._now = now
        # No sample older than now - max_delay can be accepted any more: roll up to it.
        self._roll_to(now - self.max_delay)

    def _roll_to(self, step: int) -> None:
        if step > self._t:
            self._x, self._P = propagate(self._tables, self.model.nu, self._x, self._P,
                                         self._inputs.slice(self._t, step - self._t))
            self._t = step
            self._inputs.advance(step)
            self._used = False

    def add_measurement(self, sensor: str, step: int, z: object, now: int,
                        R: object | None = None) -> bool:
        if sensor != self.sensor.name:
            raise ValueError(f"sensor: unknown sensor {sensor!r}")
        step, now = as_step(step, "step"), as_step(now, "now")
        zv = as_vector(z, "z", self.sensor.m)
        Rm = self.sensor.R if R is None else as_covariance(R, "R", self.sensor.m)
        self._advance(now)
        if step > now:
            self._counters["future"] += 1
            return False
        if step < now - self.max_delay or step < self._t or (step == self._t and self._used):
            self._counters["late"] += 1
            return False
        self._roll_to(step)
        self._x, self._P = kalman_update(self._x, self._P, self.sensor.H, Rm, zv)
        self._used = True
        self._counters["accepted"] += 1
        return True

    def predict(self, now: int) -> PredictedState:
        self._advance(as_step(now, "now"))
        target = now + self.lead
        x, P = self._x, self._P
        if target > self._t:
            x, P = propagate(self._tables, self.model.nu, x, P,
                             self._inputs.slice(self._t, target - self._t))
        return PredictedState(target, x, P, self._t if self._used else None)
