"""IMM of unscented information filters with multi-sensor fusion, batched.

One cycle per step k (Blom and Bar-Shalom; mode filters are UIFs, Lee 2008)::

    1. interaction   cbar, x0_j, P0_j = mix(mu, x_j, P_j, Pi)              (see mixing.py)
    2. prediction    x-_j, P-_j = unscented prior of mode model j from (x0_j, P0_j)
    3. update        Y_j = Y-_j + sum_s I_s,j ;  y_j = y-_j + sum_s i_s,j   (see uif.py)
    4. probability   mu_j ∝ cbar_j Lambda_j                                 (log space)
    5. output        x = sum_j mu_j x_j, P = ... (mixture moments)

A step with no measurement is 1-2 only, with mu = cbar (Lambda = 1): :meth:`ImmFilter.predict`
is one step of 1-2, :meth:`ImmFilter.update` is 3-4 on a predicted state.

Variants (how the sensors are fused; the state update is always the sum of the used sensors'
contributions on one prior):

* ``"single"``       only sensor ``node`` is used; Lambda_j from it.
* ``"centralised"``  all sensors stacked; Lambda_j = N(nu; 0, H P- H^T + blockdiag(R)), the
                     joint likelihood (cross-covariances through the common prior included).
* ``"imm1"``         UIF-IMM 1: one IMM per sensor node (node s owns sensor s); each node adds
                     every sensor's contribution on its own prior, but its mode likelihood is
                     only its own sensor's, Lambda_j^(s) = N(nu_s; 0, S_s). Nodes run apart.
                     The reported estimate is node ``node``.
* ``"imm2"``         UIF-IMM 2: likelihoods fused, Lambda_j = prod_s N(nu_s; 0, S_s) (eq. 19),
                     so every node is the same and one IMM is run.

The product of marginals in ``imm2`` ignores that the sensors' innovations are correlated
through the shared prior; ``centralised`` uses the exact joint. ``imm2`` can therefore only
approximate, never improve on, ``centralised``.

State layout: :class:`ImmState` with a node axis (size 1 except for ``imm1``) after any batch
axes: mu (..., N, r), x (..., N, r, n), P (..., N, r, n, n).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..checks import as_covariance, as_vector
from ..nonlinear.registry import MeasurementModel, NonlinearModel, TransitionFn
from . import uif
from .mixing import check_transition, combine, mix, posterior_probabilities
from .unscented import Array, apply_rows, sigma_points, unscented_propagate, weights

VARIANTS = ("single", "centralised", "imm1", "imm2")


@dataclass(frozen=True, eq=False)
class ImmState:
    """IMM posterior (or prior, after :meth:`ImmFilter.predict`).

    mu (..., N, r) mode probabilities; x (..., N, r, n) per-mode means;
    P (..., N, r, n, n) per-mode covariances. N = number of nodes.
    """

    mu: np.ndarray
    x: np.ndarray
    P: np.ndarray


#: One measurement: (sensor index, z (..., m), R (m, m) or None for the sensor's own R).
Observation = tuple[int, np.ndarray, np.ndarray | None]


class ImmFilter:
    """The IMM-UIF recursion over arbitrary batch axes (MC runs in a bench, none in a session).

    Parameters
    ----------
    modes: mode models (same state size n and input size nu), e.g. [imm_cv, imm_ct].
    transition: (r, r) Markov matrix, row i = P(next mode | mode i).
    sensors: measurement models; sensor index = position in this list.
    variant: one of :data:`VARIANTS`.
    node: for ``single``, the sensor used; for ``imm1``, the node reported by :meth:`output`.
    kappa: sigma-point scaling (n + kappa > 0).
    """

    def __init__(
        self,
        modes: Sequence[NonlinearModel],
        transition: object,
        sensors: Sequence[MeasurementModel],
        variant: str = "imm2",
        node: int = 0,
        kappa: float = 0.0,
    ) -> None:
        modes = list(modes)
        sensors = list(sensors)
        if not modes:
            raise ValueError("modes: at least one mode model is required")
        for md in modes:
            if not isinstance(md, NonlinearModel):
                raise ValueError("modes: expected NonlinearModel objects")
        n, nu = modes[0].n, modes[0].nu
        for md in modes:
            if md.n != n or md.nu != nu:
                raise ValueError(
                    f"modes: all modes need the same n and nu ({md.name!r} has n={md.n}, "
                    f"nu={md.nu}; expected n={n}, nu={nu})"
                )
        if not sensors:
            raise ValueError("sensors: at least one sensor is required")
        for s in sensors:
            if not isinstance(s, MeasurementModel):
                raise ValueError("sensors: expected MeasurementModel objects")
        names = [s.name for s in sensors]
        if len(set(names)) != len(names):
            raise ValueError(f"sensors: duplicate names in {names}")
        if variant not in VARIANTS:
            raise ValueError(f"variant: expected one of {VARIANTS}, got {variant!r}")
        if isinstance(node, bool) or not isinstance(node, (int, np.integer)):
            raise ValueError(f"node: expected an integer, got {node!r}")
        if not 0 <= node < len(sensors):
            raise ValueError(f"node: must be in [0, {len(sensors)}), got {node}")
        kappa = float(kappa)
        weights(n, kappa)  # validates n + kappa > 0
        self.modes = modes
        self.sensors = sensors
        self.Pi = check_transition(transition, len(modes))
        self.variant = variant
        self.node = int(node)
        self.kappa = kappa
        self.n, self.nu, self.r = n, nu, len(modes)
        self.n_nodes = len(sensors) if variant == "imm1" else 1
        self._w = weights(n, kappa)
        self._vec_modes = [md.vectorized for md in modes]

    # --- state construction ----------------------------------------------------------------

    def initial_state(
        self, x0: object, P0: object, mu0: object | None = None, batch: tuple[int, ...] = ()
    ) -> ImmState:
        """Every mode (and node) starts at N(x0, P0) with probabilities mu0 (uniform if None).

        x0 (n,) or (*batch, n) for a per-run initial estimate; P0 (n, n) positive definite.
        """
        n, r, N = self.n, self.r, self.n_nodes
        P = as_covariance(P0, "P0", n)
        if float(np.linalg.eigvalsh(P)[0]) <= 0.0:
            raise ValueError("P0: must be positive definite (the information form inverts it)")
        if mu0 is None:
            mu = np.full(r, 1.0 / r)
        else:
            mu = as_vector(mu0, "mu0", r)
            if np.any(mu < 0.0) or abs(mu.sum() - 1.0) > 1e-9:
                raise ValueError("mu0: must be >= 0 and sum to 1")
        x = np.asarray(x0, dtype=float)
        if x.shape == (n,):
            x = np.broadcast_to(x, (*batch, n))
        elif x.shape != (*batch, n):
            raise ValueError(f"x0: expected shape ({n},) or {(*batch, n)}, got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("x0: contains NaN or infinity")
        lead = (*batch, N, r)
        return ImmState(
            mu=np.broadcast_to(mu, lead).copy(),
            x=np.broadcast_to(x[..., None, None, :], (*lead, n)).copy(),
            P=np.broadcast_to(P, (*lead, n, n)).copy(),
        )

    # --- the recursion --------------------------------------------------------------------

    def predict(self, state: ImmState, k: int, u: np.ndarray | None = None,
                tau: float | None = None, interact: bool = True) -> ImmState:
        """x(k) -> x(k+1): interaction and mode-matched unscented prediction; mu := cbar.

        With ``tau`` (s): only the part x(t) -> x(t + tau) of step k, through each mode's
        ``flow`` with noise Q tau / period_s; ``interact`` False skips the interaction (a
        later part of a step: modes switch at the steps' starts only)."""
        if u is None:
            u = np.zeros(self.nu)
        if interact:
            cbar, x0, P0 = mix(state.mu, state.x, state.P, self.Pi)
        else:
            cbar, x0, P0 = state.mu, state.x, state.P
        xs, Ps = [], []
        for j, md in enumerate(self.modes):
            vec = self._vec_modes[j]
            if tau is None:
                fn, Q = _rows(md.f, u, k, vec), md.Q
            else:
                assert md.flow is not None
                fn, Q = _flow_rows(md.flow(tau), u, vec), md.Q * (tau / md.period_s)
            xj, Pj = unscented_propagate(
                fn,
                x0[..., j, :],
                P0[..., j, :, :],
                Q,
                self.kappa,
                md.angles,
            )
            xs.append(xj)
            Ps.append(Pj)
        return ImmState(mu=cbar, x=np.stack(xs, axis=-2), P=np.stack(Ps, axis=-3))

    def used(self, obs: Sequence[Observation]) -> list[Observation]:
        """The observations this variant uses (``single``: only sensor ``node``)."""
        if self.variant == "single":
            return [o for o in obs if o[0] == self.node]
        return list(obs)

    def update(self, state: ImmState, obs: Sequence[Observation]) -> ImmState:
        """Condition a predicted state on this step's observations (sensor indices distinct).

        z of each observation has shape (..., m), ``...`` = the state's batch axes (without
        node and mode axes), or (m,) for all.
        """
        obs = self.used(obs)
        if not obs:
            return state
        seen = [o[0] for o in obs]
        if len(set(seen)) != len(seen):
            raise ValueError(f"observations: duplicate sensor indices {seen}")
        x_pr, P_pr = state.x, state.P
        y_pr, Y_pr = uif.information_prior(x_pr, P_pr)
        X = sigma_points(x_pr, P_pr, self.kappa)  # shared by all sensors
        contribs: list[uif.Contribution] = []
        for s, z, R in obs:
            sensor = self.sensors[s]
            z = np.asarray(z, dtype=float)[..., None, None, :]  # node and mode axes
            Rs = sensor.R if R is None else R
            contribs.append(uif.sensor_contribution(sensor, z, Rs, x_pr, Y_pr, X, self._w))
        x, P, Y = uif.fuse(y_pr, Y_pr, contribs)
        loglik = self._loglik(obs, contribs, P_pr, Y_pr, Y)
        mu = posterior_probabilities(state.mu, loglik)
        return ImmState(mu=mu, x=x, P=P)

    def _loglik(
        self,
        obs: list[Observation],
        contribs: list[uif.Contribution],
        P_pr: np.ndarray,
        Y_pr: np.ndarray,
        Y_post: np.ndarray,
    ) -> np.ndarray:
        """Mode log-likelihoods (..., N, r) for the variant."""
        v = self.variant
        if v in ("single", "centralised"):
            return uif.joint_loglik(contribs, Y_pr, Y_post)
        if v == "imm2":
            return sum(uif.marginal_loglik(c, P_pr) for c in contribs)  # type: ignore[return-value]
        # imm1: node s only sees its own sensor's likelihood (none if s sent nothing).
        ll = np.zeros(P_pr.shape[:-2])
        for (s, _, _), c in zip(obs, contribs, strict=True):
            ll[..., s, :] = uif.marginal_loglik(c, P_pr)[..., s, :]
        return ll

    # --- outputs ----------------------------------------------------------------------------

    def output(self, state: ImmState, node: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Combined mean (..., n) and covariance (..., n, n) of the reported node."""
        k = self._node_index(node)
        return combine(state.mu[..., k, :], state.x[..., k, :, :], state.P[..., k, :, :, :])

    def probabilities(self, state: ImmState, node: int | None = None) -> np.ndarray:
        """Mode probabilities (..., r) of the reported node."""
        return state.mu[..., self._node_index(node), :]

    def _node_index(self, node: int | None) -> int:
        if self.n_nodes == 1:
            return 0
        k = self.node if node is None else int(node)
        if not 0 <= k < self.n_nodes:
            raise ValueError(f"node: must be in [0, {self.n_nodes}), got {k}")
        return k


def _rows(f: TransitionFn, u: np.ndarray, k: int, vectorized: bool) -> Callable[[Array], Array]:
    """X (..., n) -> f(X, u, k) row-wise (see :func:`.unscented.apply_rows`)."""
    return lambda X: apply_rows(lambda R: f(R, u, k), X, vectorized)


def _flow_rows(f: Callable[[np.ndarray, np.ndarray], np.ndarray], u: np.ndarray,
               vectorized: bool) -> Callable[[Array], Array]:
    """X (..., n) -> f(X, u) row-wise: a mode's flow over part of a step."""
    return lambda X: apply_rows(lambda R: f(R, u), X, vectorized)
