"""Named nonlinear models, so a session can choose one over the wire (a function cannot be sent).

A model is registered under a name with a factory taking keyword parameters (plain numbers
and lists, as they arrive in a SessionSpec) and returning a :class:`NonlinearModel`::

    @register_model("omni3")
    def omni3(period_s: float = 0.01, mass: float = 10.0) -> NonlinearModel: ...

    model = make_model("omni3", period_s=0.01)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: f(x (n,), u (nu,), k) -> x(k+1) without noise
TransitionFn = Callable[[np.ndarray, np.ndarray, int], np.ndarray]
#: h(x (n,)) -> z (m,)
MeasurementFn = Callable[[np.ndarray], np.ndarray]
#: f over part of a step: tau (s, 0 < tau <= period_s) -> the map (X (n,) or (N, n), u (nu,))
#: -> the state tau seconds later without noise
FlowFn = Callable[[float], Callable[[np.ndarray, np.ndarray], np.ndarray]]
#: Jacobian of f: F(x (n,), u (nu,), k) -> (n, n)  (batched: X (N, n) -> (N, n, n))
TransitionJacobianFn = Callable[[np.ndarray, np.ndarray, int], np.ndarray]
#: Jacobian of h: H(x (n,)) -> (m, n)  (batched: X (N, n) -> (N, m, n))
MeasurementJacobianFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True, eq=False)
class MeasurementModel:
    """z = h(x) + v, v ~ N(0, R). ``angles``: indices of z that are angles (wrapped to [-pi, pi)).

    Optional (consumers must work without them):
    ``jac``: H(x) = dh/dx, used for exact sensitivities (else directional finite differences);
    ``vectorized``: h (and jac) also accept a batch X (N, n) and return (N, m) ((N, m, n)).
    """

    name: str
    h: MeasurementFn
    R: np.ndarray
    angles: tuple[int, ...] = ()
    jac: MeasurementJacobianFn | None = None
    vectorized: bool = False

    @property
    def m(self) -> int:
        return self.R.shape[0]


@dataclass(frozen=True, eq=False)
class NonlinearModel:
    """x(k+1) = f(x, u, k) + w, w ~ N(0, Q). ``angles``: state indices that are angles.

    Optional (consumers must work without them):
    ``jac``: F(x, u, k) = df/dx, used for exact sensitivities (else directional finite
    differences); ``vectorized``: f (and jac) also accept a batch X (N, n) with one u and
    return (N, n) ((N, n, n)), so a filter evaluates all sigma points in one call;
    ``flow``: the model over part of a step, ``flow(tau)(X, u)`` = x(t + tau) for
    0 < tau <= ``period_s`` (s) with u held (same batching as f), so a sample taken inside a
    step is applied at its own time; the noise over tau is then Q tau / period_s (Q read as
    white noise of constant intensity over the step). Without ``flow`` (or ``period_s``)
    the model only moves whole steps.
    """

    name: str
    n: int
    nu: int
    f: TransitionFn
    Q: np.ndarray
    sensors: dict[str, MeasurementModel] = field(default_factory=dict)
    angles: tuple[int, ...] = ()
    jac: TransitionJacobianFn | None = None
    vectorized: bool = False
    flow: FlowFn | None = None
    period_s: float = 0.0


_REGISTRY: dict[str, Callable[..., NonlinearModel]] = {}


def register_model(name: str) -> Callable[[Callable[..., NonlinearModel]], Callable[..., NonlinearModel]]:
    """Decorator: register a model factory under ``name`` (unique)."""

    def deco(factory: Callable[..., NonlinearModel]) -> Callable[..., NonlinearModel]:
        if name in _REGISTRY:
            raise ValueError(f"model {name!r} is already registered")
        _REGISTRY[name] = factory
        return factory

    return deco


def make_model(name: str, **params: object) -> NonlinearModel:
    """Build the registered model ``name``; ValueError names the model or parameter that is wrong."""
    factory = _REGISTRY.get(name)
    if factory is None:
        raise ValueError(f"model: unknown model {name!r} (registered: {sorted(_REGISTRY)})")
    try:
        return factory(**params)
    except TypeError as exc:
        raise ValueError(f"model {name!r}: bad parameters ({exc})") from None


def registered_models() -> list[str]:
    return sorted(_REGISTRY)


def batched(fn: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """Lift a batched map (N, n) -> (N, ...) to also take one state (n,) -> (...)."""

    def wrapped(Xs: np.ndarray, *args: object) -> np.ndarray:
        Xs = np.asarray(Xs, dtype=float)
        if Xs.ndim == 1:
            return fn(Xs[None, :], *args)[0]
        return fn(Xs, *args)

    return wrapped


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi
