"""Sensitivities d/dq_m carried through the UKF time and measurement updates vs finite
differences of the whole filter in q (q a constant parameter over the run)."""

import numpy as np
import pytest

from pd_service.estimation.nonlinear import SigmaWeights, make_model
from pd_service.estimation.nonlinear.unscented import (
    ModelOps,
    UKFState,
    measurement_update,
    time_step,
)
from pd_service.estimation.replay import Packet
from pd_service.scenarios.omni import omni_torque

from .reference import omni_with_beacon

INDICES = (3, 4, 5)


def _run(model, sensors, q, steps, zs, tracked, weights):
    """Filter ``steps`` steps with Q's adapted diagonal = q; return per-step records."""
    ops = ModelOps(model, sensors)
    n, p = model.n, len(INDICES)
    Q = np.array(model.Q)
    Q[INDICES, INDICES] = q
    dQ = np.zeros((p, n, n))
    for j, i in enumerate(INDICES):
        dQ[j, i, i] = 1.0
    x0 = np.array([0.1, -0.2, 0.3, 0.2, 0.1, 0.5])
    st = UKFState(x0, np.diag([1e-4, 1e-4, 1e-3, 1e-3, 1e-3, 1e-2]))
    if tracked:
        st = UKFState(st.x, st.P, np.zeros((p, n)), np.zeros((p, n, n)))
    out = []
    for k in range(steps):
        st = time_step(ops, weights, Q, st, omni_torque(k), k, dQ if tracked else None)
        packets = [Packet(i, zs[k][i], None) for i in range(len(sensors)) if zs[k][i] is not None]
        st, rec = measurement_update(ops, weights, st, k + 1, packets, 1, Q)
        out.append((st, rec))
    return out


def _measurements(model, sensors, steps, rng):
    """Simulated z along a noisy truth; the beacon every 3rd step only (multi-rate)."""
    x = np.array([0.1, -0.2, 0.3, 0.2, 0.1, 0.5])
    qs = np.sqrt(np.array([1e-10, 1e-10, 1e-10, 4e-4, 4e-4, 2.5e-3]))
    zs = []
    for k in range(steps):
        x = model.f(x, omni_torque(k), k) + qs * rng.standard_normal(6)
        row = []
        for name in sensors:
            s = model.sensors[name]
            if name == "beacon" and k % 3:
                row.append(None)
                continue
            row.append(s.h(x[None, :])[0] + np.sqrt(np.diag(s.R)) * rng.standard_normal(s.m))
        zs.append(row)
    return zs


@pytest.mark.parametrize("case", ["omni-exact-jacobians", "omni-beacon-finite-difference-jvp"])
def test_sensitivities_match_finite_differences(case):
    if case == "omni-exact-jacobians":
        model, sensors = make_model("omni3"), ["pose"]
    else:
        model, sensors = omni_with_beacon(fd_beacon=True), ["pose", "beacon"]
    weights = SigmaWeights.make(6, alpha=0.8, beta=2.0, kappa=0.0)
    steps = 40
    zs = _measurements(model, sensors, steps, np.random.default_rng(11))
    q = np.array([4e-5, 6e-5, 2e-4])
    tracked = _run(model, sensors, q, steps, zs, True, weights)
    for j in range(len(INDICES)):
        h = 1e-4 * q[j]
        qp, qm = q.copy(), q.copy()
        qp[j] += h
        qm[j] -= h
        plus = _run(model, sensors, qp, steps, zs, False, weights)
        minus = _run(model, sensors, qm, steps, zs, False, weights)
        for k in (5, 17, steps - 1):
            st, rec = tracked[k]
            (sp, rp), (sm, rm) = plus[k], minus[k]
            fd_x = (sp.x - sm.x) / (2 * h)
            fd_P = (sp.P - sm.P) / (2 * h)
            fd_nu = (rp.nu - rm.nu) / (2 * h)
            fd_S = (rp.S - rm.S) / (2 * h)
            for name, got, want in (("dx", st.dx[j], fd_x), ("dP", st.dP[j], fd_P),
                                    ("dnu", rec.dnu[j], fd_nu), ("dS", rec.dS[j], fd_S)):
                scale = float(np.max(np.abs(want)))
                assert scale > 0, f"{name} q[{j}] step {k}: no effect to compare"
                np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * scale,
                                           err_msg=f"{case} {name} q[{j}] step {k}")
