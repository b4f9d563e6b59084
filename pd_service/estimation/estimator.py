"""The API every session estimator shares (ObserverPredictor, the unscented and the IMM
observer-predictors, the daemon's stacked twin): all are :class:`.replay.ReplayEstimator`
subclasses, and code that only feeds and reads one types it as :class:`Estimator`."""

from __future__ import annotations

from typing import Protocol

from .replay import PredictedState


class Estimator(Protocol):
    """Accept window, commands and prediction of x(now + lead); time is an integer step
    (plus, for samples and commands, an offset in seconds into it)."""

    @property
    def n(self) -> int:
        """State dimension."""
        ...

    @property
    def lead(self) -> int:
        """Steps from ``now`` to the predicted step (>= 0)."""
        ...

    @property
    def max_delay(self) -> int:
        """A packet stamped s is accepted iff ``now - max_delay <= s <= now``."""
        ...

    @property
    def sensor_names(self) -> list[str]: ...

    @property
    def counters(self) -> dict[str, int]:
        """Counts of accepted and refused measurements and commands, by reason."""
        ...

    @property
    def now(self) -> int | None:
        """Newest ``now`` seen (None before the first call that passed one)."""
        ...

    @property
    def committed_step(self) -> int:
        """First step that can still change; every step before it is final."""
        ...

    def add_measurement(self, sensor: str, step: int, z: object, now: int,
                        R: object | None = None, offset: float = 0.0) -> bool:
        """Offer the sample z (m,) of ``sensor`` taken ``offset`` seconds after the start of
        ``step`` (R: optional (m, m) override); True iff accepted. ValueError for malformed
        input."""
        ...

    def add_command(self, step: int, u: object, now: int | None = None,
                    offset: float = 0.0) -> bool:
        """Offer the command u (nu,) that applies from ``offset`` seconds after the start of
        ``step`` on; True iff accepted."""
        ...

    def predict(self, now: int) -> PredictedState:
        """Estimate of x(now + lead): x (n,), P (n, n)."""
        ...

    def predict_path(self, now: int, stride: int = 1,
                     max_points: int = 0) -> list[PredictedState]:
        """Estimates from the newest posterior to x(now + lead), one every ``stride`` steps
        (the first and the last always; the stride widened to at most ``max_points`` points
        if > 0); the last is :meth:`predict`'s."""
        ...
