"""TermFence: a reader shows the newest ownership term's predictions only."""

from __future__ import annotations

from pd_service.wire import fence
from pd_service.wire.fence import TermFence


def test_an_older_term_is_dropped_and_counted_the_newest_kept():
    f = TermFence()
    # two owners interleaved on one key: 5 (the older) and 9 (the taker)
    shown = [t for t in (5, 5, 9, 5, 9, 5, 9) if f.admit("s", t)]
    assert shown == [5, 5, 9, 9, 9]
    assert f.dropped == 2 and f.changes == 1 and f.newest == {"s": 9}
    # a later hand-over's newer term takes over; the taker's older one is dropped from then on
    assert f.admit("s", 12) and not f.admit("s", 9)
    assert f.dropped == 3 and f.changes == 2


def test_sessions_are_fenced_apart_and_their_number_is_bounded(monkeypatch):
    monkeypatch.setattr(fence, "MAX_FENCED_SESSIONS", 3)
    f = TermFence()
    assert f.admit("a", 7) and f.admit("b", 1) and not f.admit("a", 6) and f.admit("b", 1)
    for s in ("c", "d"):
        assert f.admit(s, 1)
    assert len(f.newest) == 3 and "a" not in f.newest  # the oldest seen forgotten first
    assert f.admit("a", 6)  # forgotten: whatever comes next is the newest known
