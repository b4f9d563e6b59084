"""The pinhole projection of a perspective CameraFrame (pd_service.wire.pinhole) against
OpenCV's ``cv2.projectPoints`` (an independent implementation of the same camera model), and
against values computed by hand; the frame's view rules."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from pd_service.wire import decode, encode
from pd_service.wire.camera import CameraFrame
from pd_service.wire.pinhole import CameraMount, PinholeView

IMG = "/9j/AAAA"  # any base64; the projection does not read the image

MODELS = [("", []), ("plumb_bob", [-0.28, 0.07, 1e-3, -2e-3, 0.01]),
          ("rational_polynomial", [0.1, -0.05, 5e-4, 1e-3, 0.002, 0.05, -0.01, 0.003])]


def _view(model: str, D: list[float], rng: np.random.Generator) -> PinholeView:
    mount = CameraMount(x=rng.uniform(-0.3, 0.3), y=rng.uniform(-0.2, 0.2),
                        z=rng.uniform(0.2, 1.5), roll=rng.uniform(-0.1, 0.1),
                        pitch=rng.uniform(0.1, 0.6), yaw=rng.uniform(-0.3, 0.3))
    return PinholeView(K=[rng.uniform(300, 700), 0.0, rng.uniform(300, 340), 0.0,
                          rng.uniform(300, 700), rng.uniform(220, 260), 0.0, 0.0, 1.0],
                       distortion_model=model, D=D, mount=mount,  # type: ignore[arg-type]
                       body_x=rng.uniform(-5, 5), body_y=rng.uniform(-5, 5),
                       body_yaw=rng.uniform(-math.pi, math.pi))


@pytest.mark.parametrize(("model", "D"), MODELS)
def test_projection_equals_opencv(model, D) -> None:
    """Ground points ahead of random mounted cameras: our pixels equal cv2.projectPoints' with
    rvec, tvec = the world -> optical transform (R_wo^T, -R_wo^T t_wo)."""
    cv2 = pytest.importorskip("cv2")
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(20):
        view = _view(model, D, rng)
        R_wo, t_wo = view.optical_pose()
        yaw = view.body_yaw
        ahead = np.array([math.cos(yaw), math.sin(yaw)])
        side = np.array([-ahead[1], ahead[0]])
        ground = np.array([[view.body_x, view.body_y] + d * ahead + s * side
                           for d in (1.5, 3.0, 6.0) for s in (-1.0, 0.0, 1.0)])
        pts = np.column_stack([ground, np.zeros(len(ground))])
        ours = view.project(pts)
        assert not np.isnan(ours).any()
        rvec, _ = cv2.Rodrigues(R_wo.T)
        theirs, _ = cv2.projectPoints(pts, rvec, -R_wo.T @ t_wo, np.array(view.K).reshape(3, 3),
                                      np.array(D, dtype=np.float64))
        np.testing.assert_allclose(ours, theirs.reshape(-1, 2), rtol=0, atol=1e-7)
        checked += len(pts)
    assert checked == 180


def test_projection_by_hand() -> None:
    """A camera 1 m up at the body's origin, pitched 45 deg down, the robot at (2, 1) heading
    +y; fx = fy = 500, (cx, cy) = (320, 240), no distortion. With s = 1/sqrt2 the optical axes
    in the world are z = (0, s, -s), x = (1, 0, 0), y = (0, -s, -s), the camera at (2, 1, 1)."""
    view = PinholeView(K=[500.0, 0.0, 320.0, 0.0, 500.0, 240.0, 0.0, 0.0, 1.0],
                       mount=CameraMount(z=1.0, pitch=math.pi / 4), body_x=2.0, body_y=1.0,
                       body_yaw=math.pi / 2)
    # (2, 2, 0) - c = (0, 1, -1): X = 0, Y = 0, Z = 2s: the principal point.
    # (2, 3, 0) - c = (0, 2, -1): X = 0, Y = -s, Z = 3s: v = 240 - 500 / 3.
    # (3, 2, 0) - c = (1, 1, -1): X = 1, Y = 0, Z = 2s: u = 320 + 500 / sqrt2.
    # (2, 0, 0) - c = (0, -1, -1): Z = 0: no pixel.
    uv = view.project(np.array([[2.0, 2.0, 0.0], [2.0, 3.0, 0.0], [3.0, 2.0, 0.0],
                                [2.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
    np.testing.assert_allclose(uv[1], [320.0, 240.0 - 500.0 / 3.0], atol=1e-9)
    np.testing.assert_allclose(uv[2], [320.0 + 500.0 / math.sqrt(2.0), 240.0], atol=1e-9)
    assert np.isnan(uv[3]).all()  # behind the camera: no pixel


def test_frame_has_exactly_one_view_and_round_trips() -> None:
    view = PinholeView(K=[400.0, 0.0, 160.0, 0.0, 400.0, 120.0, 0.0, 0.0, 1.0],
                       distortion_model="plumb_bob", D=[0.1, 0.0, 0.0, 0.0, 0.0],
                       mount=CameraMount(z=0.5, pitch=0.3), body_x=1.0, body_y=2.0, body_yaw=0.2)
    f = CameraFrame(session="s", seq=1, t_ns=5, data=IMG, width=320, height=240, pinhole=view)
    assert decode(encode(f), CameraFrame) == f
    ghost = f.project(np.array([[3.0, 2.5], [3.2, 2.4]]))
    assert ghost is not None and len(ghost) == 2
    assert f.project(np.array([[-3.0, 2.0]])) is None  # behind: no ghost
    with pytest.raises(ValidationError, match="center_x, center_y and scale"):
        CameraFrame(session="s", seq=1, t_ns=5, data=IMG, width=320, height=240, center_x=0.0)
    with pytest.raises(ValidationError, match="not both"):
        CameraFrame(session="s", seq=1, t_ns=5, data=IMG, width=320, height=240, center_x=0.0,
                    center_y=0.0, scale=10.0, pinhole=view)
    top = CameraFrame(session="s", seq=1, t_ns=5, data=IMG, width=320, height=240,
                      center_x=1.0, center_y=2.0, scale=40.0)
    assert top.project(np.array([[1.5, 1.0]])) == [[180.0, 160.0]]


@pytest.mark.parametrize(("change", "message"), [
    ({"K": [0.0, 0, 160, 0, 400, 120, 0, 0, 1]}, "must be > 0"),
    ({"K": [400.0, 0, 160, 1, 400, 120, 0, 0, 1]}, r"\[fx, s, cx, 0, fy, cy, 0, 0, 1\]"),
    ({"distortion_model": "plumb_bob", "D": [0.1]}, "takes 5 coefficients"),
    ({"D": [0.1, 0, 0, 0, 0]}, "no distortion takes 0"),
    ({"distortion_model": "equidistant", "D": [0.0] * 4}, "distortion_model"),
])
def test_bad_pinhole_views_are_refused(change, message) -> None:
    base = {"K": [400.0, 0.0, 160.0, 0.0, 400.0, 120.0, 0.0, 0.0, 1.0], "mount": CameraMount(),
            "body_x": 0.0, "body_y": 0.0, "body_yaw": 0.0}
    with pytest.raises(ValidationError, match=message):
        PinholeView(**{**base, **change})
