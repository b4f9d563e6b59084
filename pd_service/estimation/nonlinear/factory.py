"""Plain-Python construction of the unscented observer-predictor from session settings.

Everything here is numbers, lists, strings and maps, as they arrive in a SessionSpec (which
:mod:`pd_service.backends` maps onto this), so a session can select a model by name::

    op = make_unscented("omni3", {"period_s": 0.01}, x0=[0] * 6, P0=np.eye(6) * 1e-4,
                        lead=10, max_delay=12, command_hold="hold",
                        adapt={"method": "mit", "indices": [3, 4, 5]},
                        sigma={"alpha": 1.0, "beta": 2.0, "kappa": 0.0})
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

from ..checks import as_covariance
from .adaptive import make_adapter
from .registry import NonlinearModel, make_model
from .sigma import SigmaWeights
from .ukf import UnscentedObserverPredictor


def make_unscented(
    model_name: str | NonlinearModel,
    model_params: Mapping[str, object] | None,
    x0: object,
    P0: object,
    lead: int,
    max_delay: int,
    command_hold: str = "hold",
    adapt: Mapping[str, object] | None = None,
    sigma: Mapping[str, object] | None = None,
    sensors: Sequence[str] | None = None,
    sensor_R: Mapping[str, object] | None = None,
) -> UnscentedObserverPredictor:
    """Build the registered model ``model_name`` with ``model_params`` and its estimator
    (``model_name`` may be that model already built, ``model_params`` then None).

    ``adapt``: None (plain UKF) or the settings of :func:`.adaptive.make_adapter`.
    ``sigma``: optional {"alpha", "beta", "kappa"} (defaults 1, 2, 0).
    ``sensors``: which of the model's sensors, in which order (default: all, model order).
    ``sensor_R``: name -> m x m measurement covariance replacing the model's (e.g. the R of a
    session's sensor spec); a packet's own R still overrides per sample.
    Every problem raises ValueError naming the field.
    """
    if isinstance(model_name, NonlinearModel):
        if model_params is not None:
            raise ValueError("model_params: the model is already built")
        model, model_name = model_name, model_name.name
    elif not isinstance(model_name, str):
        raise ValueError("model: expected a registered model name")
    elif model_params is not None and not isinstance(model_params, Mapping):
        raise ValueError("model_params: expected a map of parameters")
    else:
        model = make_model(model_name, **dict(model_params or {}))
    weights = None
    if sigma is not None:
        if not isinstance(sigma, Mapping) or set(sigma) - {"alpha", "beta", "kappa"}:
            raise ValueError("sigma: expected a map with keys among 'alpha', 'beta', 'kappa'")
        weights = SigmaWeights.make(model.n, **sigma)  # type: ignore[arg-type]
    names = list(model.sensors) if sensors is None else list(sensors)
    unknown = [s for s in names if s not in model.sensors]
    if unknown:
        raise ValueError(f"sensors: unknown {unknown} (model {model_name!r} has {list(model.sensors)})")
    if sensor_R:
        if not isinstance(sensor_R, Mapping):
            raise ValueError("sensor_R: expected a map sensor name -> R")
        meas = dict(model.sensors)
        for name, R in sensor_R.items():
            if name not in meas:
                raise ValueError(f"sensor_R: unknown sensor {name!r} (model has {list(meas)})")
            Rm = as_covariance(R, f"sensor_R[{name!r}]", meas[name].m)
            Rm.setflags(write=False)
            meas[name] = dataclasses.replace(meas[name], R=Rm)
        model = dataclasses.replace(model, sensors=meas)
    adapter = make_adapter(adapt, model.Q, [model.sensors[s].m for s in names])
    return UnscentedObserverPredictor(model, x0, P0, lead, max_delay, command_hold,
                                      sensors=names, sigma=weights, adapter=adapter)
