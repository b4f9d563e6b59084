"""The plain-Python factory a session spec maps onto, and the estimator's input checks."""

import numpy as np
import pytest

from pd_service.estimation import COUNTER_NAMES
from pd_service.estimation.nonlinear import (
    MITAdapter,
    SageHusaAdapter,
    UnscentedObserverPredictor,
    make_model,
    make_unscented,
)

X0, P0 = [0.0] * 6, np.eye(6) * 1e-4


def test_factory_builds_each_variant():
    plain = make_unscented("omni3", {}, X0, P0, lead=5, max_delay=8)
    assert isinstance(plain, UnscentedObserverPredictor) and plain.adapter is None
    assert plain.sensor_names == ["pose"] and plain.q.size == 0
    mit = make_unscented("omni3", {"period_s": 0.02}, X0, P0, 5, 8, "zero",
                         adapt={"method": "mit", "indices": [3, 4, 5], "window": 20, "eta": 0.2},
                         sigma={"alpha": 0.5, "beta": 2.0, "kappa": 0.0})
    assert isinstance(mit.adapter, MITAdapter) and mit.command_hold == "zero"
    np.testing.assert_array_equal(mit.q, [4e-6, 4e-6, 2.5e-5])
    sh = make_unscented("omni3", None, X0, P0, 5, 8, adapt={"method": "sage_husa",
                                                            "indices": [5], "forgetting": 0.9})
    assert isinstance(sh.adapter, SageHusaAdapter)
    assert make_unscented("omni3", {}, X0, P0, 0, 0, adapt={"method": "none"}).adapter is None
    lin = make_unscented("linear", {"A": [[1.0]], "B": [[1.0]], "Q": [[0.1]],
                                    "sensors": {"s": {"H": [[1.0]], "R": [[1.0]]}}},
                         [0.0], [[1.0]], 1, 1, adapt={"method": "mit", "indices": [0]})
    assert lin.n == 1
    over = make_unscented("omni3", {}, X0, P0, 1, 1, sensor_R={"pose": np.eye(3) * 1e-6})
    assert over.model.sensors["pose"].R[0, 0] == 1e-6
    assert make_model("omni3").sensors["pose"].R[0, 0] == 1e-8  # registry model untouched


@pytest.mark.parametrize("kwargs,match", [
    ({"model_name": "nope"}, "unknown model"),
    ({"model_params": {"mass": "heavy"}}, "mass|could not convert"),
    ({"model_params": [1, 2]}, "model_params"),
    ({"x0": [0.0] * 5}, "x0"),
    ({"P0": -np.eye(6)}, "P0"),
    ({"lead": -1}, "lead"),
    ({"max_delay": 1.5}, "max_delay"),
    ({"command_hold": "sometimes"}, "command_hold"),
    ({"adapt": {"method": "mit"}}, "indices"),
    ({"model_params": {"Q": [0.0, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5]},
      "adapt": {"method": "mit", "indices": [0]}}, "start > 0"),
    ({"adapt": {"method": "mit", "indices": [3, 3]}}, "distinct"),
    ({"adapt": {"method": "mit", "indices": [9]}}, "indices"),
    ({"adapt": {"method": "mit", "indices": [3], "eta": -1}}, "eta"),
    ({"adapt": {"method": "mit", "indices": [3], "window": 2.5}}, "window"),
    ({"adapt": {"method": "mit", "indices": [3], "rule": "fast"}}, "rule"),
    ({"adapt": {"method": "mit", "indices": [3], "forgetting": 0.9}}, "unknown settings"),
    ({"adapt": {"method": "sage_husa", "indices": [3], "forgetting": 1.0}}, "forgetting"),
    ({"adapt": {"method": "kalman"}}, "method"),
    ({"adapt": {"method": "mit", "indices": [3], "q_min": [1.0], "q_max": [0.5]}}, "q_min"),
    ({"adapt": "mit"}, "adapt"),
    ({"sigma": {"alpha": 0.0}}, "alpha"),
    ({"sigma": {"gamma": 1.0}}, "sigma"),
    ({"sensors": ["lidar"]}, "sensors"),
    ({"sensor_R": {"lidar": [[1.0]]}}, "sensor_R"),
    ({"sensor_R": {"pose": [[1.0]]}}, "sensor_R"),
    ({"sensor_R": {"pose": -np.eye(3)}}, "sensor_R"),
])
def test_factory_errors_name_the_field(kwargs, match):
    args = {"model_name": "omni3", "model_params": {}, "x0": X0, "P0": P0, "lead": 2,
            "max_delay": 3}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        make_unscented(**args)


def test_window_semantics_match_the_linear_observer():
    op = make_unscented("omni3", {}, X0, P0, lead=2, max_delay=3)
    z = [0.0, 0.0, 0.0]
    assert op.add_measurement("pose", 5, z, now=5)
    assert not op.add_measurement("pose", 5, z, now=5)           # duplicate
    assert not op.add_measurement("pose", 7, z, now=6)           # future
    assert not op.add_measurement("pose", 1, z, now=6)           # late
    assert op.add_command(4, [0.1, 0.0, 0.0], now=6)
    assert not op.add_command(1, [0.1, 0.0, 0.0])                # late
    assert set(op.counters) == set(COUNTER_NAMES)
    c = op.counters
    assert (c["accepted"], c["duplicate"], c["future"], c["late"]) == (1, 1, 1, 1)
    with pytest.raises(ValueError, match="sensor"):
        op.add_measurement("lidar", 6, z, now=6)
    with pytest.raises(ValueError, match="z"):
        op.add_measurement("pose", 6, [0.0, 1.0], now=6)
    with pytest.raises(ValueError, match="z"):
        op.add_measurement("pose", 6, [0.0, np.nan, 1.0], now=6)
    with pytest.raises(ValueError, match="now"):
        op.predict(5)
    pred = op.predict(6)
    assert pred.step == 8 and pred.newest_step == 5 and pred.x.shape == (6,)
    assert np.all(np.linalg.eigvalsh(pred.P) > 0)


def test_heading_is_wrapped():
    model = make_model("omni3")
    op = UnscentedObserverPredictor(model, [0, 0, np.pi - 0.01, 0, 0, 0.0],
                                    np.diag([1e-4, 1e-4, 1e-2, 1e-4, 1e-4, 1e-4]), 0, 0)
    # a measured heading just across the +-pi seam pulls the estimate across, not around
    op.add_measurement("pose", 0, [0.0, 0.0, -np.pi + 0.01], now=0)
    x = op.predict(0).x
    assert -np.pi <= x[2] < np.pi
    assert abs(abs(x[2]) - np.pi) < 0.02


def test_set_Q_checks_and_applies():
    op = make_unscented("omni3", {}, X0, P0, 0, 2, adapt={"method": "mit", "indices": [3]})
    with pytest.raises(ValueError, match="Q"):
        op.set_Q(np.eye(5))
    Q = np.diag([0.0, 0, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="> 0"):
        op.set_Q(Q)
    op.set_Q(np.eye(6) * 1e-5)
    np.testing.assert_array_equal(op.Q, np.eye(6) * 1e-5)


def test_q_schedule_checks():
    model = make_model("omni3")
    with pytest.raises(ValueError, match="exclude"):
        UnscentedObserverPredictor(model, X0, P0, 0, 0, Q_schedule=lambda k: model.Q,
                                   adapter=make_unscented("omni3", {}, X0, P0, 0, 0, adapt={
                                       "method": "mit", "indices": [3]}).adapter)
    op = UnscentedObserverPredictor(model, X0, P0, 2, 0, Q_schedule=lambda k: np.eye(5))
    with pytest.raises(ValueError, match="Q_schedule"):
        op.predict(0)
