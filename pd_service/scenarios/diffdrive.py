"""A stock differential-drive robot as ROS 2 sees it (registered nonlinear model ``"unicycle"``
of :mod:`pd_service.estimation.nonlinear`), step d = 0.02 s::

    x = [x, y, yaw, v, yaw_rate] (m, m, rad, m/s, rad/s),  u = [v_cmd, yaw_rate_cmd] (a Twist)
    x(k+1) = f(x(k), u(k)) + w(k),  w ~ N(0, diag Q),  Q = UNICYCLE_Q0, lags tau_v, tau_w
    odom_twist: z = [v, yaw_rate] + v,  every 2 steps (25 Hz), delay 2 (40 ms),
                std 0.02 m/s, 0.02 rad/s       -> nav_msgs/Odometry on "odom", fields vx, yaw_rate
    imu:        z = [yaw_rate] + v,     every step (50 Hz),   delay 1 (20 ms),
                std 0.01 rad/s                 -> sensor_msgs/Imu on "imu", field yaw_rate
    pose:       z = [x, y, yaw] + v,    every 10 steps (5 Hz), delay 15 (300 ms),
                std 0.05 m, 0.05 m, 0.02 rad   -> PoseWithCovarianceStamped on "pose_fix"
    lead 5 (uplink 100 ms: the Twist on "cmd_vel"), max_delay 20

The session's sensors are the model's sensors of the same names (kind "model"); the spec
carries the ROS 2 bindings above, the Twist commands on ``cmd_vel`` and the predicted
Odometry / pose / TF outputs (layout x=0, y=1, yaw=2, vx=3, yaw_rate=4, body-frame velocity).
The delays are the nominal ones of ``deploy/link-ros2.toml``.

Command profiles: :func:`drive_turn_stop` (rest, drive, turn left, drive, turn right, stop,
repeated every 20 s) or, with ``stationary``, zero commands (the robot stays where it is but
for the process noise: a run to check the covariance's consistency).
"""

from __future__ import annotations

import numpy as np

from pd_service.estimation.nonlinear import make_model
from pd_service.estimation.nonlinear.models_unicycle import UNICYCLE_Q0
from pd_service.wire import UnscentedModelSpec
from pd_service.wire.ros2 import (
    CommandBinding,
    OutputBinding,
    Ros2Binding,
    StateLayout,
    TopicBinding,
)

from .simulator import Scenario, SensorDef

PERIOD_S = 0.02
TAU_V = 0.25  # s, first-order lag of the forward speed
TAU_W = 0.15  # s, first-order lag of the yaw rate
DIFFDRIVE_LEAD = 5  # steps: uplink 100 ms
DIFFDRIVE_MAX_DELAY = 20  # steps: the pose fix's 15 plus 100 ms of slack
#: Parameters of the registered model "unicycle" (the robot), as sent in the spec.
DIFFDRIVE_PARAMS: dict[str, float] = {"period_s": PERIOD_S, "tau_v": TAU_V, "tau_w": TAU_W}
#: Prior: the robot starts at the origin, at rest, known to 5 cm / 0.05 rad / 5 cm/s.
P0 = np.diag([0.05**2, 0.05**2, 0.05**2, 0.05**2, 0.05**2])
#: name -> (interval, delay) in steps, noise std per component.
SENSOR_TIMING: dict[str, tuple[int, int]] = {"odom_twist": (2, 2), "imu": (1, 1), "pose": (10, 15)}
SENSOR_STD: dict[str, tuple[float, ...]] = {
    "odom_twist": (0.02, 0.02), "imu": (0.01,), "pose": (0.05, 0.05, 0.02)}
#: The ROS 2 side: topics (relative to the robot's namespace) and what each carries.
ROS2_BINDING = Ros2Binding(
    sensors={
        "odom_twist": TopicBinding(topic="odom", msg_type="nav_msgs/msg/Odometry",
                                   fields=["vx", "yaw_rate"]),
        "imu": TopicBinding(topic="imu", msg_type="sensor_msgs/msg/Imu", fields=["yaw_rate"]),
        "pose": TopicBinding(topic="pose_fix",
                             msg_type="geometry_msgs/msg/PoseWithCovarianceStamped",
                             fields=["x", "y", "yaw"]),
    },
    commands=CommandBinding(topic="cmd_vel", msg_type="geometry_msgs/msg/Twist"),
    outputs=OutputBinding(layout=StateLayout(x=0, y=1, yaw=2, vx=3, yaw_rate=4,
                                             velocity_frame="body")),
)
#: (duration s, v_cmd m/s, yaw_rate_cmd rad/s) of one 20 s cycle of :func:`drive_turn_stop`.
PROFILE: tuple[tuple[float, float, float], ...] = (
    (1.0, 0.0, 0.0),    # rest (longer than the lead: the first command arrives in time)
    (4.0, 0.5, 0.0),    # drive straight
    (3.0, 0.4, 0.5),    # turn left (radius 0.8 m, 86 degrees)
    (3.0, 0.5, 0.0),    # drive straight
    (3.0, 0.4, -0.5),   # turn right
    (2.0, 0.3, 0.0),    # slow down
    (4.0, 0.0, 0.0),    # stop
)
CYCLE_S = sum(p[0] for p in PROFILE)


def drive_turn_stop(k: int, period_s: float = PERIOD_S) -> np.ndarray:
    """The Twist (v_cmd, yaw_rate_cmd) the operator sends for step k: :data:`PROFILE`, repeated."""
    t = (k * period_s + 1e-9) % CYCLE_S
    for duration, v, w in PROFILE:
        if t < duration:
            return np.array([v, w])
        t -= duration
    return np.zeros(2)  # pragma: no cover (t < CYCLE_S)


def stationary(k: int) -> np.ndarray:
    """Zero commands: the robot stands still."""
    return np.zeros(2)


def diffdrive_scenario(stationary_robot: bool = False) -> Scenario:
    """The scenario (see the module docstring); ``stationary_robot``: zero commands."""
    model = make_model("unicycle", **DIFFDRIVE_PARAMS)
    sensors = []
    for name, (interval, delay) in SENSOR_TIMING.items():
        ms = model.sensors[name]
        sensors.append(SensorDef(name, None, np.diag(SENSOR_STD[name]), delay=delay,
                                 interval=interval, kind="model", h=ms.h, angles=ms.angles))
    return Scenario(
        name="diffdrive-stationary" if stationary_robot else "diffdrive",
        description=("differential-drive robot at rest (NEES run)" if stationary_robot else
                     "differential-drive robot: drive, turn, stop") +
                    "; odometry twist, IMU, delayed pose fix; ROS 2 topics; UKF",
        period_s=PERIOD_S,
        Q=np.diag(UNICYCLE_Q0),
        nonlinear=model,
        model_spec=UnscentedModelSpec(model="unicycle", params=dict(DIFFDRIVE_PARAMS)),
        sensors=tuple(sensors),
        x0_true=np.zeros(5), x0=np.zeros(5), P0=P0.copy(),
        lead=DIFFDRIVE_LEAD, max_delay=DIFFDRIVE_MAX_DELAY,
        state_names=("x", "y", "yaw", "v", "yaw_rate"),
        command=stationary if stationary_robot else drive_turn_stop,
        default_steps=int(round(CYCLE_S / PERIOD_S)),
        angles=model.angles,
        loss_draw=False,
        ros2=ROS2_BINDING,
    )
