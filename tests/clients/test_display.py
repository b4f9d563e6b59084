"""Display: predictions by iterator / callback / latest(), truth pairing, counters.

The daemon side is faked by publishing Prediction messages directly on the bus.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from pd_client import Display, Prediction, Timeout, Truth
from pd_service.wire import ErrorReport, encode, keys


def _pred(seq, step, x=None, session="s1", made_ns=None, term=0):
    x = np.full(4, float(step)) if x is None else np.asarray(x, dtype=float)
    return Prediction(session=session, seq=seq, step=step, t_ns=step * 1000, x=x,
                      P=np.diag([0.25, 0.01, 0.25, 0.01]), newest_step=max(0, step - 12),
                      made_ns=time.time_ns() if made_ns is None else made_ns,
                      counters={"accepted": seq}, term=term)


def _truth(step, x, session="s1"):
    return Truth(session=session, step=step, t_ns=step * 1000, x=np.asarray(x, dtype=float),
                 names=["p1", "v1", "p2", "v2"])


def test_latest_iterator_and_callback(bus):
    daemon = bus.transport()
    seen = []
    with Display(bus.transport(), "s1") as d:
        d.on_prediction(seen.append)
        assert d.latest() is None
        for seq in range(3):
            daemon.put(keys.prediction_key("s1"), encode(_pred(seq, 10 + seq)))
        daemon.put(keys.prediction_key("s2"), encode(_pred(0, 99, session="s2")))  # other
        assert d.latest().step == 12 and d.latest().counters == {"accepted": 2}
        assert [p.seq for p in seen] == [0, 1, 2]
        assert [p.step for p in d.predictions(timeout=0.01)] == [10, 11, 12]
        assert d.prediction_for(11).seq == 1 and d.prediction_for(50) is None
        st = d.stats()
        assert (st.received, st.missed, st.invalid) == (3, 0, 0)
        assert st.latency_us_last is not None and st.latency_us_last >= 0


def test_gaps_invalid_payloads_and_errors_are_counted(bus):
    daemon = bus.transport()
    with Display(bus.transport(), "s1") as d:
        daemon.put(keys.prediction_key("s1"), encode(_pred(0, 10)))
        daemon.put(keys.prediction_key("s1"), encode(_pred(4, 14)))  # 1..3 lost
        daemon.put(keys.prediction_key("s1"), b"\x81\xa1v\x02")  # not a Prediction
        daemon.put(keys.error_key("s1"), encode(ErrorReport(
            session="s1", key="pd/p9/s1/sensor/camera", seq=3, reason="late", t_ns=1)))
        st = d.stats()
        assert (st.received, st.missed, st.invalid, st.errors) == (2, 3, 1, 1)
        assert st.last_error == "pd/p9/s1/sensor/camera: late"


def test_two_owners_interleaved_show_as_the_newest_term_only(bus):
    """A partition between instances: the old owner (term 5) and the taker (term 9) publish
    on the same key. The Display shows the taker's predictions only, counts the others, and
    starts its seq and latest() over with the new owner (its seq goes on from its state)."""
    daemon = bus.transport()
    seen = []
    with Display(bus.transport(), "s1") as d:
        d.on_prediction(seen.append)
        for seq, step, term in ((0, 10, 5), (1, 11, 5), (40, 9, 9), (2, 12, 5), (41, 10, 9),
                                (3, 13, 5), (42, 11, 9)):
            daemon.put(keys.prediction_key("s1"), encode(_pred(seq, step, term=term)))
        assert [(p.seq, p.term) for p in seen] == [(0, 5), (1, 5), (40, 9), (41, 9), (42, 9)]
        assert d.latest().term == 9 and d.latest().step == 11  # not the old owner's step 13
        st = d.stats()
        assert (st.received, st.missed, st.stale_term, st.term) == (5, 0, 2, 9)


def test_latency_is_receipt_minus_made(bus):
    daemon = bus.transport()
    with Display(bus.transport(), "s1") as d:
        made = time.time_ns() - 5_000_000  # made 5 ms ago
        daemon.put(keys.prediction_key("s1"), encode(_pred(0, 10, made_ns=made)))
        assert d.stats().latency_us_last >= 5_000


def test_truth_pairs_by_target_step(bus):
    daemon, sim = bus.transport(), bus.transport()
    with Display(bus.transport(), "s1", truth=True) as d:
        daemon.put(keys.prediction_key("s1"), encode(_pred(0, 10, x=[1, 0, 5, 0])))
        daemon.put(keys.prediction_key("s1"), encode(_pred(1, 11, x=[2, 0, 5, 0])))
        assert d.latest_pair() is None
        sim.put(keys.truth_key("s1"), encode(_truth(10, [1.5, 0, 5, 0])))
        p, t = d.latest_pair()
        assert (p.step, t.step) == (10, 10) and p.x[0] - t.x[0] == -0.5
        # truth first, then the prediction for that step (lead 0)
        sim.put(keys.truth_key("s1"), encode(_truth(12, [3, 0, 5, 0])))
        daemon.put(keys.prediction_key("s1"), encode(_pred(2, 12, x=[3, 0, 5, 0])))
        assert d.latest_pair()[0].step == 12
        assert d.latest_truth().step == 12 and d.truth_at(10).x[0] == 1.5
        assert d.wait_pair(min_step=12, timeout=0)[1].step == 12
        assert d.stats().truth_received == 2


def test_wait_blocks_until_enough_predictions(bus):
    daemon = bus.transport()
    with Display(bus.transport(), "s1") as d:
        with pytest.raises(Timeout):
            d.wait(1, timeout=0.01)
        th = threading.Thread(target=lambda: [
            daemon.put(keys.prediction_key("s1"), encode(_pred(i, 10 + i))) for i in range(3)])
        th.start()
        assert d.wait(3, timeout=5).seq == 2
        th.join()
        with pytest.raises(Timeout):
            d.wait_pair(timeout=0.01)


def test_closing_ends_iteration_and_unsubscribes(bus):
    daemon = bus.transport()
    d = Display(bus.transport(), "s1")
    out = []
    th = threading.Thread(target=lambda: out.extend(d))
    th.start()
    daemon.put(keys.prediction_key("s1"), encode(_pred(0, 10)))
    d.wait(1, timeout=5)
    d.close()
    th.join(5)
    assert not th.is_alive() and [p.seq for p in out] == [0]
    daemon.put(keys.prediction_key("s1"), encode(_pred(1, 11)))
    assert d.stats().received == 1
