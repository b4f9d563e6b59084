"""From-scratch runs of the unscented filters: the definitions the replaying estimator must equal.

One step at a time from x0, P0 at step 0 over every accepted packet in stamp order; no window,
no checkpoints, no replay. It reuses the package's single-step UKF functions (``time_step``,
``measurement_update``) because what is under test here is the window / replay / committed-
horizon logic; the UKF steps themselves are tested against a Kalman filter and finite
differences elsewhere.
"""

from __future__ import annotations

import numpy as np

from pd_service.estimation.nonlinear.registry import MeasurementModel, NonlinearModel, wrap_angle
from pd_service.estimation.nonlinear.sigma import SigmaWeights
from pd_service.estimation.nonlinear.unscented import (
    ModelOps,
    UKFState,
    measurement_update,
    time_step,
)
from pd_service.estimation.replay import Packet
from tests.estimation.reference import applied_inputs


def from_scratch(model, sensor_names, x0, P0, commands, packets, commit, target, adapter=None,
                 weights=None, hold=True):
    """(x, P, Q) of x(target) and the final Q.

    commands: {step: u}; packets: list of (sensor_idx, step, z); commit: first step that is not
    final (steps < commit use the adaptive filter, the rest Q frozen).
    """
    ops = ModelOps(model, sensor_names)
    w = weights or SigmaWeights.make(model.n)
    n = model.n
    Q = np.array(model.Q, dtype=float)
    dQ = None
    x = np.array(x0, dtype=float)
    if model.angles:
        x[list(model.angles)] = wrap_angle(x[list(model.angles)])
    state = UKFState(x, np.array(P0, dtype=float))
    if adapter is not None and adapter.needs_sensitivities:
        p = len(adapter.indices)
        dQ = np.zeros((p, n, n))
        for j, i in enumerate(adapter.indices):
            dQ[j, i, i] = 1.0
        state = UKFState(state.x, state.P, np.zeros((p, n)), np.zeros((p, n, n)))
    by_step: dict[int, list[Packet]] = {}
    for idx, step, z in packets:
        by_step.setdefault(step, []).append(Packet(idx, np.asarray(z, float), None))
    last = 0
    us = applied_inputs(commands, model.nu, target, hold)
    for k in range(target + 1):
        if k in by_step:
            pk = sorted(by_step[k], key=lambda p: p.sensor)
            if adapter is not None and k < commit:
                state, rec = measurement_update(ops, w, state, k, pk, k - last, Q)
                last = k
                Qn = adapter.observe(rec, Q)
                if Qn is not None:
                    Q = Qn
            else:
                state = measurement_update(ops, w, UKFState(state.x, state.P), k, pk)[0]
        if k == target:
            break
        state = time_step(ops, w, Q, state, us[k], k, dQ if state.tracked else None)
    return state.x, state.P, Q


def omni_with_beacon(fd_beacon: bool = True) -> NonlinearModel:
    """omni3 plus a range-bearing beacon at (2, 1): z = (|b - p|, atan2(by - y, bx - x) - theta),
    bearing an angle. The beacon has no Jacobian when ``fd_beacon`` (finite-difference path)."""
    from pd_service.estimation.nonlinear.models_omni import omni3

    base = omni3()
    b = np.array([2.0, 1.0])

    def h(X):
        X = np.atleast_2d(X)
        d = b - X[:, :2]
        rng = np.hypot(d[:, 0], d[:, 1])
        brg = np.arctan2(d[:, 1], d[:, 0]) - X[:, 2]
        return np.stack((rng, wrap_angle(brg)), axis=1)

    def H(X):
        X = np.atleast_2d(X)
        d = b - X[:, :2]
        r2 = d[:, 0] ** 2 + d[:, 1] ** 2
        r = np.sqrt(r2)
        J = np.zeros((X.shape[0], 2, 6))
        J[:, 0, 0] = -d[:, 0] / r
        J[:, 0, 1] = -d[:, 1] / r
        J[:, 1, 0] = d[:, 1] / r2
        J[:, 1, 1] = -d[:, 0] / r2
        J[:, 1, 2] = -1.0
        return J

    beacon = MeasurementModel(name="beacon", h=h, R=np.diag([1e-4, 1e-4]), angles=(1,),
                              jac=None if fd_beacon else H, vectorized=True)
    sensors = dict(base.sensors)
    sensors["beacon"] = beacon
    return NonlinearModel(name="omni3+beacon", n=6, nu=3, f=base.f, Q=base.Q, sensors=sensors,
                          angles=base.angles, jac=base.jac, vectorized=True)
