"""Numerical health (pd_service.service.health): a session whose estimate turns non-finite or
loses positive semi-definiteness is reported, recovered (snapshot, else prior) and counted,
on the in-memory core with an injected clock."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from pd_service import native
from pd_service.estimation.linear import LinearBackend
from pd_service.estimation.nonlinear import unscented
from pd_service.service import health
from pd_service.transport import InMemoryBus
from pd_service.wire import encode, keys

from .helpers import Clock, Collector, cmd_bytes, meas_bytes, paper_spec
from .test_core import at, make_core
from .test_nonlinear import omni_spec

LEAD = paper_spec("x").lead


def world():
    bus = InMemoryBus()
    return bus, Clock(0), Collector().attach(bus.transport()), bus.transport()


class Poison:
    """Wraps a numerics function: the next ``times`` calls return a NaN state (``make_bad``
    of the real result), the others the real one."""

    def __init__(self, real, make_bad, times: int = 0) -> None:
        self.real, self.make_bad, self.times = real, make_bad, times

    def __call__(self, *a, **k):
        out = self.real(*a, **k)
        if self.times > 0:
            self.times -= 1
            return self.make_bad(a, out)
        return out


def nan_state(args, out):
    return out._replace(x=np.full_like(out.x, np.nan))


def poison_steps(monkeypatch, times: int, measured: bool = True) -> Poison:
    """The next ``times`` steps of the linear backend (``measured``: only a measured step's
    propagate then update; else every step, pure propagations too) come out with a NaN
    mean."""
    poison = Poison(LinearBackend.advance, nan_state, times=times)
    real = LinearBackend.advance

    def advance(self, state, m, U, packets, old):
        if measured and not packets:
            return real(self, state, m, U, packets, old)
        return poison(self, state, m, U, packets, old)

    monkeypatch.setattr(LinearBackend, "advance", advance)
    # the replay's C loop makes its steps without calling advance: every step through it
    monkeypatch.setattr(LinearBackend, "advance_run",
                        lambda self, state, a, *rest: (state, a, 0))
    return poison


def drive(core, cli, clock, session, steps, sensor="ranger", z=(1.0,)):
    for k in steps:
        clock.t = at(k + 0.1)
        cli.put(keys.sensor_key(session, sensor), meas_bytes(session, sensor, k, list(z), k))
        core.run_once()
        clock.t = at(k + 0.6)
        core.run_once()


def test_check_is_cheap_and_catches_what_it_should():
    P = np.eye(4)
    assert health.inspect(np.zeros(4), P)[0] is None
    assert "non-finite" in health.inspect(np.array([0, np.nan, 0, 0.0]), P)[0]
    assert "non-finite" in health.inspect(np.zeros(4), np.full((4, 4), np.inf))[0]
    Pn = P.copy()
    Pn[2, 2] = -1e-3
    assert "positive" in health.inspect(np.zeros(4), Pn)[0]
    assert health.inspect(np.zeros(2), np.zeros((2, 2)))[0] is None  # a known state is fine
    assert health.thoroughly_healthy(P)
    assert not health.thoroughly_healthy(np.array([[1.0, 2.0], [2.0, 1.0]]))  # eig -1


def _with_min_eig(rng, n: int, lam: float, scale: float = 1.0) -> np.ndarray:
    """A symmetric (n, n) matrix with eigenvalues in [lam, scale], one of them lam."""
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    ev = rng.uniform(max(lam, 0.0), max(lam, scale), size=n)
    ev[0] = lam
    return (Q * ev) @ Q.T


def test_thorough_test_gives_the_eigenvalues_verdict():
    """The C Cholesky shortcut only ever says "healthy" where the eigenvalues say so, and
    is what decides the usual healthy covariance (where the kernel is in use)."""
    rng = np.random.default_rng(11)
    tol = health.EIG_TOL
    cases = [np.zeros((0, 0)), np.eye(4), np.zeros((3, 3)), np.array([[1.0, 2.0], [2.0, 1.0]]),
             np.full((2, 2), np.nan), np.array([[1.0, np.inf], [0.0, 1.0]]),
             np.eye(70), np.eye(4, dtype=np.float32), np.eye(6)[::2, ::2],
             np.asfortranarray(_with_min_eig(rng, 5, 0.3)), np.array([[1.0, 5.0], [-5.0, 1.0]])]
    for n in (1, 2, 4, 9):
        for scale in (1e-12, 1.0, 1e6):
            for f in (-10.0, -1.01, -0.99, -0.51, -0.49, 0.0, 1e-3, 0.5):
                lam = f * tol * max(1.0, scale)
                cases.append(_with_min_eig(rng, n, lam, scale))
    for P in cases:
        assert health.thoroughly_healthy(P) == health.thoroughly_healthy_eig(P), P
    k = health._MOMENTS
    if k is not None:
        assert k.clearly_psd(np.eye(4), 0.5 * tol) is True
        assert k.clearly_psd(_with_min_eig(rng, 4, 0.1), 0.5 * tol) is True
        assert k.clearly_psd(_with_min_eig(rng, 4, -2 * tol), 0.5 * tol) is False
        with pytest.raises(TypeError):
            k.clearly_psd(np.eye(65), 0.5 * tol)


@pytest.mark.parametrize("n", [4, 17])  # Python floats (n^2 <= 256) and numpy's reductions
def test_check_agrees_with_numpy_on_both_paths(n):
    rng = np.random.default_rng(n)
    for _ in range(200):
        x = rng.normal(size=n) * 10.0 ** rng.integers(-300, 300)
        P = np.diag(np.abs(rng.normal(size=n))) * 10.0 ** rng.integers(-300, 300)
        if rng.random() < 0.3:
            P[rng.integers(n), rng.integers(n)] = rng.choice([np.nan, np.inf, -np.inf, -1.0, 1e308])
        if rng.random() < 0.2:
            x[rng.integers(n)] = rng.choice([np.nan, np.inf, -np.inf, 1e308])
        if rng.random() < 0.1:  # inf and -inf together: fsum raises, not overflows
            P[0, 1], P[1, 0] = np.inf, -np.inf
        finite = np.isfinite(x).all() and np.isfinite(P).all()
        want = None if finite and P.diagonal().min() >= 0 else (
            "non-finite" if not finite else "positive")
        got, xs, ps = health.inspect(x, P)
        assert (got is None) == (want is None), (x, P, got)
        np.testing.assert_array_equal(np.array(xs), x)  # the values read, as they are
        np.testing.assert_array_equal(np.array(ps).reshape(n, n), P)
        if want is not None:
            assert want in got


@pytest.mark.parametrize("n", [0, 1, 4, 5, 17])  # array headers: fixarray, array 16
def test_packed_check_gives_the_checks_verdict_and_msgpacks_bytes(n):
    """inspect_packed (C where compiled: service/_moments.c) against inspect and msgpack:
    the same verdict, and x's and P's values packed byte for byte as msgpack.packb of the
    lists, for values of every kind and for arrays of other layouts and dtypes (taken by
    the Python form)."""
    rng = np.random.default_rng(100 + n)
    special = [np.nan, np.inf, -np.inf, -1.0, -0.0, 0.0, 1e308, -1e308, 5e-324, -5e-324]
    for i in range(300):
        x = rng.normal(size=n) * 10.0 ** rng.integers(-300, 300)
        P = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-300, 300)
        for _ in range(int(rng.integers(0, 3)) if n else 0):
            if rng.random() < 0.5:
                x[rng.integers(n)] = rng.choice(special)
            P[rng.integers(n), rng.integers(n)] = rng.choice(special)
        if i % 4 == 0 and n:
            P[np.diag_indices(n)] = np.abs(P.diagonal())  # often healthy
        if i % 5 == 1:
            P = np.asfortranarray(P)  # other layouts: strided reads
        elif i % 5 == 2:
            x, P = np.concatenate([x, x])[::2], np.hstack([P, P])[:, :n]
        elif i % 5 == 3:
            with np.errstate(over="ignore"):  # the Python form (float32: inf where too big)
                x, P = x.astype(np.float32), P.astype(np.float32)
        elif i % 5 == 4 and n:  # not aligned in memory
            raw = b"\0" + P.tobytes()
            P = np.frombuffer(raw, dtype=np.float64, offset=1).reshape(n, n)
            assert not P.flags.aligned
        bad, xb, pb = health.inspect_packed(x, P)
        want, xs, ps = health.inspect(x, P)
        assert bad == want, (x, P)
        assert xb == msgpack.packb(xs) and pb == msgpack.packb(ps)


def test_packed_check_kernel_refuses_what_it_does_not_take():
    k = health._MOMENTS
    if k is None:
        pytest.skip(f"no C kernel here ({native.STATUS}): the Python form runs")
    with pytest.raises(TypeError):
        k.moments(np.zeros(3), np.zeros((3, 4)))
    for bad in ([0.0], np.zeros(3, dtype=np.int64), np.zeros((3, 1))):
        with pytest.raises(TypeError):
            k.moments(bad, np.zeros((3, 3)))
    with pytest.raises(TypeError):
        k.moments(np.zeros(2), np.zeros((2, 2, 1)))
    with pytest.raises(TypeError):
        k.moments(np.zeros(2))


def test_a_poisoned_posterior_is_recovered_from_the_snapshot(tmp_path, monkeypatch):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    cli.put(keys.config_key("calm"), encode(paper_spec("calm")))
    # one command: "calm" ticks every step (80 steps < idle_after_s) without more traffic
    cli.put(keys.command_key("calm"), cmd_bytes("calm", LEAD, [0.0]))
    core.run_once()
    drive(core, cli, clock, "s1", range(0, 40))
    sess = core._routes["s1"].sess
    assert sess.snapshot is not None
    # the next measured step (propagate, then update) writes NaN into its
    # posterior: without recovery every later prediction of s1 would be NaN
    # (internal_error every step)
    poison = poison_steps(monkeypatch, times=1)
    drive(core, cli, clock, "s1", range(40, 80))
    assert poison.times == 0
    c = core.session_status("s1").counters
    assert c["unhealthy"] >= 1 and c["recovered"] >= 1 and c["recovered_from_snapshot"] >= 1
    assert c.get("internal_error", 0) == 0
    s = core.service_status().counters
    assert s["recovered"] == c["recovered"]
    preds = col.predictions["s1"]
    assert set(range(40, 80)) <= {p.step - LEAD for p in preds}  # one per step, none lost
    assert all(np.isfinite(p.x).all() and np.isfinite(p.P).all() for p in preds)
    assert any("recovered from its snapshot" in e.reason for e in col.errors["s1"])
    # the innocent session never noticed
    assert set(range(1, 80)) <= {p.step - LEAD for p in col.predictions["calm"]}
    assert core.session_status("calm").counters.get("recovered", 0) == 0


def test_without_a_snapshot_the_session_restarts_from_its_prior(tmp_path, monkeypatch):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    drive(core, cli, clock, "s1", range(0, 10))
    sess = core._routes["s1"].sess
    sess.snapshot, sess.next_snapshot_step = None, 10**9  # none from now on
    poison_steps(monkeypatch, times=1)
    drive(core, cli, clock, "s1", range(10, 30))
    c = core.session_status("s1").counters
    assert c["recovered_from_prior"] >= 1 and c.get("internal_error", 0) == 0
    assert set(range(10, 30)) <= {p.step - LEAD for p in col.predictions["s1"]}
    assert core._routes["s1"].sess.intake.est is core._routes["s1"].sess.est


def test_unrecoverable_is_reported_then_retried_not_every_step(tmp_path, monkeypatch):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("s1"), encode(paper_spec("s1")))
    core.run_once()
    drive(core, cli, clock, "s1", range(0, 10))
    # every node, the prior's pure propagations too
    poisons = [poison_steps(monkeypatch, 10**9, measured=False)]
    drive(core, cli, clock, "s1", range(10, 30))  # 1 s at 50 ms
    c = core.session_status("s1").counters
    assert c["internal_error"] >= 10 and c.get("recovered", 0) == 0
    assert c["unhealthy"] >= 10
    assert any("not even from the prior" in e.reason for e in col.errors["s1"])
    for poison in poisons:  # the numerics are well again: recovered at the next attempt
        poison.times = 0
    drive(core, cli, clock, "s1", range(30, 60))
    assert core.session_status("s1").counters["recovered"] >= 1
    assert set(range(52, 60)) <= {p.step - LEAD for p in col.predictions["s1"]}


@pytest.mark.parametrize("times", [1, 3])
def test_unscented_session_with_a_nan_propagation_is_recovered(tmp_path, monkeypatch, times):
    bus, clock, col, cli = world()
    core = make_core(bus, clock, tmp_path)
    cli.put(keys.config_key("u1"), encode(omni_spec("u1")))
    core.run_once()
    lead = omni_spec("u1").lead
    drive(core, cli, clock, "u1", range(0, 30), sensor="pose", z=(0.0, 0.0, 0.0))

    def bad(args, out):
        return dataclasses.replace(out, x=np.full_like(out.x, np.nan))

    poison = Poison(unscented.UnscentedBackend.propagate, bad, times=times)
    monkeypatch.setattr(unscented.UnscentedBackend, "propagate",
                        lambda self, *a: poison(self, *a))
    drive(core, cli, clock, "u1", range(30, 60), sensor="pose", z=(0.0, 0.0, 0.0))
    c = core.session_status("u1").counters
    assert poison.times == 0, c
    assert c.get("recovered", 0) >= 1 and c.get("internal_error", 0) == 0, c
    preds = col.predictions["u1"]
    assert set(range(30, 60)) <= {p.step - lead for p in preds}
    assert all(np.isfinite(p.x).all() for p in preds)
