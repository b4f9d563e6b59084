"""The omni robot on the daemon core (in-process, in-memory bus) with a camera 12 steps late:
what the ghost tests of pd-web and pd-viz drive (a straight line at a known pose per step)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from pd_client.tools.camera_view import render_view
from pd_service.scenarios import get_scenario
from pd_service.transport import InMemoryTransport
from pd_service.wire import Command, Measurement, Prediction, SessionSpec, decode, encode, keys
from pd_service.wire.camera import CameraFrame
from pd_service.wire.path import PredictedPath
from pd_service.wire.truth import Truth

#: Steps between the capture of a frame and its arrival.
VIDEO_DELAY = 12


def omni_spec() -> SessionSpec:
    """The omni session (50 ms steps) asking for the path of x, y, theta."""
    spec = get_scenario("omni").spec("omni", 0).model_copy(update={"period_ns": 50_000_000})
    return SessionSpec.model_validate({**spec.model_dump(), "path": {"indices": [0, 1, 2]}})


def pose(k: int) -> tuple[float, float, float]:
    """The robot's true pose at step k (m, m, rad)."""
    return 0.05 * k, 0.02 * k, 0.1


def drive(t: InMemoryTransport, spec: SessionSpec, run: Callable[[int], None], steps: int,
          frame_every: int, on_frame: Callable[[CameraFrame], None] | None = None,
          view: str = "top") -> None:
    """Per step k: a command (so the session is live), the truth, the pose sensor's sample
    of k - 3, then ``run(k)`` (the core's clock at mid-step and its run_once); every
    ``frame_every`` steps from VIDEO_DELAY on, the frame captured VIDEO_DELAY steps ago
    (passed to ``on_frame`` just after it is put), of the camera ``view`` (camera_view.VIEWS)."""
    scn = get_scenario("omni")
    for k in range(steps):
        t.put(keys.command_key("omni"), encode(Command(
            session="omni", seq=k, step=k + spec.lead, u=np.full(scn.nu, 0.01))))
        t.put(keys.truth_key("omni"), encode(Truth(
            session="omni", step=k, t_ns=spec.time_of(k), names=list(scn.state_names),
            x=np.array([*pose(k), 0.0, 0.0, 0.0]))))
        if k >= 3:
            t.put(keys.sensor_key("omni", "pose"), encode(Measurement(
                session="omni", sensor="pose", seq=k, step=k - 3, z=np.array(pose(k - 3)))))
        run(k)
        if k >= VIDEO_DELAY and k % frame_every == 0:
            f = render_view(view, "omni", k, spec.time_of(k - VIDEO_DELAY), *pose(k - VIDEO_DELAY))
            t.put(keys.camera_key("omni"), encode(f))
            if on_frame is not None:
                on_frame(f)


class OmniOutputs:
    """The daemon's outputs for the omni session, in the order published: ``preds``, and
    ``paths`` by their prediction's seq; ``frames`` is for the test's (frame, seq of the newest
    prediction when the frame was put)."""

    def __init__(self, t: InMemoryTransport) -> None:
        self.preds: list[Prediction] = []
        self.paths: dict[int, PredictedPath] = {}
        self.frames: list[tuple[CameraFrame, int]] = []
        t.subscribe(keys.prediction_key("omni"),
                    lambda s: self.preds.append(decode(bytes(s.payload), Prediction)))
        t.subscribe(keys.path_key("omni"), self._on_path)

    def _on_path(self, sample: object) -> None:
        p = decode(bytes(sample.payload), PredictedPath)  # type: ignore[attr-defined]
        self.paths[p.seq] = p

    def on_frame(self, f: CameraFrame) -> None:
        """Keep ``f`` with the newest prediction's seq."""
        self.frames.append((f, self.preds[-1].seq))
