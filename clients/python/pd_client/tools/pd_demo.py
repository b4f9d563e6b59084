"""pd-demo: the whole system on one machine, for about 30 seconds, then a summary.

Starts, each as its own process on a free loopback port:

1. ``pd-service``     the daemon (peer mode, listening on 127.0.0.1:<port>)
2. ``pd-link``        the link emulator with the paper's link (camera 10 steps, range
                      finder 12, uplink 10, plus loss: ``link-paper.toml``, shipped in
                      ``pd_client/tools/data/``; ``deploy/link-paper.toml`` links to it)
3. ``pd-record``      records predictions and truth for both sessions, renders PNGs, and
                      (with the ``viz`` extra) every input and output to ``<out>/run.mcap``
   ``pd-viz``         (with the ``viz`` extra) a Foxglove WebSocket server on
                      ws://127.0.0.1:8765 showing both sessions live (docs/visualize.md)
4. ``pd-operator``    sends the paper's commands, stamped with their apply step
5. ``pd-robot-sim``   the paper's vehicle chasing an object, publishing camera and range
                      finder to session ``paper`` and the camera only to ``paper-cam``
   ``pd-robot-sim``   (with the ``viz`` extra: Pillow) the camera robot ``rover``: the
                      differential-drive robot of ``--async`` (x, y, yaw; its own operator)
                      with its commands 500 ms late like the paper's (lead 10 steps) and a
                      camera: a perspective chase view every 2 steps (10 frames/s) that pd-link
                      delays 500 ms (its ``video`` rule), on which pd-web and pd-viz draw the
                      ghost: the robot's outline where the command sent now will act, and the
                      predicted path
6. ``pd-web``         the live view in the browser (http://127.0.0.1:8080/, or a free port
                      when 8080 is taken); it keeps serving the final state ``--web-linger``
                      seconds after the run (the page keeps it after that too)

and prints a side-by-side summary: RMS prediction error and mean predicted variance of p1 and
p2 with the range finder (``paper``) and with the camera only (``paper-cam``). Ctrl-C stops
every process cleanly.

``pd-demo --ros2`` (needs the ``ros2`` extra) runs the ROS 2 variant: the simulated
differential-drive robot as a ROS 2 node (``pd-robot-sim --scenario diffdrive --ros2``: Odometry,
Imu and a delayed pose fix in rmw_zenoh's format) over pd-link's ``link-ros2.toml`` (shipped in
``pd_client/tools/data/``, ``deploy/link-ros2.toml`` links to it), ``pd-ros2`` bridging it to
the daemon and publishing the predicted Odometry / pose / TF back on ROS topics, and
``pd-operator --ros2`` sending the Twist commands on ``cmd_vel``; pd-record, pd-viz and pd-web
as above, for session ``bot``, whose camera (with the ``viz`` extra; ``--camera 5``: the chase
view as ``sensor_msgs/CompressedImage`` + ``CameraInfo``, 400 ms late) pd-ros2 turns into
frames with the ghost. Summary: RMS prediction error of x, y and yaw against the truth,
the number of predictions compared, and the bridge's counters (predictions republished as ROS
messages, refusals). See docs/ros2.md.

``pd-demo --async`` runs the asynchronous-sensor robot (``pd-robot-sim --scenario async``:
odometry 25 Hz, IMU 100 Hz and a pose fix 5 Hz 300 ms late, none on the 50 ms step grid, each
sample stamped with the time it was taken) over pd-link's ``link-async.toml`` (sensors
unchanged, commands 100 ms), with its operator, pd-record, pd-viz and pd-web, for session
``async``. Summary: RMS prediction error of x, y and yaw against the truth (100 ms ahead). How
the service applies a stamp between two steps is in docs/protocol.md; bench/stamps.py
compares the ways in-process.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from pd_service.logs import add_logging_args, level_of, setup_logging
from pd_service.transport import Transport
from pd_service.wire import keys

from .._base import connect
from ..errors import ServiceUnavailable
from .common import plain_text
from .record_csv import read_csv

TOOL = "pd-demo"
SESSIONS = ("paper", "paper-cam")
#: The demo's camera robot: a differential-drive robot (the async scenario, 50 ms steps) whose
#: video pd-web shows with the ghost; its lead is the paper's 500 ms uplink, a frame every 2 steps.
CAMERA_SESSION, CAMERA_LEAD, CAMERA_EVERY = "rover", 10, 2
ROS2_SESSION = "bot"
ASYNC_SESSION = "async"
ROS2_STATES = "x,y,yaw"
LEAD, RANGER_DELAY = 10, 12  # the paper's uplink and range-finder delays, steps
#: How long one process is given to stop on each signal before the next one (s).
STOP_TIMEOUT_S = 3.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def web_port(preferred: int) -> int:
    """``preferred`` if nothing listens on it on 127.0.0.1, else a free port."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", preferred))
        except OSError:
            return free_port()
    return preferred


class Proc:
    """A child process whose output is relayed line by line with a name prefix."""

    def __init__(self, name: str, args: list[str], quiet: bool = False) -> None:
        self.name = name
        self.quiet = quiet
        self.popen = subprocess.Popen(
            [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True, bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1"},
            # its own session: a Ctrl-C in the terminal reaches pd-demo alone, which then
            # stops the processes in order (the daemon last, so the others' goodbyes land)
            start_new_session=True)
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._relay, daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            line = line.rstrip("\n")
            self.lines.append(line)
            if not self.quiet:
                print(f"[{self.name:8}] {line}", flush=True)

    def stop(self, timeout: float = STOP_TIMEOUT_S) -> int | None:
        """SIGINT, then SIGTERM, then SIGKILL, each given ``timeout`` s; the exit code."""
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            if self.popen.poll() is not None:
                break
            self.popen.send_signal(sig)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                continue
        self._thread.join(2.0)
        return self.popen.returncode


def stop_all(procs: list[Proc]) -> None:
    """Stop ``procs`` in the reverse of their start order (the daemon, started first, last:
    the others' last messages still reach it)."""
    for p in reversed(procs):
        p.stop()


@contextlib.contextmanager
def packaged_link_config(name: str = "link-paper.toml") -> Iterator[Path]:
    """A file path of link rules shipped with the package (``data/link-paper.toml``, or
    ``data/link-ros2.toml`` for the ROS 2 demo)."""
    with resources.as_file(resources.files("pd_client.tools").joinpath("data", name)) as p:
        yield p


def has_viz() -> bool:
    """foxglove-sdk, mcap and Pillow (the client's ``viz`` extra) are installed."""
    return all(importlib.util.find_spec(m) is not None for m in ("foxglove", "mcap", "PIL"))


def wait_for(what: str, check: Callable[[], bool], timeout: float, procs: list[Proc]) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for p in procs:
            if p.popen.poll() is not None:
                tail = "\n".join(p.lines[-15:])
                raise RuntimeError(f"{p.name} exited with code {p.popen.returncode}:\n{tail}")
        if check():
            return
        time.sleep(0.1)
    raise RuntimeError(f"timed out after {timeout:g} s waiting for {what}")


def open_probe(endpoint: str, procs: list[Proc], timeout: float = 30.0) -> Transport:
    """A client session to the daemon, retried until the daemon listens."""
    box: list[Transport] = []

    def attempt() -> bool:
        try:
            box.append(connect([endpoint], "client"))
        except ServiceUnavailable:
            return False
        return True

    wait_for(f"the daemon to listen on {endpoint}", attempt, timeout, procs)
    return box[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog=TOOL, description=plain_text(__doc__).split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=None,
                    help="simulated steps, 50 ms each (default 420: about 30 s with start-up); "
                         "with --ros2 20 ms each (default 1000: one 20 s drive cycle)")
    ap.add_argument("--ros2", action="store_true",
                    help="the ROS 2 variant: a differential-drive robot speaking rmw_zenoh, "
                         "pd-ros2 and a Twist operator (needs the ros2 extra)")
    ap.add_argument("--async", dest="async_sensors", action="store_true",
                    help="the asynchronous-sensor robot: samples off the step grid, stamped "
                         "with their own time (default 400 steps of 50 ms)")
    ap.add_argument("--out", default="out/demo", help="output directory (default out/demo)")
    ap.add_argument("--link-config", type=Path,
                    help="link emulator rules (default: the paper's link, shipped with pd-client)")
    ap.add_argument("--seed", type=int, default=1,
                    help="the simulator's random seed (default 1)")
    ap.add_argument("--quiet", action="store_true", help="do not relay the processes' output")
    ap.add_argument("--viz-port", type=int, default=8765,
                    help="pd-viz's WebSocket port (default 8765; 0: any free port)")
    ap.add_argument("--no-viz", action="store_true", help="do not start pd-viz")
    ap.add_argument("--web-port", type=int, default=8080,
                    help="port of the live view (default 8080, a free one if taken; 0: any "
                         "free port)")
    ap.add_argument("--no-web", action="store_true", help="do not start the live view (pd-web)")
    ap.add_argument("--no-camera", action="store_true",
                    help="no camera: no camera robot (session rover); with --ros2, the robot "
                         "without its camera")
    ap.add_argument("--web-linger", type=float, default=10.0,
                    help="seconds the live view keeps serving the final state after the run "
                         "(default 10)")
    add_logging_args(ap, default_level="WARNING")
    args = ap.parse_args(argv)
    setup_logging(level_of(args) or "WARNING", args.log_format)
    if args.ros2 and args.async_sensors:
        print(f"{TOOL}: --ros2 and --async are two different demos: choose one", file=sys.stderr)
        return 2
    if args.steps is None:
        args.steps = 1000 if args.ros2 else 400 if args.async_sensors else 420
    if args.ros2 and importlib.util.find_spec("rosbags") is None:
        print(f"{TOOL}: --ros2 needs the ros2 extra: pip install 'pd-service[ros2]'",
              file=sys.stderr)
        return 2
    if args.link_config is not None and not args.link_config.is_file():
        print(f"{TOOL}: link config {args.link_config} not found", file=sys.stderr)
        return 2
    with contextlib.ExitStack() as stack:
        link_config = args.link_config or stack.enter_context(
            packaged_link_config("link-ros2.toml" if args.ros2 else
                                 "link-async.toml" if args.async_sensors else "link-paper.toml"))
        return run(args, link_config)


def run(args: argparse.Namespace, link_config: Path) -> int:
    """Start the processes, wait for the simulation to end, stop them, print the report: the
    paper demo, or with ``args.ros2`` the ROS 2 variant (pd-ros2 beside pd-link, a
    differential-drive robot and a Twist operator, and the report of :func:`report_ros2`
    with the bridge's counters, queried before the probe session closes)."""
    ros2 = args.ros2
    asy = bool(getattr(args, "async_sensors", False))
    robot = ros2 or asy  # one differential-drive session: x, y, yaw
    variant = "demo-ros2" if ros2 else "demo-async" if asy else "demo"
    out = Path(f"out/{variant}" if args.out == "out/demo" else args.out)
    if (out / "state").exists():
        shutil.rmtree(out / "state")  # a fresh daemon: no sessions restored from a past run
    out.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    zenoh_args = ["--connect", endpoint]
    procs: list[Proc] = []

    def start(name: str, *a: str) -> Proc:
        p = Proc(name, list(a), quiet=args.quiet)
        procs.append(p)
        return p

    interrupted = False
    bridge: dict[str, object] | None = None
    t0 = time.monotonic()
    try:
        with contextlib.ExitStack() as probe_open:
            print(f"{TOOL}: {'ROS 2 variant; ' if ros2 else 'asynchronous sensors; ' if asy else ''}"
                  f"daemon on {endpoint}, "
                  f"output in {out}/", flush=True)
            start("service", "-m", "pd_service", "--listen", endpoint, "--state-dir",
                  str(out / "state"), "--instance", "demo")
            probe = open_probe(endpoint, procs)
            probe_open.callback(probe.close)
            wait_for("the daemon", lambda: bool(probe.get_liveliness(keys.ALL_SERVICES, 0.5)),
                     30.0, procs)
            start("link", "-m", "pd_service.link", "--config", str(link_config), *zenoh_args,
                  "--instance", "demo", "--stats-interval", "10")
            if ros2:
                start("pd-ros2", "-m", "pd_service.ros2", "--instance", "demo", "--session",
                      ROS2_SESSION, *zenoh_args)
            wait_for("the link emulator",
                     lambda: any(r.ok for r in probe.get(keys.link_stats_key("demo"), timeout=0.5)),
                     30.0, procs)
            if ros2:
                wait_for("pd-ros2", lambda: any(r.ok for r in probe.get(
                    keys.ros2_status_key("demo"), timeout=0.5)), 30.0, procs)
            else:
                probe_open.close()
            viz = has_viz()
            mcap = ["--mcap", str(out / "run.mcap")] if viz else []
            web_url = None
            if not args.no_web:
                port = web_port(args.web_port) if args.web_port else free_port()
                start("web", "-m", "pd_client.tools", "web", "--port", str(port), *zenoh_args)
                web_url = f"http://127.0.0.1:{port}/"
                print(f"{TOOL}: live view at {web_url} (open it in a browser)", flush=True)
            camera = viz and not robot and not getattr(args, "no_camera", False)
            ros2_camera = viz and ros2 and not getattr(args, "no_camera", False)
            names = ((ROS2_SESSION,) if ros2 else (ASYNC_SESSION,) if asy
                     else (*SESSIONS, CAMERA_SESSION) if camera else SESSIONS)
            sessions = [f"--session={s}" for s in names]
            recorder = start("record", "-m", "pd_client.tools", "record", *sessions,
                             "--out", str(out), "--idle-timeout", "3",
                             *(["--until-step", str(args.steps)] if robot else []),
                             "--states", ROS2_STATES if robot else "p1,p2",
                             *(["--warmup", "20" if asy else "50"] if robot else []), *mcap,
                             *zenoh_args)
            # the recorder subscribed before the first message is sent: the MCAP holds every
            # input the daemon handles (pd-replay then reproduces each prediction exactly)
            wait_for("the recorder", lambda: any("recording" in line for line in recorder.lines),
                     30.0, procs)
            if viz and not args.no_viz:  # a live view; the demo goes on without it if it fails
                viz_port = args.viz_port or free_port()
                start("viz", "-m", "pd_client.tools", "viz", *sessions,
                      "--port", str(viz_port), *zenoh_args)
                print(f"{TOOL}: Foxglove live view on ws://127.0.0.1:{viz_port}"
                      + ("" if ros2 else " (open it in Foxglove: docs/visualize.md)"), flush=True)
            elif not viz and not ros2:
                print(f"{TOOL}: no live view / MCAP: pip install 'pd-client[viz]'", flush=True)
            if ros2:
                start("operator", "-m", "pd_client.tools", "operator", "--scenario", "diffdrive",
                      "--session", ROS2_SESSION, "--ros2", "--steps", str(args.steps),
                      *zenoh_args)
                sim = start("sim", "-m", "pd_client.tools", "sim", "--scenario", "diffdrive",
                            "--session", ROS2_SESSION, "--create-session", "--ros2",
                            *(["--camera", "5"] if ros2_camera else []),
                            "--path", "1", "--steps", str(args.steps), "--seed", str(args.seed), *zenoh_args)
            elif asy:
                start("operator", "-m", "pd_client.tools", "operator", "--scenario", "async",
                      "--session", ASYNC_SESSION, "--steps", str(args.steps), *zenoh_args)
                sim = start("sim", "-m", "pd_client.tools", "sim", "--scenario", "async",
                            "--session", ASYNC_SESSION, "--create-session", "--close-on-exit",
                            "--steps", str(args.steps), "--seed", str(args.seed), *zenoh_args)
            else:
                start("operator", "-m", "pd_client.tools", "operator",
                      *(f"--session={s}" for s in SESSIONS), "--steps", str(args.steps),
                      *zenoh_args)
                if camera:
                    rover = ["--scenario", "async", "--session", CAMERA_SESSION, "--steps",
                             str(args.steps)]
                    start("operator-rover", "-m", "pd_client.tools", "operator", *rover,
                          *zenoh_args)
                    start("sim-rover", "-m", "pd_client.tools", "sim", *rover, "--create-session",
                          "--lead", str(CAMERA_LEAD), "--camera", str(CAMERA_EVERY),
                          "--camera-view", "chase", "--path", "2",
                          "--close-on-exit", "--seed", str(args.seed), *zenoh_args)
                sim = start("sim", "-m", "pd_client.tools", "sim", "--session", "paper",
                            "--session", "paper-cam:camera", "--create-session",
                            "--path", "1", "--close-on-exit", "--steps", str(args.steps), "--seed",
                            str(args.seed), *zenoh_args)
            sim.popen.wait()
            if sim.popen.returncode != 0:
                raise RuntimeError(f"the simulator exited with code {sim.popen.returncode}")
            print(f"{TOOL}: simulation done after {time.monotonic() - t0:.1f} s; "
                  "waiting for the recorder", flush=True)
            if ros2:
                bridge = next((json.loads(r.payload) for r in probe.get(
                    keys.ros2_status_key("demo"), timeout=3.0) if r.ok), None)
        try:
            recorder.popen.wait(60)
        except subprocess.TimeoutExpired:
            recorder.stop()
        if web_url is not None and args.web_linger > 0:
            print(f"{TOOL}: the live view at {web_url} shows the final state for "
                  f"{args.web_linger:g} s more (Ctrl-C to skip)", flush=True)
            try:
                time.sleep(args.web_linger)
            except KeyboardInterrupt:
                pass
    except KeyboardInterrupt:
        interrupted = True
        print(f"\n{TOOL}: interrupted, stopping every process", flush=True)
    except RuntimeError as exc:
        print(f"{TOOL}: {exc}", file=sys.stderr, flush=True)
        interrupted = True
    finally:
        stop_all(procs)
    if interrupted:
        return 130
    if asy:
        return report_robot(out, ASYNC_SESSION, "pd-service asynchronous-sensor demo: predicted "
                            "pose 100 ms ahead (lead 2 steps)\nof the robot whose sensors "
                            "sample off the 50 ms grid, after 1 s of warm-up")
    return report_ros2(out, bridge) if ros2 else report(out)


def read_summary(out: Path) -> dict[str, Any] | None:
    """pd-record's ``<out>/summary.json``; None (said on stderr) when it was not written."""
    path = out / "summary.json"
    if not path.exists():
        print(f"{TOOL}: no summary was written ({path} missing)", file=sys.stderr)
        return None
    summary: dict[str, Any] = json.loads(path.read_text())
    return summary


def print_outputs(out: Path) -> None:
    """The report's last lines: the MCAP file and the PNG plots of the run, and the rule."""
    if (out / "run.mcap").exists():
        print(f"MCAP of the run: {out / 'run.mcap'} (pd-replay {out / 'run.mcap'})")
    pngs = sorted(out.glob("*.png"))
    print("PNG plots:" if pngs else "PNG plots: none (matplotlib not installed)")
    for p in pngs:
        print(f"  {p}")
    print("=" * 68)


def print_pose_rows(row: Mapping[str, Any]) -> None:
    """pd-record's accuracy of x, y, yaw of a differential-drive session."""
    for key, label, unit in [("rms_x", "RMS error x", "m"), ("rms_y", "RMS error y", "m"),
                             ("rms_yaw", "RMS error yaw", "rad"),
                             ("mean_var_x", "mean variance x", "m^2"),
                             ("mean_var_yaw", "mean variance yaw", "rad^2")]:
        v = row.get(key)
        print(f"{label:28}" + ("-" if v is None else f"{v:12.3g} {unit}"))
    print(f"{'predictions compared':28}{row.get('rows', 0):12d}")


def report_robot(out: Path, session: str, title: str) -> int:
    """A differential-drive demo's summary: ``title``, then pd-record's accuracy."""
    summary = read_summary(out)
    if summary is None:
        return 1
    print()
    print("=" * 68)
    print(title)
    print_pose_rows(summary.get(session, {}))
    print_outputs(out)
    return 0


def report_ros2(out: Path, bridge: Mapping[str, object] | None) -> int:
    """The ROS 2 demo's summary: pd-record's accuracy of x, y, yaw and the bridge's counters."""
    summary = read_summary(out)
    if summary is None:
        return 1
    print()
    print("=" * 68)
    print("pd-service ROS 2 demo: predicted pose 100 ms ahead (lead 5 steps) of the")
    print("differential-drive robot, over link-ros2.toml, after 1 s of warm-up")
    print_pose_rows(summary.get(ROS2_SESSION, {}))
    sessions = bridge.get("sessions") if isinstance(bridge, dict) else None
    counters = sessions.get(ROS2_SESSION, {}).get("counters") if isinstance(sessions, dict) \
        else None
    if isinstance(counters, dict):
        refusals = {k: v for k, v in counters.items() if k.startswith("refused_")}
        print(f"pd-ros2: {counters.get('received', 0)} ROS messages in, "
              f"{counters.get('forwarded', 0)} forwarded, {counters.get('refused', 0)} refused"
              f"{' ' + str(refusals) if refusals else ''}; "
              f"{counters.get('predictions_republished', 0)} predictions "
              f"republished as {counters.get('outputs_published', 0)} ROS messages")
    else:
        print("pd-ros2: no status reply")
    print_outputs(out)
    return 0


def ranger_window(out: Path) -> dict[str, dict[str, float]]:
    """RMS error and mean variance over the target steps whose prediction can use the range
    finder: its sample (12 steps old at arrival, 22 before the target) was taken while
    |p2 - p1| <= 3 on the recorded truth."""
    result: dict[str, dict[str, float]] = {}
    shift = RANGER_DELAY + LEAD
    for session in SESSIONS:
        path = out / f"{session}.csv"
        if not path.exists():
            continue
        _, cols = read_csv(path)
        steps = cols["step"].astype(int)
        gap = dict(zip(steps.tolist(), np.abs(cols["true_p2"] - cols["true_p1"]).tolist(),
                       strict=True))
        keep = np.array([gap.get(int(t) - shift, np.inf) <= 3.0 for t in steps])
        if not keep.any():
            continue
        row: dict[str, float] = {"rows": int(keep.sum()), "first": int(steps[keep].min()),
               "last": int(steps[keep].max())}
        for name in ("p1", "p2"):
            row[f"rms_{name}"] = float(np.sqrt(np.nanmean(cols[f"err_{name}"][keep] ** 2)))
            row[f"mean_var_{name}"] = float(np.nanmean(cols[f"var_{name}"][keep]))
        result[session] = row
    return result


def print_table(title: str, data: Mapping[str, Mapping[str, float]]) -> None:
    cols = [("paper", "with range finder"), ("paper-cam", "camera only")]
    print(title)
    print(f"{'':28}" + "".join(f"{label:>20}" for _, label in cols))
    for key, label in [("rms_p1", "RMS error p1"), ("rms_p2", "RMS error p2"),
                       ("mean_var_p1", "mean variance p1"), ("mean_var_p2", "mean variance p2"),
                       ("rows", "predictions compared")]:
        cells = []
        for s, _ in cols:
            v = data.get(s, {}).get(key)
            cells.append(f"{'-':>20}" if v is None else
                         (f"{v:>20d}" if isinstance(v, int) else f"{v:>20.4f}"))
        print(f"{label:28}" + "".join(cells))


def report(out: Path) -> int:
    summary = read_summary(out)
    if summary is None:
        return 1
    print()
    print("=" * 68)
    print_table("pd-service demo: predicted x(k + 10) over the paper's link, whole run "
                "after warm-up", summary)
    window = ranger_window(out)
    if window:
        w = window.get("paper", next(iter(window.values())))
        print()
        print_table(f"... while the range finder reports (target steps {w['first']}-{w['last']})",
                    window)
    if CAMERA_SESSION in summary:
        print()
        print(f"camera robot {CAMERA_SESSION}: predicted pose 500 ms ahead (lead {CAMERA_LEAD} "
              "steps), its ghost drawn on video\n500 ms old in pd-web and pd-viz")
        print_pose_rows(summary[CAMERA_SESSION])
    print_outputs(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
