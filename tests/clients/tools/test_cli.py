"""Command-line tools: argument errors, the display's frame, the module entry point."""

from __future__ import annotations

import time

import numpy as np
import pytest

from pd_client import Display, Prediction, Truth
from pd_client.tools import __main__ as entry
from pd_client.tools import pd_display, pd_operator, pd_record, pd_robot_sim
from pd_client.tools.common import parse_session_arg
from pd_service.wire import encode, keys


@pytest.mark.parametrize("main, argv", [
    (pd_robot_sim.main, ["--scenario", "submarine"]),
    (pd_robot_sim.main, ["--session", "paper:lidar"]),
    (pd_robot_sim.main, ["--time-scale", "0"]),
    (pd_robot_sim.main, ["--steps", "-1"]),
    (pd_operator.main, ["--scenario", "nope"]),
    (pd_display.main, ["--count", "0"]),
    (pd_record.main, ["--bogus"]),
])
def test_bad_command_lines_exit_2(main, argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert "error" in capsys.readouterr().err


def test_module_entry_point_usage(capsys):
    assert entry.main([]) == 2
    assert entry.main(["fly"]) == 2
    assert "usage: python -m pd_client.tools" in capsys.readouterr().err


def test_session_argument():
    assert parse_session_arg("paper") == ("paper", None)
    assert parse_session_arg("paper-cam:camera") == ("paper-cam", ["camera"])
    assert parse_session_arg("x:a,b") == ("x", ["a", "b"])


def test_display_frame_shows_prediction_truth_and_counters(bus):
    pub = bus.transport()
    with Display(bus.transport(), "s1", truth=True) as d:
        assert "waiting for predictions" in pd_display.render_frame(d)
        for seq, step in enumerate((20, 21)):
            pub.put(keys.prediction_key("s1"), encode(Prediction(
                session="s1", seq=seq, step=step, t_ns=0, x=np.array([1.0, 2.0, 3.0, 4.0]),
                P=np.diag([0.04, 0.01, 0.09, 0.01]), newest_step=9, made_ns=time.time_ns(),
                counters={"accepted": 7, "late": 1})))
        pub.put(keys.truth_key("s1"), encode(Truth(
            session="s1", step=20, t_ns=0, x=np.array([1.1, 2.0, 2.7, 4.0]),
            names=["p1", "v1", "p2", "v2"])))
        frame = pd_display.render_frame(d)
    assert "predictions 2" in frame and "truth 1" in frame
    assert "x(step 21)" in frame and "newest sample used: step 9" in frame
    assert "checked against truth at step 20" in frame
    p2 = next(line for line in frame.splitlines() if line.strip().startswith("p2") and
              "2.7000" in line)
    assert "0.3000" in p2 and "1.00" in p2  # error 0.3 = 1.0 sigma (sd 0.3)
    assert "service counters: accepted 7  late 1" in frame


def test_no_listener_gives_service_unavailable_and_exit_1(capsys):
    import socket

    from pd_client import ServiceUnavailable, connect

    with socket.socket() as s:  # a free loopback port: nothing listens there
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    with pytest.raises(ServiceUnavailable, match="cannot open a Zenoh client session"):
        connect(endpoint)
    assert pd_robot_sim.main(["--connect", endpoint, "--connect-wait", "0"]) == 1
    assert "pd-robot-sim: error: cannot open" in capsys.readouterr().err
