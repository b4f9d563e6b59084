"""Valid example messages and hypothesis strategies for the wire tests."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from pd_service.wire import (
    Command,
    ErrorReport,
    LinearModelSpec,
    Measurement,
    Prediction,
    SensorSpec,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
)
from pd_service.wire.messages import INT64_MAX, INT64_MIN

PERIOD_NS = 50_000_000  # the paper's 0.05 s step


def paper_spec(session: str = "s1", epoch_ns: int = 1_700_000_000_000_000_000) -> SessionSpec:
    """The paper's vehicle-chasing example: x = (p1, p2, v1, v2), camera + range finder."""
    T = 0.05
    A = np.eye(4)
    A[0, 2] = A[1, 3] = T
    B = np.array([[0.0], [0.0], [T], [0.0]])
    Q = np.diag([1e-4, 1e-4, 1e-3, 1e-3])
    return SessionSpec(
        session=session, period_ns=PERIOD_NS, epoch_ns=epoch_ns,
        model=LinearModelSpec(A=A, B=B, Q=Q),
        x0=np.zeros(4), P0=np.eye(4),
        sensors=[
            SensorSpec(name="camera", H=np.eye(2, 4), R=0.25 * np.eye(2), delay=10, interval=2),
            SensorSpec(name="ranger", H=np.array([[-1.0, 1.0, 0.0, 0.0]]), R=np.array([[0.01]]),
                       delay=12, interval=1),
        ],
        lead=10, max_delay=12,
    )


def measurement(**kw) -> Measurement:
    base = dict(session="s1", sensor="camera", seq=7, step=100, z=np.array([0.5, 1.5]))
    base.update(kw)
    return Measurement(**base)


def command(**kw) -> Command:
    base = dict(session="s1", seq=3, step=120, u=np.array([0.5]))
    base.update(kw)
    return Command(**base)


def prediction(n: int = 4, **kw) -> Prediction:
    rng = np.random.default_rng(n)
    L = rng.normal(size=(n, n))
    P = L @ L.T
    P = 0.5 * (P + P.T)
    base = dict(session="s1", seq=11, step=110, t_ns=5_500_000_000, x=rng.normal(size=n), P=P,
                newest_step=98, made_ns=5_000_000_123,
                counters={"accepted": 10, "late": 2, "rejected_dim": 0})
    base.update(kw)
    return Prediction(**base)


def error_report(**kw) -> ErrorReport:
    base = dict(session="s1", key="pd/s1/sensor/camera", seq=7,
                reason="Measurement.z: expected 2 values", t_ns=123)
    base.update(kw)
    return ErrorReport(**base)


def session_status(**kw) -> SessionStatus:
    base = dict(session="s1", instance="pd-a", state="active", now_step=100,
                counters={"accepted": 5}, published=90, latency_p50_us=41.5,
                latency_p99_us=120.0)
    base.update(kw)
    return SessionStatus(**base)


def service_status(**kw) -> ServiceStatus:
    base = dict(instance="pd-a", sessions=["s1", "s2"], counters={"ticks": 5},
                latency_p50_us=30.0, latency_p99_us=99.5, uptime_s=12.25, shard="0/2")
    base.update(kw)
    return ServiceStatus(**base)


#: One valid example per message type.
EXAMPLES = {
    SessionSpec: paper_spec,
    Measurement: measurement,
    Command: command,
    Prediction: prediction,
    ErrorReport: error_report,
    SessionStatus: session_status,
    ServiceStatus: service_status,
}

# --- hypothesis strategies --------------------------------------------------------------

names = st.from_regex(r"[a-z0-9][a-z0-9_-]{0,63}", fullmatch=True)
int64 = st.integers(INT64_MIN, INT64_MAX)
nonneg = st.integers(0, INT64_MAX)
finite = st.floats(allow_nan=False, allow_infinity=False)
counters = st.dictionaries(st.text(min_size=1, max_size=64), int64, max_size=8)
text = st.text(max_size=200)


def vectors(n: int) -> st.SearchStrategy[np.ndarray]:
    return st.lists(finite, min_size=n, max_size=n).map(np.array)


def matrices(rows: int, cols: int) -> st.SearchStrategy[np.ndarray]:
    return st.lists(finite, min_size=rows * cols, max_size=rows * cols).map(
        lambda v: np.array(v).reshape(rows, cols))


def _dense_psd(args: tuple[int, int, int, float]) -> np.ndarray:
    n, rank, seed, scale = args
    L = np.random.default_rng(seed).normal(size=(n, rank)) * scale
    M = L @ L.T
    return 0.5 * (M + M.T)


def psd(n: int) -> st.SearchStrategy[np.ndarray]:
    """Symmetric PSD n x n: dense of any rank and scale, or diagonal with any non-negative
    finite entries."""
    dense = st.tuples(st.just(n), st.integers(0, n), st.integers(0, 2**32 - 1),
                      st.sampled_from([1e-6, 1.0, 1e3, 1e6])).map(_dense_psd)
    diag = st.lists(st.floats(0.0, 1e300), min_size=n, max_size=n).map(np.diag)
    return st.one_of(dense, diag)


@st.composite
def sensor_specs(draw, n: int, max_delay: int, name: str) -> SensorSpec:
    m = draw(st.integers(1, 3))
    return SensorSpec(name=name, H=draw(matrices(m, n)), R=draw(psd(m)),
                      delay=draw(st.integers(0, max_delay)), interval=draw(st.integers(1, 10**6)))


@st.composite
def session_specs(draw) -> SessionSpec:
    n = draw(st.integers(1, 6))
    r = draw(st.integers(1, 3))
    max_delay = draw(st.integers(0, 1000))
    sensor_names = draw(st.lists(names, min_size=1, max_size=4, unique=True))
    return SessionSpec(
        session=draw(names), period_ns=draw(st.integers(1, INT64_MAX)), epoch_ns=draw(int64),
        model=LinearModelSpec(A=draw(matrices(n, n)), B=draw(matrices(n, r)), Q=draw(psd(n))),
        x0=draw(vectors(n)), P0=draw(psd(n)),
        sensors=[draw(sensor_specs(n, max_delay, s)) for s in sensor_names],
        lead=draw(st.integers(0, 10_000)), max_delay=max_delay,
        publish_every=draw(st.integers(1, INT64_MAX)),
        command_hold=draw(st.sampled_from(["hold", "zero"])),
    )


@st.composite
def measurements(draw) -> Measurement:
    m = draw(st.integers(1, 6))
    stamp = draw(st.sampled_from(["step", "t_ns"]))
    return Measurement(
        session=draw(names), sensor=draw(names), seq=draw(nonneg),
        step=draw(nonneg) if stamp == "step" else None,
        t_ns=draw(int64) if stamp == "t_ns" else None,
        z=draw(vectors(m)), R=draw(st.none() | psd(m)),
    )


@st.composite
def commands(draw) -> Command:
    stamp = draw(st.sampled_from(["step", "issued_ns"]))
    return Command(
        session=draw(names), seq=draw(nonneg),
        step=draw(nonneg) if stamp == "step" else None,
        issued_ns=draw(int64) if stamp == "issued_ns" else None,
        u=draw(st.integers(1, 6).flatmap(vectors)),
    )


@st.composite
def predictions(draw) -> Prediction:
    n = draw(st.integers(1, 8))
    return Prediction(
        session=draw(names), seq=draw(nonneg), step=draw(nonneg), t_ns=draw(int64),
        x=draw(vectors(n)), P=draw(psd(n)), newest_step=draw(st.none() | nonneg),
        made_ns=draw(int64), counters=draw(counters),
    )


error_reports = st.builds(
    ErrorReport, session=names, key=st.text(max_size=512), seq=st.none() | nonneg,
    reason=st.text(max_size=1024), t_ns=int64)

session_statuses = st.builds(
    SessionStatus, session=names, instance=names,
    state=st.sampled_from(["active", "restored", "expired", "removed"]), now_step=int64,
    counters=counters, published=nonneg, latency_p50_us=st.floats(0, 1e12),
    latency_p99_us=st.floats(0, 1e12), detail=text)

service_statuses = st.builds(
    ServiceStatus, instance=names, sessions=st.lists(names, max_size=20), counters=counters,
    latency_p50_us=st.floats(0, 1e12), latency_p99_us=st.floats(0, 1e12),
    uptime_s=st.floats(0, 1e12), shard=st.text(max_size=64))

STRATEGIES = {
    SessionSpec: session_specs(),
    Measurement: measurements(),
    Command: commands(),
    Prediction: predictions(),
    ErrorReport: error_reports,
    SessionStatus: session_statuses,
    ServiceStatus: service_statuses,
}
