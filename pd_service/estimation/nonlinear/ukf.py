"""Unscented observer-predictor, optionally with adaptive process noise (MIT rule, Sage-Husa).

Same semantics as :class:`~pd_service.estimation.observer.ObserverPredictor` (accept window,
late / future / duplicate refusal, counters, commands, ``predict(now)`` = mean and covariance of
x(now + lead)), on the shared :class:`~pd_service.estimation.replay.ReplayEstimator`; only the
filter inside is the UKF of :mod:`.unscented`.

Adaptation and replay. Q may only change on the *committed* horizon (steps before
``committed_step``, whose packets are final)::

    committed: x(s), q(s) of the adaptive filter     |  open window: UKF with q frozen
    ... s1 -- s2 -- s3 (innovations -> adapter) ---- c ---- s4 -- s5 ---- now ---- now + lead

When steps become final, :meth:`_on_commit` re-runs them from the previous committed state
with sensitivities, feeds each innovation to the adapter (which may change Q for the steps
after it) and installs the result as the new base; if Q (or the base) changed, the open window
is replayed with the new, frozen Q. Hence ``predict(now)`` equals, to rounding, a from-scratch
run over the accepted packets in stamp order: the adaptive UKF over every packet stamped before
``now - max_delay``, then the plain UKF with the last q over the rest, then the prediction.
Late packets are refused by the window, so they never enter the innovation statistics.
Samples taken inside a step (a packet's ``offset``) are applied at their own time
(:mod:`.events`); the adapter learns from the innovations of the samples at the steps'
starts only.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from ..checks import as_covariance, as_vector
from ..estimator_state import EstimatorState, StateError
from ..replay import Packet, ReplayEstimator
from .adaptive import Adapter
from .events import split_packets, splits, step_inputs
from .registry import NonlinearModel, wrap_angle
from .sigma import SigmaWeights
from .unscented import ModelOps, UKFState, UnscentedBackend


class UnscentedObserverPredictor(ReplayEstimator[UKFState]):
    """UKF observer-predictor of x(now + lead) from delayed, multi-rate, lossy packets.

    Example::

        model = make_model("omni3")
        op = UnscentedObserverPredictor(model, x0=np.zeros(6), P0=1e-4 * np.eye(6), lead=10,
                                        max_delay=12,
                                        adapter=make_adapter({"method": "mit",
                                                              "indices": [3, 4, 5]},
                                                             model.Q, [3]))
        op.add_command(step=j, u=tau)                    # wheel torques from step j on
        op.add_measurement("pose", step=s, z=z, now=k)
        pred = op.predict(now=k)                         # x, P of x(k + lead)

    Parameters: ``sensors`` selects (and orders) the model's sensors (default: all);
    ``sigma`` the sigma-point weights (default alpha = 1, beta = 2, kappa = 0); ``adapter`` an
    :class:`~.adaptive.Adapter` bound to this model's Q (None: the plain UKF);
    ``Q_schedule`` a known process noise k -> Q(k) (n, n) for each step k -> k+1 instead of the
    model's constant Q (oracles, known terrain); not together with an adapter.
    """

    def __init__(
        self,
        model: NonlinearModel,
        x0: object,
        P0: object,
        lead: int,
        max_delay: int,
        command_hold: str = "hold",
        *,
        sensors: Sequence[str] | None = None,
        sigma: SigmaWeights | None = None,
        adapter: Adapter | None = None,
        Q_schedule: Callable[[int], np.ndarray] | None = None,
    ) -> None:
        if not isinstance(model, NonlinearModel):
            raise ValueError("model: expected a NonlinearModel (see make_model)")
        names = list(model.sensors) if sensors is None else list(sensors)
        if not names:
            raise ValueError("sensors: the model has no sensors / none selected")
        if len(set(names)) != len(names):
            raise ValueError(f"sensors: duplicate names in {names}")
        for name in names:
            if name not in model.sensors:
                raise ValueError(f"sensors: unknown sensor {name!r} (model has {list(model.sensors)})")
        n = model.n
        x = as_vector(x0, "x0", n)
        if model.angles:
            x[list(model.angles)] = wrap_angle(x[list(model.angles)])
        P = as_covariance(P0, "P0", n)
        Q = as_covariance(model.Q, "model.Q", n)
        if sigma is None:
            sigma = SigmaWeights.make(n)
        elif not isinstance(sigma, SigmaWeights) or sigma.n != n:
            raise ValueError(f"sigma: expected SigmaWeights for n={n}")
        if Q_schedule is not None:
            if adapter is not None:
                raise ValueError("Q_schedule: a known Q schedule and an adapter exclude each other")
            if not callable(Q_schedule):
                raise ValueError("Q_schedule: expected a function step -> Q (n, n)")
            Q_schedule = _checked_schedule(Q_schedule, n)
        dQ = None
        idx: tuple[int, ...] = ()
        if adapter is not None:
            idx = tuple(adapter.indices)
            if any(not 0 <= i < n for i in idx):
                raise ValueError(f"adapter: indices {list(idx)} out of range for n={n}")
            if adapter.needs_sensitivities:
                dQ = np.zeros((len(idx), n, n))
                for j, i in enumerate(idx):
                    dQ[j, i, i] = 1.0  # dQ / dq_m = e_m e_m^T
        tracked = dQ is not None
        initial = UKFState(x, P, np.zeros((len(idx), n)) if tracked else None,
                           np.zeros((len(idx), n, n)) if tracked else None)
        backend = UnscentedBackend(ModelOps(model, names), sigma, Q, dQ, Q_schedule)
        super().__init__(
            backend=backend,
            initial=initial,
            sensor_dims={name: model.sensors[name].m for name in names},
            nu=model.nu,
            lead=lead,
            max_delay=max_delay,
            command_hold=command_hold,
        )
        self.model = model
        self.adapter = adapter
        self._ukf = backend  # self._backend, with its own type
        backend.inputs_at = self._inputs_at
        # seconds a sample may lie inside a step; 0.0: a model without flow takes none
        self.period_s = model.period_s if splits(model) else 0.0
        self._prev_base: tuple[int, UKFState] = (self._base_step, self._base)
        self._last_update = 0  # newest committed measured step (0 before any): gaps count from it

    @property
    def n(self) -> int:
        return self.model.n

    @property
    def Q(self) -> np.ndarray:
        """Process noise in use now (the adapted one, frozen over the open window), (n, n)."""
        return self._ukf.Q.copy()

    @property
    def q(self) -> np.ndarray:
        """The adapted diagonal entries of Q (empty without an adapter)."""
        if self.adapter is None:
            return np.zeros(0)
        return np.diag(self._ukf.Q)[list(self.adapter.indices)].copy()

    def _inputs_at(self, k: int) -> tuple[np.ndarray, tuple[float, np.ndarray] | None]:
        return step_inputs(self._inputs, k)

    def set_Q(self, Q: object) -> None:
        """Replace the process noise for every step not yet committed (the open window is
        replayed with it). For oracles and operator overrides; an adapter continues from it."""
        Qm = as_covariance(Q, "Q", self.n)
        if self.adapter is not None and np.any(np.diag(Qm)[list(self.adapter.indices)] <= 0):
            raise ValueError("Q: adapted diagonal entries must stay > 0")
        self._ukf.Q = Qm
        self.invalidate_from(self._c)

    # --- export / restore ------------------------------------------------------------------

    def _export_extras(self) -> dict[str, np.ndarray]:
        """"Q" (n, n) in use and "last_update" (1,); with an adapter, its memory ("adapter.*")."""
        out = {"Q": self._ukf.Q.copy(), "last_update": np.array([self._last_update])}
        if self.adapter is not None:
            out.update({f"adapter.{k}": v for k, v in self.adapter.export_memory().items()})
        return out

    def _restore_extras(self, extras: dict[str, np.ndarray]) -> None:
        n = self.n
        if "Q" not in extras:
            raise StateError("extras.Q: missing")
        try:
            Q = as_covariance(extras["Q"], "Q", n)
        except ValueError as exc:
            raise StateError(f"extras: {exc}") from None
        lu = np.asarray(extras.get("last_update", []))
        if lu.shape != (1,) or not float(lu[0]).is_integer() or lu[0] < 0:
            raise StateError("extras.last_update: expected one step >= 0")
        memory = {k[len("adapter."):]: v for k, v in extras.items() if k.startswith("adapter.")}
        unknown = set(extras) - {"Q", "last_update"} - {f"adapter.{k}" for k in memory}
        if unknown:
            raise StateError(f"extras: unexpected {sorted(unknown)}")
        if self.adapter is None:
            if memory:
                raise StateError("extras: adapter memory for an estimator without adapter")
            if not np.array_equal(Q, self._ukf.Q):
                raise StateError("extras.Q: differs from the model's Q (no adapter)")
        else:
            self.adapter.restore_memory(memory)  # checks first, StateError if it does not fit
        self._ukf.Q = Q
        self._last_update = int(lu[0])

    def restore_state(self, state: EstimatorState) -> None:
        super().restore_state(state)
        self._prev_base = (self._base_step, self._base)

    # --- committed-horizon adaptation ----------------------------------------------------

    def _advance(self, now: int) -> None:
        self._prev_base = (self._base_step, self._base)
        super()._advance(now)

    def _on_commit(self, committed: list[tuple[int, UKFState, list[Packet]]]) -> None:
        if self.adapter is None:
            return
        backend = self._ukf
        Q_before = backend.Q
        a, state = self._prev_base
        for s, _, packets in committed:
            if s > a:
                state = backend.propagate(state, a, s - a, self._inputs.slice(a, s - a))
            state, rec = backend.update_tracked(state, s, packets, s - self._last_update)
            # samples inside step s: the state handed on is x(s + 1)
            a = s + 1 if split_packets(packets, splits(self.model))[1] else s
            if rec is None:  # only samples taken inside the step: nothing for the adapter
                continue
            self._last_update = s
            Qn = self.adapter.observe(rec, backend.Q)
            if Qn is not None:
                backend.Q = Qn  # used from the step after s on
        frozen = committed[-1][1]  # what the window computed with Q frozen
        self._base = state
        if (backend.Q is not Q_before or not np.array_equal(state.x, frozen.x)
                or not np.array_equal(state.P, frozen.P)):
            self.invalidate_from(self._c)  # every open posterior depends on the base and Q


def _checked_schedule(fn: Callable[[int], np.ndarray], n: int) -> Callable[[int], np.ndarray]:
    def checked(k: int) -> np.ndarray:
        Q = np.asarray(fn(k), dtype=float)
        if Q.shape != (n, n) or not np.all(np.isfinite(Q)):
            raise ValueError(f"Q_schedule({k}): expected a finite {n}x{n} matrix")
        return Q

    return checked

