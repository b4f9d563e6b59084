"""Valid example messages and hypothesis strategies for the wire tests."""

from __future__ import annotations

import copy

import numpy as np
from hypothesis import strategies as st

from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario
from pd_service.wire import (
    ClockProbe,
    ClockProbeReply,
    ClockStatus,
    Command,
    CommandEcho,
    DelayStatus,
    ErrorReport,
    LinearModelSpec,
    Measurement,
    Prediction,
    SensorSpec,
    ServiceStatus,
    SessionSpec,
    SessionStatus,
)
from pd_service.wire.messages import (
    INT64_MAX,
    INT64_MIN,
    AdaptSpec,
    ImmModelSpec,
    ModeSpec,
    SigmaSpec,
    UnscentedModelSpec,
)

PERIOD_NS = 50_000_000  # the paper's 0.05 s step


def paper_spec(session: str = "s1", epoch_ns: int = 1_700_000_000_000_000_000) -> SessionSpec:
    """The paper's vehicle-chasing example (camera + range finder), max_delay 12."""
    return paper_scenario().spec(session, epoch_ns, max_delay=RANGER_DELAY)


def paper_continuous_spec(session: str = "s1",
                          epoch_ns: int = 1_700_000_000_000_000_000) -> SessionSpec:
    """:func:`paper_spec` with the paper's double integrators in continuous time: F the
    two (position, velocity) chains, G the first's acceleration input, Qc white
    acceleration noise of the discrete model's per-step variance (0.01^2 / period)."""
    spec = paper_spec(session, epoch_ns)
    T = spec.period_ns / 1e9
    F = np.zeros((4, 4))
    F[0, 1] = F[2, 3] = 1.0
    G = np.array([[0.0], [1.0], [0.0], [0.0]])
    Qc = np.diag([0.0, 0.01**2 / T, 0.0, 0.01**2 / T])
    return SessionSpec.model_validate(
        {**spec.model_dump(), "model": {"kind": "linear", "F": F, "G": G, "Qc": Qc}})


OMNI_Q0 = [1e-14, 1e-14, 1e-14, 4e-6, 4e-6, 2.5e-5]


def omni_spec(session: str = "u1", epoch_ns: int = 0, adapt: bool = True,
              sigma: bool = False) -> SessionSpec:
    """The three-wheel omnidirectional robot (registered model "omni3") with the
    MIT-rule adaptation of its acceleration channels; pose sensor (x, y, theta)."""
    return SessionSpec(
        session=session, period_ns=10_000_000, epoch_ns=epoch_ns,
        model=UnscentedModelSpec(
            model="omni3", params={"period_s": 0.01, "mass": 10, "Q": OMNI_Q0},
            adapt=AdaptSpec(method="mit", indices=[3, 4, 5], window=20, eta=0.1) if adapt else None,
            sigma=SigmaSpec(alpha=1.0, beta=2.0, kappa=0.0) if sigma else None),
        x0=np.zeros(6), P0=np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3]),
        sensors=[SensorSpec(name="pose", kind="model", R=1e-8 * np.eye(3), delay=3, interval=1)],
        lead=5, max_delay=10,
    )


STATIONS = [(9.5, -8.5), (25.1, 18.5), (-6.1, 18.5)]
SIGMA_BEARING = float(np.deg2rad(3.5))


def imm_spec(session: str = "i1", epoch_ns: int = 0, variant: str = "imm2", node: int = 0,
             position: bool = False) -> SessionSpec:
    """The issue-10 tracking scenario: CV / CT modes, three range-bearing stations (plus a
    position sensor if ``position``)."""
    sensors = [SensorSpec(name=f"st{i + 1}", kind="range_bearing", station=np.array(st),
                          R=np.diag([0.3**2, SIGMA_BEARING**2]), delay=2, interval=1)
               for i, st in enumerate(STATIONS)]
    if position:
        sensors.append(SensorSpec(name="cam", kind="position", R=np.array([[0.04, 0.01],
                                                                          [0.01, 0.04]]),
                                  delay=1, interval=2))
    return SessionSpec(
        session=session, period_ns=100_000_000, epoch_ns=epoch_ns,
        model=ImmModelSpec(
            modes=[ModeSpec(model="imm_cv", params={"period_s": 0.1, "sigma_accel": 0.003}),
                   ModeSpec(model="imm_ct", params={"period_s": 0.1, "sigma_accel": 0.0016,
                                                     "sigma_turn_step": 0.00349})],
            transition=np.array([[0.995, 0.005], [0.005, 0.995]]), variant=variant, node=node),
        x0=np.array([0.0, 0.3, 0.0, 0.0, 0.0]),
        P0=np.diag([0.25, 0.0025, 0.25, 0.0025, np.deg2rad(1.0) ** 2]),
        sensors=sensors, lead=5, max_delay=10,
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
    base = dict(session="s1", key="pd/p9/s1/sensor/camera", seq=7,
                reason="Measurement.z: expected 2 values", t_ns=123)
    base.update(kw)
    return ErrorReport(**base)


def session_status(**kw) -> SessionStatus:
    base = dict(session="s1", instance="pd-a", state="active", now_step=100,
                counters={"accepted": 5}, published=90, latency_p50_us=41.5,
                latency_p99_us=120.0)
    base.update(kw)
    return SessionStatus(**base)


def command_echo(**kw) -> CommandEcho:
    base = dict(session="s1", seq=4, applied_ns=10_000_000_123, sent_ns=10_000_000_456)
    base.update(kw)
    return CommandEcho(**base)


def clock_probe(**kw) -> ClockProbe:
    base = dict(session="s1", probe=3, t1_ns=5_000)
    base.update(kw)
    return ClockProbe(**base)


def clock_probe_reply(**kw) -> ClockProbeReply:
    base = dict(session="s1", probe=3, t1_ns=5_000, t2_ns=10_000_005_100, t3_ns=10_000_005_120)
    base.update(kw)
    return ClockProbeReply(**base)


def clocked_session_status(**kw) -> SessionStatus:
    """A SessionStatus with the clock and delay fields of issue 43 set."""
    return session_status(
        clock=ClockStatus(known=True, offset_ns=10_000_000_000, uncertainty_ns=30_000,
                          drift_ppm=100.0, age_s=0.2, steps=1, warning=""),
        delays={"camera": DelayStatus(count=100, p50_ms=600.0, p99_ms=648.0, max_ms=650.0)},
        recommended_max_delay=33, recommended_lead=25, late_share=0.0005, **kw)


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
    CommandEcho: command_echo,
    ClockProbe: clock_probe,
    ClockProbeReply: clock_probe_reply,
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


param_numbers = st.one_of(int64, finite)
params = st.dictionaries(
    st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,10}", fullmatch=True),
    st.one_of(param_numbers, st.lists(param_numbers, min_size=1, max_size=8)), max_size=6)


@st.composite
def nonlinear_session_specs(draw) -> SessionSpec:
    """Unscented or IMM specs with arbitrary (valid) parameters: wire round trips only."""
    n = draw(st.integers(1, 6))
    max_delay = draw(st.integers(0, 1000))
    sensor_names = draw(st.lists(names, min_size=1, max_size=4, unique=True))
    probs = st.floats(0.0, 1.0)
    if draw(st.booleans()):
        adapt = None
        if draw(st.booleans()):
            idx = draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=n, unique=True))
            method = draw(st.sampled_from(["mit", "sage_husa"]))
            mit = method == "mit"
            adapt = AdaptSpec(
                method=method, indices=idx,
                window=draw(st.none() | st.integers(1, 10_000)) if mit else None,
                eta=draw(st.none() | st.floats(1e-6, 10.0)) if mit else None,
                rule=draw(st.none() | st.sampled_from(["normalised", "plain"])) if mit else None,
                forgetting=None if mit else draw(st.none() | st.floats(0.01, 0.99)),
                q_min=draw(st.none() | st.just([1e-9] * len(idx))))
        sigma = draw(st.none() | st.builds(SigmaSpec, alpha=st.floats(1e-3, 2.0),
                                           beta=finite, kappa=st.floats(-0.5, 3.0)))
        model = UnscentedModelSpec(model=draw(names), params=draw(params), adapt=adapt,
                                   sigma=sigma)
        sensors = [SensorSpec(name=s, kind="model", R=draw(psd(draw(st.integers(1, 3)))),
                              delay=draw(st.integers(0, max_delay)), interval=1)
                   for s in sensor_names]
    else:
        r = draw(st.integers(2, 8))
        rows = [draw(st.lists(probs, min_size=r, max_size=r)) for _ in range(r)]
        T = np.array([[v / sum(row) for v in row] if sum(row) > 0 else [1.0 / r] * r
                      for row in rows])
        model = ImmModelSpec(
            modes=[ModeSpec(model=draw(names), params=draw(params)) for _ in range(r)],
            transition=T, variant=draw(st.sampled_from(["single", "centralised", "imm1", "imm2"])),
            node=draw(st.integers(0, len(sensor_names) - 1)),
            mu0=draw(st.none() | st.just(np.full(r, 1.0 / r))), kappa=draw(st.floats(0.0, 3.0)))
        sensors = []
        for s in sensor_names:
            if draw(st.booleans()):
                sensors.append(SensorSpec(
                    name=s, kind="range_bearing", station=draw(vectors(2)),
                    R=np.diag(draw(st.lists(st.floats(1e-12, 1e6), min_size=2, max_size=2))),
                    delay=draw(st.integers(0, max_delay)), interval=1))
            else:
                sensors.append(SensorSpec(name=s, kind="position", R=np.eye(2) * 0.5,
                                          delay=0, interval=draw(st.integers(1, 10**6))))
    return SessionSpec(
        session=draw(names), period_ns=draw(st.integers(1, INT64_MAX)), epoch_ns=draw(int64),
        model=model, x0=draw(vectors(n)), P0=draw(psd(n)), sensors=sensors,
        lead=draw(st.integers(0, 1000)), max_delay=max_delay,
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

clock_statuses = st.builds(
    ClockStatus, known=st.booleans(), offset_ns=int64, uncertainty_ns=st.none() | int64,
    drift_ppm=finite, age_s=st.floats(0, 1e12), steps=nonneg, warning=text)
delay_statuses = st.builds(DelayStatus, count=nonneg, p50_ms=finite, p99_ms=finite,
                           max_ms=finite)

session_statuses = st.builds(
    SessionStatus, session=names, instance=names,
    state=st.sampled_from(["active", "restored", "expired", "removed"]), now_step=int64,
    counters=counters, published=nonneg, latency_p50_us=st.floats(0, 1e12),
    latency_p99_us=st.floats(0, 1e12), detail=text, clock=st.none() | clock_statuses,
    delays=st.dictionaries(names, delay_statuses, max_size=3),
    recommended_max_delay=st.none() | nonneg, recommended_lead=st.none() | nonneg,
    late_share=st.floats(0, 1))

service_statuses = st.builds(
    ServiceStatus, instance=names, sessions=st.lists(names, max_size=20), counters=counters,
    latency_p50_us=st.floats(0, 1e12), latency_p99_us=st.floats(0, 1e12),
    uptime_s=st.floats(0, 1e12), shard=st.text(max_size=64))

command_echoes = st.builds(CommandEcho, session=names, seq=nonneg, applied_ns=int64,
                           sent_ns=st.none() | int64)
clock_probes = st.builds(ClockProbe, session=names, probe=nonneg, t1_ns=int64)


@st.composite
def clock_probe_replies(draw) -> ClockProbeReply:
    t2 = draw(int64)
    return ClockProbeReply(session=draw(names), probe=draw(nonneg), t1_ns=draw(int64),
                           t2_ns=t2, t3_ns=draw(st.integers(t2, INT64_MAX)))


STRATEGIES = {
    SessionSpec: st.one_of(session_specs(), nonlinear_session_specs()),
    Measurement: measurements(),
    Command: commands(),
    CommandEcho: command_echoes,
    ClockProbe: clock_probes,
    ClockProbeReply: clock_probe_replies(),
    Prediction: predictions(),
    ErrorReport: error_reports,
    SessionStatus: session_statuses,
    ServiceStatus: service_statuses,
}


#: ``set_field`` value meaning "remove the field".
DELETE = object()


def set_field(obj: dict, path: str | bytes, value) -> dict:
    """A deep copy of a raw (decoded msgpack) message with the field at ``path`` (dotted,
    list indices as digits; or one bytes key) set to ``value``, or removed for DELETE."""
    obj = copy.deepcopy(obj)
    if isinstance(path, bytes):
        keys = [path]
    else:
        keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    parent = obj
    for k in keys[:-1]:
        parent = parent[k]
    if value is DELETE:
        del parent[keys[-1]]
    else:
        parent[keys[-1]] = value
    return obj
