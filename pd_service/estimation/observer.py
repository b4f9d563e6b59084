"""The exact observer-predictor for multi-delay, multi-rate measurements with missing data."""

from __future__ import annotations

from collections.abc import Sequence

from mypy_extensions import mypyc_attr

from .checks import as_covariance, as_vector
from .linear import Gaussian, LinearBackend
from .model import LinearModel, Sensor, check_sensors
from .replay import ReplayEstimator


# compiled by mypyc (setup.py): a compiled subclass, so the window's calls on its own
# methods skip the glue an interpreted subclass needs; the flags as on ReplayEstimator
# (deep copies, see inputs.py)
@mypyc_attr(serializable=True, allow_interpreted_subclasses=True)
class ObserverPredictor(ReplayEstimator[Gaussian]):
    """Exact LMMSE predictor of x(now + lead) from delayed, multi-rate, lossy packets.

    Example::

        op = ObserverPredictor(LinearModel(A=A, B=B, Q=Q),
                               [Sensor(name="camera", H=H0, R=R0), Sensor("ranger", H1, R1)],
                               x0=x0, P0=P0, lead=10, max_delay=12)
        op.add_command(step=j, u=u)                       # u applies from step j on
        ok = op.add_measurement("camera", step=s, z=z, now=k)
        pred = op.predict(now=k)                          # pred.step == k + lead

    Guarantee: ``predict(now=k)`` equals (to rounding) a Kalman filter run from x0, P0 at step
    0 over every accepted packet in sample-stamp order, then predicted to k + lead with the
    known commands. With a continuous-time model (:meth:`LinearModel.continuous`) packets
    and commands may carry offsets into their steps (``add_measurement(..., offset=s)``,
    ``add_command(..., offset=s)``): then it equals the continuous-discrete Kalman filter
    over every event at its own time. Cost per call is bounded by the window, not by
    elapsed steps.
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
        sensors = check_sensors(model, sensors)
        x = as_vector(x0, "x0", model.n)
        P = as_covariance(P0, "P0", model.n)
        super().__init__(
            backend=None,  # type: ignore[arg-type]  # set below, once the horizon is known
            initial=Gaussian(x, P),
            sensor_dims={s.name: s.m for s in sensors},
            nu=model.nu,
            lead=lead,
            max_delay=max_delay,
            command_hold=command_hold,
        )
        self.model = model
        self.sensors = sensors
        self._backend = LinearBackend(model, sensors, self._inputs.capacity)
        # samples and commands inside a step need a continuous-time model
        self.period_s = model.period if model.period is not None else 0.0

    @property
    def n(self) -> int:
        return self.model.n

