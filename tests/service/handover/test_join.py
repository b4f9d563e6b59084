"""A join hands sessions over: the sessions that move to a joining instance resume from their
previous owner's state (sent when it sees the joiner, :meth:`HandoverKeeper.hand_to`), not
from the prior, and continue exactly as the estimator that never stopped; what was sent
during the hand-over comes back from the senders' caches; a state that never comes leaves
the session at its prior after ``recover_timeout_s``, said in its status."""

from __future__ import annotations

from pd_service.backends import build
from pd_service.service.handover.keeper import replica_key
from pd_service.service.ownership import Ownership
from pd_service.transport import InMemoryBus
from pd_service.wire import keys

from ..helpers import Clock, Collector
from ..test_core import make_core, settle
from .test_keeper import CachedSender, Driver, status, two_instances

TRIO = ["inst-a", "inst-b", "inst-c"]


class LosesHandovers:
    """A transport that loses every put and delete to inst-c's replica keys."""

    def __init__(self, t):
        self._t = t

    def __getattr__(self, name):
        return getattr(self._t, name)

    def put(self, key, payload):
        if not key.startswith(replica_key("inst-c", "x")[:-1]):
            self._t.put(key, payload)

    def delete(self, key):
        if not key.startswith(replica_key("inst-c", "x")[:-1]):
            self._t.delete(key)


def pair_with_sessions(bus, clock, tmp_path, cli, n=40, **kw):
    """inst-a and inst-b (inst-c trusted too) serving n paper sessions; returns them and
    the name of a session that moves to inst-c when it joins, and its owner before."""
    a, b, names = two_instances(bus, clock, tmp_path, cli, sessions=n, peers=TRIO, **kw)
    three = Ownership("inst-c")
    three.join("inst-a")
    three.join("inst-b")
    moving = [s for s in names if three.owns(s)]
    assert moving
    s = moving[0]
    old = a if s in a.served_sessions() else b
    return a, b, names, moving, s, old


def test_a_join_hands_the_moved_sessions_over_exactly(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    # no sender cache to wait for (the read-back: test_keeper)
    a, b, names, moving, s, old = pair_with_sessions(bus, clock, tmp_path, cli,
                                                     recover_samples=0)
    before = {n: "inst-a" if n in a.served_sessions() else "inst-b" for n in names}
    d = Driver(cli, clock, col, s)
    for k in range(30):
        d.step([a, b], k)
    sent0 = a.counters["replicas_handover_join"] + b.counters["replicas_handover_join"]
    c = make_core(bus, clock, tmp_path, "inst-c", peers=TRIO, recover_samples=0)
    assert s in c.lifecycle.awaiting and s not in c.served_sessions()  # not from the prior
    settle(a, b, c)  # a and b see c: they hand the moved sessions over, c resumes them
    assert not c.lifecycle.awaiting
    assert sorted(c.served_sessions()) == sorted(moving)
    assert s not in old.served_sessions()
    for k in range(30, 50):
        d.step([a, b, c], k)
        d.check(k, d.off)  # as if it never moved
    st = status(cli, s)
    assert st.instance == "inst-c" and st.origin == "replica" and st.origin_step is not None
    assert "handed over by " + old.instance in st.detail
    # the others, at their prior alone, were handed over as such (no state, no refusal)
    assert c.counters["resumed_from_replica"] == 1 and "restore_refused" not in c.counters
    # every session that changed owner was handed over (bounded load may move a partition
    # between the two old members too), each served once
    moved = [n for n in names if c.ownership.owner(n) != before[n]]
    sent = a.counters["replicas_handover_join"] + b.counters["replicas_handover_join"] - sent0
    assert sent == len(moved) >= len(moving) and "handover_timeout" not in c.counters
    served = a.served_sessions() + b.served_sessions() + c.served_sessions()
    assert sorted(served) == sorted(names)
    assert not (a.lifecycle.awaiting or b.lifecycle.awaiting)
    # the estimate continued: far from a fresh start's covariance
    fresh = build(d.spec).est
    assert float(col.predictions[s][-1].P[1, 1]) < 0.1 * float(fresh.predict(49).P[1, 1])


def test_what_was_sent_during_the_hand_over_is_read_back(tmp_path):
    """Inputs of the step at which the old owner sees the joiner reach the old owner (it
    drops them: no longer its session) and not the joiner (still waiting): the joiner reads
    them back from the senders' caches after resuming, and continues exactly."""
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a, b, _, _, s, old = pair_with_sessions(bus, clock, tmp_path, cli)
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    for k in range(30):
        d.step([a, b], k)
    c = make_core(bus, clock, tmp_path, "inst-c", peers=TRIO)
    for k in range(30, 50):
        d.step([a, b, c], k)  # the first one: the hand-over with inputs on their way
        settle(a, b, c)
        d.check(k, d.off)
    st = status(cli, s)
    assert st.instance == "inst-c" and st.origin == "replica"
    assert c.counters["recovered_accepted"] > 0 and c.counters["refused"] == 0


def test_a_state_that_never_comes_leaves_the_session_at_its_prior_after_the_wait(tmp_path):
    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a, b, _, moving, s, old = pair_with_sessions(bus, clock, tmp_path, cli)
    d = Driver(cli, clock, col, s)
    for k in range(10):
        d.step([a, b], k)
    old.outbox.t = LosesHandovers(old.outbox.t)  # the states are lost on the way
    c = make_core(bus, clock, tmp_path, "inst-c", peers=TRIO, recover_timeout_s=0.5)
    settle(a, b, c)
    assert s in c.lifecycle.awaiting and s not in c.served_sessions()
    wait_end = c.lifecycle.next_await_ns()
    assert wait_end is not None and c.next_deadline_ns() <= wait_end
    clock.t = wait_end
    c.run_once()
    assert s in c.served_sessions() and c.counters["handover_timeout"] >= 1
    st = status(cli, s)
    assert st.origin == "prior" and "no state handed over by " + old.instance in st.detail
    d.step([a, b, c], 11)
    prior = build(d.spec).est
    assert float(col.predictions[s][-1].P[1, 1]) > 0.1 * float(prior.predict(11).P[1, 1])


def test_a_previous_owner_that_goes_away_during_the_wait_ends_it(tmp_path):
    """The state does not come and its sender dies: the session is taken over at once (as
    at any takeover), not after the rest of the wait."""
    bus, clock = InMemoryBus(), Clock(0)
    cli = bus.transport()
    a, b, _, _, s, old = pair_with_sessions(bus, clock, tmp_path, cli)
    old.outbox.t = LosesHandovers(old.outbox.t)  # the states are lost on the way
    c = make_core(bus, clock, tmp_path, "inst-c", peers=TRIO, recover_timeout_s=60.0)
    settle(a, b, c)
    assert s in c.lifecycle.awaiting
    old.t.close()  # it dies
    c.dispatch.on_liveliness(keys.service_token_key(old.instance), False)
    c.run_once()
    assert s not in c.lifecycle.awaiting and s in c.served_sessions()
    assert "taken over" in status(cli, s).detail


def partition(a, b, apart: bool) -> None:
    """Two instances stop (``apart``) or start again hearing each other's liveliness: a
    partition between them, or its heal (each side sees the other leave, then join)."""
    a.dispatch.on_liveliness(keys.service_token_key(b.instance), not apart)
    b.dispatch.on_liveliness(keys.service_token_key(a.instance), not apart)


def test_a_partition_fences_the_older_owner_and_the_heal_keeps_the_newer_estimate(tmp_path):
    """inst-a serves s, inst-b is its successor. The link between them goes down: b takes s
    over from its replica with a newer term while a goes on serving it; both publish, a
    Display shows b's predictions only (a's counted as of an older term). At the heal b hands
    s back: a yields to b's newer state (a term newer still), and the estimate goes on
    exactly as the one that never stopped (the inputs reached both sides). A session b held at
    its prior alone is handed back as a delete: a keeps its estimate under a renewed term."""
    from pd_client import Display

    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli, replica_interval_s=0.3)
    s = next(n for n in names if n in a.served_sessions() and a.ownership.successor(n) == b.instance)
    idle = next(n for n in names if n in a.served_sessions() and n != s)
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    disp = Display(bus.transport(), s)
    for k in range(30):
        d.step([a, b], k)
    t0 = status(cli, s).term
    assert t0 > 0 and all(p.term == t0 for p in col.predictions[s])
    assert s in b.keeper.replicas
    partition(a, b, apart=True)
    for k in range(30, 45):
        d.step([a, b], k)
        settle(a, b)
        d.check(k, d.off)  # either owner's: b read back what came after its replica
    assert s in a.served_sessions() and s in b.served_sessions()  # two owners
    during = [p.term for p in col.predictions[s][-20:]]
    t1 = max(during)
    assert t1 > t0 and sorted(set(during)) == [t0, t1]  # interleaved on the key ...
    assert disp.stats().stale_term > 0 and disp.stats().term == t1  # ... not on the display
    assert disp.latest().term == t1
    partition(a, b, apart=False)
    settle(a, b)
    for k in range(45, 60):
        d.step([a, b], k)
        settle(a, b)
        d.check(k, d.off)  # continuous and exact: nothing regressed
    assert s in a.served_sessions() and s not in b.served_sessions()
    st = status(cli, s)
    # both sides took in the same inputs: either estimate is the right one, a newer term
    assert st.instance == a.instance and st.term > t1
    assert "yielded to inst-b" in st.detail or "kept its estimate" in st.detail
    assert a.counters["term_yielded"] + a.counters["term_kept"] >= 1
    after = [p.term for p in col.predictions[s][-10:]]
    assert after == [st.term] * 10 and disp.stats().term == st.term
    # the idle session: b took it from the prior, a kept it; after the heal a's term is newest
    assert idle in a.served_sessions() and idle not in b.served_sessions()
    assert a.counters["term_kept"] >= 2 and status(cli, idle).term > t1
    disp.close()


class DataCut:
    """A transport whose instance receives no session data (sensors, commands, read-backs)
    while ``cut``: the robots reach only the other side of a partition."""

    def __init__(self, t):
        self._t = t
        self.cut = False

    def __getattr__(self, name):
        return getattr(self._t, name)

    def _data(self, callback):
        def on(sample):
            if not (self.cut and ("/sensor/" in sample.key or sample.key.endswith("/cmd"))):
                callback(sample)
        return on

    def drain_group(self, wake):
        group, data = self._t.drain_group(wake), self._data

        class Cut:  # the group, its members' callbacks behind the cut
            def __getattr__(self, name):
                return getattr(group, name)

            def add(self, keyexpr, callback):
                return group.add(keyexpr, data(callback))
        return Cut()

    def read_back(self, keyexpr, callback, **kw):
        return self._t.read_back(keyexpr, self._data(callback), **kw)


def robot_on_a_side(tmp_path, spawn_a=None):
    """inst-a (background work run by ``spawn_a``, at once by default) and inst-b, whose
    transport is a :class:`DataCut`, serving 12 paper sessions; s, a session inst-a owns
    with inst-b as its successor, fed 30 steps through cached senders. Returns (a, b, tb, s,
    the Driver, the collector, the client transport)."""
    from pd_service.service.config import Settings
    from pd_service.service.core import ServiceCore
    from pd_service.service.spec_store import SpecStore
    from pd_service.wire import encode

    from ..helpers import paper_spec
    from ..test_core import PAIR

    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    cores = []
    for name, t, spawn in (("inst-a", bus.transport(), spawn_a or (lambda fn: fn())),
                           ("inst-b", DataCut(bus.transport()), lambda fn: fn())):
        core = ServiceCore(t, Settings(instance=name, peers=PAIR, replica_interval_s=0.3),
                           store=SpecStore(tmp_path / name), now_ns=clock,
                           run_clock_ns=lambda: 0, spawn=spawn)
        core.start()
        cores.append(core)
    a, b = cores
    names = [f"s{i:02d}" for i in range(12)]
    for n in names:
        cli.put(keys.config_key(n), encode(paper_spec(n)))
    settle(a, b)
    s = next(n for n in names if n in a.served_sessions() and a.ownership.successor(n) == b.instance)
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    for k in range(30):
        d.step([a, b], k)
    return a, b, b.t, s, d, col, cli


def test_at_the_heal_the_estimate_that_took_in_the_data_is_kept(tmp_path):
    """The robot reaches only inst-a (the owner) during the partition: inst-b's takeover
    predicts from its replica alone, with a newer term. At the heal b hands its state back;
    a keeps its own estimate (more inputs accepted), renews its term above b's, and its
    predictions never left the estimate that never stopped."""
    a, b, tb, s, d, col, cli = robot_on_a_side(tmp_path)
    tb.cut = True
    partition(a, b, apart=True)
    for k in range(30, 60):  # 1.5 s: longer than the window (max_delay 16 steps)
        d.step([a, b], k)
        settle(a, b)
    b_terms = {p.term for p in col.predictions[s][-30:]} - {status(cli, s).term}
    assert s in b.served_sessions() and b_terms  # b published too, its own term
    tb.cut = False
    partition(a, b, apart=False)
    settle(a, b)
    assert s in a.served_sessions() and s not in b.served_sessions()
    assert a.counters["term_kept"] >= 1 and "term_yielded" not in a.counters
    st = status(cli, s)
    assert st.term > max(b_terms) and "kept its estimate" in st.detail
    for k in range(60, 70):
        d.step([a, b], k)
        settle(a, b)
        d.check(k, d.off)  # a's estimate: as if nothing happened
    assert all(p.term == st.term for p in col.predictions[s][-10:])


def test_an_asymmetric_partition_settles_once_and_the_display_stays_with_one_owner(tmp_path):
    """inst-b stops hearing inst-a while inst-a still hears inst-b (an asymmetric
    partition): b, alone in its view, takes s over (and sends no replicas: nobody to send
    them to); a goes on serving s and sending its replicas to b. b settles a's first state
    it gets (a term newer than both) and no later one of the same term: over 10 replica
    intervals the two owners do not take turns, and a Display switches owner once."""
    from pd_client import Display

    bus, clock = InMemoryBus(), Clock(0)
    col, cli = Collector().attach(bus.transport()), bus.transport()
    a, b, names = two_instances(bus, clock, tmp_path, cli, replica_interval_s=0.3)
    s = next(n for n in names if n in a.served_sessions() and a.ownership.successor(n) == b.instance)
    d = Driver(CachedSender(bus.transport(), 64), clock, col, s)
    disp = Display(bus.transport(), s)
    shown: list[int] = []
    disp.on_prediction(lambda p: shown.append(p.term))
    for k in range(30):
        d.step([a, b], k)
    b.dispatch.on_liveliness(keys.service_token_key(a.instance), False)  # b only
    settled = []
    for k in range(30, 90):  # 3 s: 10 of a's replica intervals
        d.step([a, b], k)
        settle(a, b)
        settled.append(b.counters["term_yielded"] + b.counters["term_kept"])
    assert s in a.served_sessions() and s in b.served_sessions()  # two owners all along
    assert settled[-1] <= 1 and a.counters["replicas_sent"] > 0
    switches = sum(1 for x, y in zip(shown, shown[1:], strict=False) if y != x)
    assert switches <= 2, shown  # to b's takeover, then (at most) to b's settled term
    assert all(p.term == shown[-1] for p in col.predictions[s][-20:] if p.term >= shown[-1])
    disp.close()


def test_a_session_kept_at_the_heal_takes_in_its_live_inputs_while_its_caches_are_read(tmp_path):
    """As above, inst-a keeps its estimate at the heal and reads the senders' caches back;
    that read-back runs on a thread and can take a while (here it waits until released).
    Meanwhile a goes on taking in the live inputs and publishing: its predictions stay those
    of the estimator that never stopped, and once the read-back ends nothing was lost. (A
    session parked for its read-back would have ticked without them, its window moving past
    the inputs waiting in its inbox: refused as late when released.)"""
    later: list = []  # inst-a's background work, run when the test says
    a, b, tb, s, d, col, cli = robot_on_a_side(tmp_path, later.append)
    tb.cut = True
    partition(a, b, apart=True)
    for k in range(30, 45):
        d.step([a, b], k)
        settle(a, b)
    tb.cut = False
    later.clear()
    partition(a, b, apart=False)
    settle(a, b)
    assert a.counters["term_kept"] >= 1 and later  # the read-back waits
    for k in range(45, 60):  # 0.75 s: longer than the ranger's room in the window
        d.step([a, b], k)
        settle(a, b)
        d.check(k, d.off)
    for fn in later:
        fn()
    for k in range(60, 65):
        d.step([a, b], k)
        settle(a, b)
        d.check(k, d.off)
    assert s in a.served_sessions() and s not in b.served_sessions()
    assert a.counters["late"] == 0
