"""The C form of LinearBackend.advance (pd_service/estimation/_kalman.c) against its numpy form.

The numpy form is the reference: the same backend is run twice on the same random steps,
once with the kernel and once without (``use_kernel = False``), and every mean, covariance and
stored gain must agree to rounding. A (nearly) singular innovation covariance makes the
kernel hand the step back to the numpy form; bad arguments raise, never crash. (The replay's
C loop, ``_kalman.replay``, against the step-by-step loop: test_replay_cache.py.)
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pd_service.estimation import LinearModel, Sensor
from pd_service.estimation.linear import _KALMAN, _SPLIT, Gaussian, LinearBackend, read_stages
from pd_service.estimation.replay import Packet

pytestmark = pytest.mark.skipif(
    _KALMAN is None, reason="the C kernel is not in use here (PD_SERVICE_PURE=1, or no C "
                            "compiler at install time): the numpy form runs everywhere")

RTOL = 1e-10


def close(a: np.ndarray, b: np.ndarray) -> bool:
    scale = max(1.0, float(np.max(np.abs(b))) if b.size else 1.0)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=RTOL, atol=RTOL * scale))


def random_backend(rng: np.random.Generator, n: int, nu: int) -> LinearBackend:
    A = rng.standard_normal((n, n))
    A *= 0.95 / max(1e-9, max(abs(np.linalg.eigvals(A))))
    L = rng.standard_normal((n, n)) * 0.2
    model = LinearModel(A=A, B=rng.standard_normal((n, nu)), Q=L @ L.T + 1e-3 * np.eye(n))
    sensors = []
    j = int(rng.integers(n))
    unit = np.zeros((1, n))
    unit[0, j] = 1.0
    for i, H in enumerate([unit, rng.standard_normal((1, n)),
                           rng.standard_normal((int(rng.integers(2, 6)), n))]):
        Lr = rng.standard_normal((H.shape[0], H.shape[0])) * 0.3
        sensors.append(Sensor(name=f"s{i}", H=H, R=Lr @ Lr.T + 0.05 * np.eye(H.shape[0])))
    return LinearBackend(model, sensors, int(rng.integers(1, 8)))


def both(backend: LinearBackend, state: Gaussian, m: int, U: np.ndarray,
         packets: list[Packet], old: Gaussian | None) -> tuple[Gaussian, Gaussian]:
    backend.use_kernel = True
    got = backend.advance(state, m, U, packets, old)
    backend.use_kernel = False
    want = backend.advance(state, m, U, packets, old)
    backend.use_kernel = True
    return got, want


def stages_of(b: LinearBackend, g: Gaussian) -> list:
    """A state's stages, read: per packet (sensor, kind, j, c, z, K)."""
    return read_stages(g.stages, b.model.n)


def assert_same(got: Gaussian, want: Gaussian, b: LinearBackend) -> None:
    assert close(got.x, want.x) and close(got.P, want.P)
    assert np.array_equal(got.P, got.P.T)  # exactly symmetric, as the numpy form
    assert got.src is want.src and got.m == want.m and got.sensors == want.sensors
    gs, ws = stages_of(b, got), stages_of(b, want)
    assert len(gs) == len(ws)
    for g, w in zip(gs, ws, strict=True):
        assert g[:3] == w[:3]  # sensor, kind, j
        assert close(g[5], w[5])  # K
        assert close(g[4], w[4]) and abs(g[3] - w[3]) <= RTOL * abs(w[3])  # z, c


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 8), nu=st.integers(0, 2))
def test_the_kernel_gives_the_numpy_form_to_rounding(seed: int, n: int, nu: int) -> None:
    rng = np.random.default_rng(seed)
    b = random_backend(rng, n, nu)
    L = rng.standard_normal((n, n))
    state = Gaussian(rng.standard_normal(n), L @ L.T + np.eye(n))
    prev: Gaussian | None = None
    for _ in range(12):
        m = int(rng.integers(0, b._M + 3))  # beyond the tables too (an idle session)
        U = rng.standard_normal((m, nu))
        present = sorted(int(i) for i in rng.choice(3, size=int(rng.integers(0, 4)),
                                                    replace=False))
        packets = []
        for i in present:
            r = b.sensors[i].m
            R = None
            if rng.random() < 0.3:  # a per-sample override
                Lr = rng.standard_normal((r, r)) * 0.3
                R = Lr @ Lr.T + 0.05 * np.eye(r)
            packets.append(Packet(i, rng.standard_normal(r) * 3.0, R))
        got, want = both(b, state, m, U, packets, None)
        assert_same(got, want, b)
        # the same step again, offered its previous result: covariance reused, means re-run
        # (only commands changed), or only a packet that joined it updated
        U2 = U + rng.standard_normal(U.shape)
        again, want2 = both(b, state, m, U2, packets, want)
        assert_same(again, want2, b)
        if packets:
            fewer = packets[:1]
            first = b.advance(state, m, U, fewer, None)
            joined, want3 = both(b, state, m, U, packets, first)
            assert_same(joined, want3, b)
        prev, state = state, want
    assert prev is not None


def continuous_backend(rng: np.random.Generator, n: int, nu: int,
                       period: float = 0.05) -> LinearBackend:
    """A continuous-time model (Taylor polynomials: ||F||_1 period <= 1/2) and the three
    sensors of :func:`random_backend`."""
    F = rng.standard_normal((n, n))
    F *= rng.uniform(0.1, 9.0) / max(float(np.abs(F).sum(axis=0).max()), 1e-9)
    L = rng.standard_normal((n, n)) * 0.5
    model = LinearModel.continuous(F, rng.standard_normal((n, nu)), L @ L.T, period)
    assert model.taylor is not None
    tmp = random_backend(rng, n, nu)
    return LinearBackend(model, tmp.sensors, int(rng.integers(2, 8)))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 8), nu=st.integers(0, 2))
def test_the_kernels_split_step_gives_the_numpy_form_to_rounding(seed: int, n: int,
                                                                 nu: int) -> None:
    """Steps with packets at their own times and commands taking effect inside steps:
    ``_kalman.split`` against :meth:`LinearBackend.split_step`."""
    rng = np.random.default_rng(seed)
    b = continuous_backend(rng, n, nu)
    T = b._period
    L = rng.standard_normal((n, n))
    state = Gaussian(rng.standard_normal(n), L @ L.T + np.eye(n))
    for _ in range(10):
        m = int(rng.integers(0, b._M))
        packets = []
        for i in range(3):
            for _ in range(int(rng.integers(0, 3))):
                off = 0.0 if rng.random() < 0.2 else float(rng.uniform(0, T))
                if any(p.sensor == i and p.offset == off for p in packets):
                    continue
                packets.append(Packet(i, rng.standard_normal(b.sensors[i].m) * 3.0, None, off))
        packets.sort(key=lambda p: (p.offset, p.sensor))
        end = m + 1 if packets and packets[-1].offset > 0.0 else m
        U = rng.standard_normal((end, nu))
        cuts = None
        if nu and end and rng.random() < 0.6:
            rows = sorted(set(rng.integers(0, end, size=int(rng.integers(1, 3))).tolist()))
            cuts = [(r, float(rng.uniform(0, T)), rng.standard_normal(nu)) for r in rows]
        if cuts is None and end == m:
            continue  # a grid step: the other test's
        b.use_kernel = True
        got = b.advance(state, m, U, packets, None, cuts)
        want = b.split_step(state, m, U, packets, cuts)
        taken = _SPLIT(Gaussian, b._jumps, b._G, b._single, state, m, U, packets,
                       cuts or [], b._coef, b._period, not packets)
        assert taken is not None  # the kernel took it (no singular S here)
        assert np.array_equal(taken.x, got.x)
        assert close(got.x, want.x) and close(got.P, want.P)
        assert np.array_equal(got.P, got.P.T)
        if packets:
            assert np.array_equal(taken.P, got.P)
            assert got.src is None and want.src is None
        else:  # commands inside steps alone: the grid step's covariance, the mean walked
            assert got.src is state.P and np.array_equal(taken.P, state.P)
            b.use_kernel = False
            alone = b.advance(state, m, U, packets, None, cuts)
            assert close(alone.x, got.x) and close(alone.P, got.P)
            assert np.array_equal(alone.x, b.split_step(state, m, U, [], cuts, True).x)
            b.use_kernel = True
        state = want


def test_a_singular_innovation_covariance_goes_to_the_numpy_form() -> None:
    """Two equal rows with zero noise on a known direction: S is singular, the kernel hands
    the step back, and the backend's result is the numpy form's (pseudo-inverse) bits."""
    n = 3
    H = np.array([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    model = LinearModel(A=np.eye(n), B=np.zeros((n, 0)), Q=np.zeros((n, n)))
    b = LinearBackend(model, [Sensor(name="twin", H=H, R=np.zeros((2, 2)))], 4)
    P = np.diag([0.0, 1.0, 2.0])
    state = Gaussian(np.zeros(n), P)
    assert _KALMAN.advance(Gaussian, b._jumps, b._G, b._single, state, 1, np.empty((1, 0)),
                           [Packet(0, np.array([0.0, 0.0]), None)], None) is None
    got, want = both(b, state, 1, np.empty((1, 0)), [Packet(0, np.array([0.0, 0.0]), None)],
                     None)
    assert np.array_equal(got.x, want.x) and np.array_equal(got.P, want.P)


def test_a_row_with_zero_innovation_variance_tells_nothing() -> None:
    n = 2
    model = LinearModel(A=np.eye(n), B=np.zeros((n, 0)), Q=np.zeros((n, n)))
    b = LinearBackend(model, [Sensor(name="x", H=np.array([[1.0, 0.0]]), R=np.zeros((1, 1)))],
                      4)
    state = Gaussian(np.array([1.0, 2.0]), np.diag([0.0, 1.0]))
    got, want = both(b, state, 0, np.empty((0, 0)), [Packet(0, np.array([5.0]), None)], None)
    assert_same(got, want, b)
    assert np.array_equal(got.x, state.x) and np.array_equal(got.P, state.P)
    assert isinstance(got.stages, bytes)
    assert not np.any(stages_of(b, got)[0][5]) and stages_of(b, got)[0][3] == 0.0


_P2 = np.eye(2)
_UNIT = [(1, np.array([1.0, 0.0]), None, np.eye(1), 1.0, 0)]  # linear._rows of e_0


def _step(k, packets, rows=_UNIT, state=None, old=None):  # type: ignore[no-untyped-def]
    """advance with m = 0 (no jump: the tables are not read)."""
    return k.advance(Gaussian, (None,), None, rows, state or Gaussian(np.zeros(2), _P2), 0,
                     np.empty((0, 0)), packets, old)


def _jump(k, n, A, P, G=None, U=None):  # type: ignore[no-untyped-def]
    """advance with m = 1 and no packets (the jump only)."""
    x = "x" if n == 0 else np.zeros(n)
    return k.advance(Gaussian, (None, (A, None, np.eye(len(A)))), G,
                     [], Gaussian(x, P), 1, np.empty((1, 0)) if U is None else U, [], None)


def _reusing(k, stages):  # type: ignore[no-untyped-def]
    """advance offered an old state that it reuses, with these stages."""
    return _step(k, [], old=Gaussian(np.zeros(2), _P2, _P2, 0, (), stages))


@pytest.mark.parametrize("call", [
    lambda k: _jump(k, 3, np.eye(2), np.eye(3)),  # A of another size
    lambda k: _jump(k, 3, np.eye(3), np.eye(2)),  # P of another size
    lambda k: _jump(k, 2, np.eye(2), np.eye(2), np.ones((2, 1)), np.ones(3)),  # G too narrow
    lambda k: _jump(k, 2, np.eye(2), np.eye(2), np.ones(2), np.ones(1)),  # G not a matrix
    lambda k: _jump(k, 65, np.eye(65), np.eye(65)),  # beyond MAX_N
    lambda k: _jump(k, 0, np.eye(2), np.eye(2)),  # x not numbers
    lambda k: _step(k, [Packet(0, np.zeros(1), None)], state=Gaussian(np.zeros(2), np.eye(3))),
    lambda k: _step(k, [Packet(5, np.zeros(1), None)]),  # an unknown sensor
    lambda k: _step(k, [Packet(0, np.zeros(2), None)]),  # z of another size
    lambda k: _step(k, [Packet(0, np.zeros(1), None)],
                    rows=[(1, np.array([1.0, 0.0]), None, np.eye(1), 1.0, 7)]),  # j outside
    lambda k: _step(k, [(0,)], rows=[]),
    lambda k: _step(k, [Packet(0, np.zeros(3), None)],
                    rows=[(3, np.ones((2, 2)), None, np.eye(2), 0.0, -1)]),
    lambda k: _step(k, ()),  # packets not a list
    lambda k: k.fill(np.zeros((4, 2)), 0, 1),
    lambda k: k.advance(Gaussian, (), None, [], Gaussian(np.zeros(2), np.eye(2)), 0,
                        np.empty((0, 0)), []),
    lambda k: k.advance(dict, (None,), None, [], Gaussian(np.zeros(2), np.eye(2)), 0,
                        np.empty((0, 0)), [], None),
    lambda k: k.advance(Gaussian, (None,), None, [], Gaussian(np.zeros(2), np.eye(2)), 1,
                        np.empty((1, 0)), [], None),
    lambda k: k.advance(Gaussian, (None,), None, [], Gaussian(np.zeros(2), np.eye(2)), 0,
                        np.empty((0, 0)), [], (1, 2)),
    lambda k: k.advance(Gaussian, (None, 5), None, [], Gaussian(np.zeros(2), np.eye(2)), 1,
                        np.empty((1, 0)), [], None),
    lambda k: k.advance(Gaussian, (None,), None, [], Gaussian(np.zeros(2), np.eye(2)), 0,
                        np.empty((0, 0)), [(0,)], None),
    lambda k: k.fill(np.zeros((4, 2)), 0, "1", np.zeros(2)),
    lambda k: k.replay(Gaussian, (None,), None, [], Gaussian(np.zeros(2), np.eye(2)), 0, (1,),
                       np.zeros((2, 0)), 0, {}, {}, None),  # steps not a list
    lambda k: k.replay(Gaussian, (None, None), None, [], Gaussian(np.zeros(2), np.eye(2)), 0,
                       [1], np.zeros((2, 0)), 1, {1: []}, {}, None),  # outside the buffer
    # stages that are not the kernel's records
    lambda k: _reusing(k, b"\x00" * 7),  # not whole float64 values
    lambda k: _reusing(k, np.array([0.0, 9.0, 0.0, 1.0, 1.0]).tobytes()),  # kind 9
    lambda k: _reusing(k, np.array([0.0, 1.0, 0.0, 1.0, 1.0, 0.0]).tobytes()),  # cut
    lambda k: _reusing(k, np.array([0.0, 1.0, 5.0, 1.0, 1.0, 0.0, 0.0,
                                    0.0]).tobytes()),  # j outside the state
    lambda k: _reusing(k, ((1, np.zeros(2), None, 0.0, 0, 1.0),)),  # stages not bytes
])
def test_bad_arguments_raise(call) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises((ValueError, TypeError, IndexError)):
        call(_KALMAN)


def test_arrays_are_never_written() -> None:
    rng = np.random.default_rng(3)
    b = random_backend(rng, 4, 2)
    P = np.eye(4)
    x = np.ones(4)
    for a in (x, P):
        a.setflags(write=False)
    state = Gaussian(x, P)
    out = b.advance(state, 2, np.ones((2, 2)), [Packet(2, np.ones(b.sensors[2].m), None)], None)
    assert np.array_equal(x, np.ones(4)) and np.array_equal(P, np.eye(4))
    assert out.x is not x and out.P is not P
    # writeable arrays that another state holds: no jump (m = 0: the parent's x and P), or
    # old's covariance reused, are copied before the update, never written in place
    for m in (0, 2):
        x, P = np.ones(4), np.eye(4)
        state = Gaussian(x, P)
        U = np.ones((m, 2))
        first = b.advance(state, m, U, [], None)
        fx, fP = first.x.copy(), first.P.copy()
        pk = [Packet(2, np.ones(b.sensors[2].m), None)]
        joined = b.advance(state, m, U, pk, first)  # old's covariance reused, then updated
        again = b.advance(state, m, U, pk, None)
        assert np.array_equal(x, np.ones(4)) and np.array_equal(P, np.eye(4))
        assert np.array_equal(first.x, fx) and np.array_equal(first.P, fP)
        assert np.array_equal(joined.x, again.x) and np.array_equal(joined.P, again.P)


def test_each_form_reuses_the_others_stages() -> None:
    """One stage format: a state the kernel made is reused by the numpy form and one the
    numpy form made by the kernel (the same covariance object kept, the means re-run), and
    both give what a recompute gives, to rounding. Kinds 1, 2 and 3 are in the records."""
    rng = np.random.default_rng(11)
    b = random_backend(rng, 4, 1)
    state = Gaussian(rng.standard_normal(4), np.eye(4))
    packets = [Packet(i, rng.standard_normal(b.sensors[i].m), None) for i in range(3)]
    U = rng.standard_normal((2, 1))
    got, want = both(b, state, 2, U, packets, None)
    assert [s[1] for s in stages_of(b, got)] == [1, 2, 3]  # a unit row, a row, several rows
    U2 = U + 1.0
    fresh = b.numpy_step(state, 2, U2, packets, None)
    b.use_kernel = False
    by_numpy = b.advance(state, 2, U2, packets, got)  # the kernel's stages, read in numpy
    b.use_kernel = True
    by_kernel = b.advance(state, 2, U2, packets, want)  # the numpy form's, read in C
    for out, old in ((by_numpy, got), (by_kernel, want)):
        assert out.P is old.P and out.stages is old.stages
        assert close(out.x, fresh.x) and close(out.P, fresh.P)


@pytest.mark.parametrize("n, rows", [(_KALMAN.MAX_N + 1 if _KALMAN else 65, 1),
                                     (6, _KALMAN.MAX_R + 1 if _KALMAN else 17)])
def test_sizes_beyond_the_kernel_run_the_numpy_form(n: int, rows: int) -> None:
    """A model or a sensor larger than the kernel's buffers: that backend runs the numpy
    form throughout (an estimator of such a spec works, only slower)."""
    rng = np.random.default_rng(5)
    model = LinearModel(A=np.eye(n) * 0.9, B=np.zeros((n, 0)), Q=np.eye(n) * 0.01)
    b = LinearBackend(model, [Sensor(name="s", H=rng.standard_normal((rows, n)),
                                     R=np.eye(rows))], 4)
    assert not b.use_kernel
    small = LinearBackend(model if n <= 8 else LinearModel(A=np.eye(2), B=np.zeros((2, 0)),
                                                            Q=np.eye(2)),
                          [Sensor(name="s", H=np.ones((1, 6 if n <= 8 else 2)), R=np.eye(1))], 4)
    assert small.use_kernel is (_KALMAN is not None)
    state = Gaussian(np.zeros(n), np.eye(n))
    out = b.advance(state, 2, np.empty((2, 0)), [Packet(0, np.ones(rows), None)], None)
    again = b.advance(state, 2, np.empty((2, 0)), [Packet(0, np.ones(rows), None)], out)
    assert np.array_equal(out.x, again.x) and out.P is again.P


def test_arrays_of_other_layouts_and_types_are_converted() -> None:
    """The kernel takes the backend's float64 C-contiguous arrays as they are and converts
    anything else (a transposed view, integers, a byte-swapped array) first: same result."""
    rng = np.random.default_rng(11)
    n = 4
    b = random_backend(rng, n, 2)
    L = rng.standard_normal((n, n))
    P, x, U = L @ L.T, np.arange(n), rng.standard_normal((2, 2))
    pk = [Packet(2, np.ones(b.sensors[2].m), None)]
    want = b.advance(Gaussian(x.astype(float), P), 2, U, pk, None)
    for args in [(x, P, U), (x.astype(float), np.asfortranarray(P), np.asfortranarray(U)),
                 (x.astype(">f8"), P.astype(">f8"), U.astype(">f8"))]:
        got = b.advance(Gaussian(args[0], args[1]), 2, args[2], pk, None)
        assert np.array_equal(got.x, want.x) and np.array_equal(got.P, want.P)
        assert got.stages == want.stages


def test_fill_sets_rows_as_numpy_does_or_declines() -> None:
    """fill(buf, start, end, u) writes what buf[start:end] = u writes, or returns False and
    writes nothing (the caller then assigns with numpy)."""
    rng = np.random.default_rng(21)
    for _ in range(200):
        rows, nu = int(rng.integers(1, 9)), int(rng.integers(0, 4))
        buf = rng.standard_normal((rows, nu))
        ref = buf.copy()
        start = int(rng.integers(-1, rows + 2))
        end = int(rng.integers(-1, rows + 2))
        u = rng.standard_normal(nu)
        took = _KALMAN.fill(buf, start, end, u)
        if took:
            ref[start:end] = u
        else:
            assert not (0 <= start <= end <= rows)
        assert np.array_equal(buf, ref)
    buf = np.zeros((4, 2))
    for u in (np.ones(3), np.ones((1, 2)), np.ones(2, dtype=np.float32), np.ones(4)[::2],
              [1.0, 1.0]):
        assert _KALMAN.fill(buf, 0, 2, u) is False  # numpy decides (broadcast or convert)
    for b in (np.zeros((4, 2)).T, np.zeros((4, 2), dtype=np.float32), np.zeros(8)):
        assert _KALMAN.fill(b, 0, 1, np.ones(b.shape[-1] if b.ndim == 2 else 1)) is False
    ro = np.zeros((4, 2))
    ro.setflags(write=False)
    assert _KALMAN.fill(ro, 0, 1, np.ones(2)) is False
    assert not ro.any() and not buf.any()


def test_freeze_makes_arrays_read_only_as_setflags_does() -> None:
    a, b = np.zeros(3), np.ones((2, 2))
    view = b[:, 0]
    assert _KALMAN.freeze(a, view) is None
    assert not a.flags.writeable and not view.flags.writeable and b.flags.writeable
    with pytest.raises(ValueError):
        a[0] = 1.0
    _KALMAN.freeze(a)  # already read-only: nothing changes
    assert not a.flags.writeable
    c = np.zeros(2)
    with pytest.raises(TypeError):
        _KALMAN.freeze(c, [1.0])
    assert c.flags.writeable  # nothing changed
    assert _KALMAN.freeze() is None


def test_the_kernels_states_are_left_out_of_the_cycle_collector() -> None:
    """advance's Gaussian, its stages and sensors hold only numbers, arrays and such tuples
    (no cycle is possible): the kernel untracks them, so that a session's window does not
    fill the collector's young generation (docs/service.md, "Performance"). Their
    contents are what the numpy form gives, and they are freed by reference counting."""
    import gc
    import weakref

    rng = np.random.default_rng(7)
    b = random_backend(rng, 4, 1)
    state = Gaussian(rng.standard_normal(4), np.eye(4))
    packets = [Packet(i, rng.standard_normal(b.sensors[i].m), None) for i in range(3)]
    got, want = both(b, state, 2, rng.standard_normal((2, 1)), packets, None)
    assert_same(got, want, b)
    assert not gc.is_tracked(got) and not gc.is_tracked(got.stages)
    assert not gc.is_tracked(got.sensors) and len(stages_of(b, got)) == 3
    assert isinstance(got.stages, bytes)  # packed: one object, not tracked (no references)
    assert gc.is_tracked(want)  # the numpy form's are tracked, as any tuple subclass
    # a packet that joins later: the carried and the new stages, untracked as well
    joined, want2 = both(b, state, 2, np.zeros((2, 1)), packets + packets[:1], got)
    assert_same(joined, want2, b)
    assert not gc.is_tracked(joined.stages) and isinstance(joined.stages, bytes)
    ref = weakref.ref(got.x)
    del got, joined
    assert ref() is None  # freed by reference counting, with no collection


def test_a_snapshot_is_left_out_of_the_cycle_collector() -> None:
    """A session's snapshot (an EstimatorState kept for a second) and the tuples, lists and
    dicts it holds are untracked by the kernel's untrack (docs/service.md, "Performance"):
    1,000 sessions' snapshots were most of the collector's young generation. Nothing is
    copied or changed, and it is freed by reference counting."""
    import gc
    import weakref

    from pd_service.backends import build
    from pd_service.estimation.estimator_state import untracked
    from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario, simulate_paper

    sc = paper_scenario()
    est = build(sc.spec("s", 0, max_delay=RANGER_DELAY)).est
    run = simulate_paper(40, np.random.default_rng(3))
    for k in range(30):  # a window with commands and packets in it
        est.add_command(k, sc.command(k), now=k)
        for smp in run.samples:
            if smp.arrival == k:
                est.add_measurement(smp.sensor, smp.step, smp.z, now=k)
        est.predict(k)
    state = est.export_state()
    assert gc.is_tracked(state)
    parts = [state, state.base, state.packets, state.commands, state.counters,
             *state.packets, *state.commands]
    same = untracked(state)
    assert same is state
    assert not any(gc.is_tracked(p) for p in parts)
    # a container that holds something tracked stays tracked (and so does what holds it)
    class Holder:  # an instance: tracked, it could close a cycle
        pass

    live = [Holder()]
    outer = untracked((1, live, (2.0, "x")))
    assert gc.is_tracked(outer) and gc.is_tracked(live) and not gc.is_tracked(outer[2])
    ref = weakref.ref(state.u_origin)
    del state, same, parts
    assert ref() is None
