"""IMM-UIF observer-predictor on the shared timestamp window and exact replay.

The backend state is the whole IMM posterior (:class:`~.filter.ImmState`: mode probabilities,
per-mode means and covariances, per node). The window keeps one per measured step plus the
raw packets, so a late packet for step s is inserted at s and steps s.. are re-run; the result
equals a from-scratch IMM run over every accepted packet in stamp order (see
:class:`~pd_service.estimation.replay.ReplayEstimator`).

Example::

    op = make_imm(modes=["imm_cv", "imm_ct"], transition=[[0.995, 0.005], [0.005, 0.995]],
                  sensors=[{"name": "st1", "kind": "range_bearing", "station": [9.5, -8.5],
                            "sigma_range": 0.3, "sigma_bearing": 0.061}],
                  variant="imm2", x0=x0, P0=P0, lead=5, max_delay=20)
    op.add_measurement("st1", step=s, z=[r, b], now=k)
    pred = op.predict(now=k)            # combined mean/cov of x(k + lead)
    modes = op.predict_modes(now=k)     # mode probabilities and per-mode moments
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..estimator_state import StateError, check_names, take
from ..nonlinear.events import segments, split_packets, splits, step_inputs
from ..nonlinear.unscented import InputsAt
from ..replay import Packet, ReplayEstimator
from .filter import ImmFilter, ImmState


class ImmBackend:
    """:class:`~pd_service.estimation.replay.Backend` over :class:`ImmState` (no batch axes).

    Packets with an offset inside their step are applied at their own time when every mode
    has a ``flow`` (:mod:`pd_service.estimation.nonlinear.events`): the modes interact at
    the step's start, then each part of the step is a prediction without interaction, each
    instant with samples an update, and :meth:`update` hands on x(step + 1)."""

    def __init__(self, filt: ImmFilter) -> None:
        self.filter = filt
        self.splits = all(splits(md) for md in filt.modes)
        self.inputs_at: InputsAt | None = None  # set by the estimator (see UnscentedBackend)

    def propagate(self, state: ImmState, step: int, m: int, U: np.ndarray) -> ImmState:
        """m IMM cycles without measurement (interaction + prediction; mu = cbar)."""
        f = self.filter
        for j in range(m):
            state = f.predict(state, step + j, U[j])
        return state

    def _through_step(self, state: ImmState, k: int, inside: list[Packet]) -> ImmState:
        """x(k) -> x(k+1) through the packets sampled inside step k (sorted by offset)."""
        f = self.filter
        if self.inputs_at is None:
            raise ValueError("samples inside a step need the estimator's inputs (inputs_at)")
        u, cut = self.inputs_at(k)
        first = True
        for t, tau, group in segments(inside, f.modes[0].period_s,
                                      None if cut is None else cut[0]):
            uk = u if cut is None or t >= cut[0] else cut[1]  # the command held at t
            state = f.predict(state, k, uk, tau=tau, interact=first)
            first = False
            if group:
                state = f.update(state, [(p.sensor, p.z, p.R) for p in group])
        return state

    def update(self, state: ImmState, step: int, packets: list[Packet]) -> ImmState:
        """Every packet stamped ``step`` at its start, fused on the step's one prior; with
        packets inside the step, then through it to x(step + 1)."""
        start, inside = split_packets(packets, self.splits)
        if start:
            state = self.filter.update(state, [(p.sensor, p.z, p.R) for p in start])
        return self._through_step(state, step, inside) if inside else state

    def moments(self, state: ImmState) -> tuple[np.ndarray, np.ndarray]:
        return self.filter.output(state)

    def export_state(self, state: ImmState) -> dict[str, np.ndarray]:
        """Mode probabilities "mu" (N, r), per-mode "x" (N, r, n) and "P" (N, r, n, n)."""
        return {"mu": state.mu.copy(), "x": state.x.copy(), "P": state.P.copy()}

    def import_state(self, arrays: dict[str, np.ndarray]) -> ImmState:
        f = self.filter
        N, r, n = f.n_nodes, f.r, f.n
        check_names(arrays, {"mu", "x", "P"})
        mu = take(arrays, "mu", (N, r))
        if np.any(mu < 0) or not np.allclose(mu.sum(axis=1), 1.0, atol=1e-9):
            raise StateError("base.mu: not a probability vector per node")
        return ImmState(mu, take(arrays, "x", (N, r, n)), take(arrays, "P", (N, r, n, n)))


@dataclass(frozen=True, slots=True)
class ImmPrediction:
    """IMM estimate of x(step) for the reported node: mu (r,), x (r, n), P (r, n, n) per
    mode, and the combined mean ``x_combined`` (n,) and covariance ``P_combined`` (n, n)."""

    step: int
    mu: np.ndarray
    x: np.ndarray
    P: np.ndarray
    x_combined: np.ndarray
    P_combined: np.ndarray


class ImmObserverPredictor(ReplayEstimator[ImmState]):
    """Exact IMM-UIF predictor of x(now + lead) from delayed, shuffled, lossy packets.

    Parameters
    ----------
    filt: the IMM recursion (modes, transition, sensors, variant); see :func:`.factory.make_imm`.
    x0, P0: initial estimate (n,), (n, n) positive definite, shared by every mode.
    mu0: initial mode probabilities (r,), uniform if None.
    lead, max_delay, command_hold: as for :class:`ReplayEstimator`.
    """

    def __init__(
        self,
        filt: ImmFilter,
        x0: object,
        P0: object,
        lead: int,
        max_delay: int,
        mu0: object | None = None,
        command_hold: str = "hold",
    ) -> None:
        if not isinstance(filt, ImmFilter):
            raise ValueError("filt: expected an ImmFilter")
        initial = filt.initial_state(x0, P0, mu0)
        super().__init__(
            backend=ImmBackend(filt),
            initial=initial,
            sensor_dims={s.name: s.m for s in filt.sensors},
            nu=filt.nu,
            lead=lead,
            max_delay=max_delay,
            command_hold=command_hold,
        )
        self.filter = filt
        backend = self._backend
        assert isinstance(backend, ImmBackend)
        backend.inputs_at = self._inputs_at
        # seconds a sample may lie inside a step; 0.0: modes without flow take none
        self.period_s = filt.modes[0].period_s if backend.splits else 0.0

    def _inputs_at(self, k: int) -> tuple[np.ndarray, tuple[float, np.ndarray] | None]:
        return step_inputs(self._inputs, k)

    @property
    def n(self) -> int:
        return self.filter.n

    @property
    def variant(self) -> str:
        return self.filter.variant

    def add_measurement(
        self, sensor: object, step: object, z: object, now: object, R: object | None = None,
        offset: object = 0.0,
    ) -> bool:
        """As :meth:`ReplayEstimator.add_measurement`; a per-sample R must also be positive
        definite (the information form uses R^{-1})."""
        if R is not None:
            try:
                Rm = np.array(R, dtype=float)
                ok = Rm.ndim == 2 and Rm.shape[0] == Rm.shape[1] and np.all(np.isfinite(Rm))
                ok = ok and float(np.linalg.eigvalsh(0.5 * (Rm + Rm.T))[0]) > 0.0
            except (TypeError, ValueError, np.linalg.LinAlgError):
                ok = False
            if not ok:
                raise ValueError("R: must be a finite, positive definite matrix")
        return super().add_measurement(sensor, step, z, now, R, offset)

    def predict_modes(self, now: int) -> ImmPrediction:
        """Mode probabilities and per-mode moments of x(now + lead) (reported node)."""
        pred = self.predict(now)  # validates now, advances, replays
        step, state, _ = self._newest(pred.step)
        if pred.step > step:
            state = self._propagate(state, step, pred.step - step)
        k = self.filter._node_index(None)
        return ImmPrediction(
            step=pred.step,
            mu=state.mu[k].copy(),
            x=state.x[k].copy(),
            P=state.P[k].copy(),
            x_combined=pred.x,
            P_combined=pred.P,
        )

