"""Duplicate, reorder, corrupt, rate limit, outage, ordering and seeding of LinkModel."""

from __future__ import annotations

import random

import numpy as np
import pytest

from pd_service.link.model import (
    DelaySpec,
    LinkModel,
    LinkParams,
    Outage,
    RandomLoss,
    Rate,
    reorder_theory,
)

MS = 1_000_000
S = 1_000_000_000


def run(params: LinkParams, n: int, spacing_ns: int = MS, seed: int = 2, payload=b"payload"):
    model = LinkModel(params, seed=seed)
    return [model.process(i * spacing_ns, payload) for i in range(n)]


# --- duplicate ---------------------------------------------------------------------------


def test_duplicate_rate():
    n = 100_000
    ds = run(LinkParams(duplicate=0.05), n)
    two = np.mean([len(d.releases) == 2 for d in ds])
    assert two == pytest.approx(0.05, abs=4 * np.sqrt(0.05 * 0.95 / n))
    assert all(len(d.releases) >= 1 for d in ds)
    flagged = [d.releases for d in ds if len(d.releases) == 2]
    assert all(sum(r.duplicate for r in rels) == 1 for rels in flagged)


def test_duplicate_copy_meets_the_loss_model_again():
    # netem re-enqueues the clone: P(2 copies) = dup (1 - loss)^2, P(0) = (1 - dup) loss
    n = 100_000
    ds = run(LinkParams(duplicate=0.05, loss=RandomLoss(0.1)), n)
    counts = np.array([len(d.releases) for d in ds])
    assert np.mean(counts == 2) == pytest.approx(0.05 * 0.81, abs=0.003)
    assert np.mean(counts == 0) == pytest.approx(0.95 * 0.1, abs=0.004)
    assert all(d.dropped == "loss" for d in ds if not d.releases)


def test_duplicate_correlation_keeps_rate_and_clusters():
    n = 100_000
    ds = run(LinkParams(duplicate=0.1, duplicate_correlation=0.7), n)
    dup = np.array([len(d.releases) == 2 for d in ds], dtype=float)
    assert dup.mean() == pytest.approx(0.1, rel=0.1)
    assert np.corrcoef(dup[:-1], dup[1:])[0, 1] == pytest.approx(0.7, abs=0.03)


# --- reorder -----------------------------------------------------------------------------


@pytest.mark.parametrize("reorder,gap", [(0.25, 1), (0.25, 5), (1.0, 5), (0.5, 3)])
def test_reorder_rate_matches_netem_gap_semantics(reorder, gap):
    n = 60_000
    ds = run(LinkParams(delay=DelaySpec(10 * MS), reorder=reorder, gap=gap), n)
    frac = np.mean([d.releases[0].reordered for d in ds])
    expected = reorder_theory(reorder, gap)
    assert frac == pytest.approx(expected, abs=4 * np.sqrt(expected / n) + 1e-3)


def test_reorder_100_gap_5_reorders_every_5th():
    ds = run(LinkParams(delay=DelaySpec(10 * MS), reorder=1.0, gap=5), 20)
    flags = [d.releases[0].reordered for d in ds]
    assert [i for i, f in enumerate(flags) if f] == [4, 9, 14, 19]


def test_reordered_messages_are_sent_immediately_and_overtake():
    ds = run(LinkParams(delay=DelaySpec(10 * MS), reorder=0.3), 2000)
    times = [d.releases[0].time_ns for d in ds]
    for i, d in enumerate(ds):
        r = d.releases[0]
        assert r.time_ns == (i * MS if r.reordered else i * MS + 10 * MS)
    # some message is released before one that arrived earlier
    assert any(times[i + 1] < times[i] for i in range(len(times) - 1))


# --- corrupt -----------------------------------------------------------------------------


def hamming(a: bytes, b: bytes) -> int:
    return sum(bin(x ^ y).count("1") for x, y in zip(a, b, strict=True))


def test_corrupt_flips_exactly_one_bit_at_the_configured_rate():
    payload = bytes(random.Random(0).randbytes(32))
    n = 50_000
    ds = run(LinkParams(corrupt=0.1), n, payload=payload)
    rels = [d.releases[0] for d in ds]
    corrupted = [r for r in rels if r.corrupted]
    assert len(corrupted) / n == pytest.approx(0.1, abs=0.006)
    assert all(hamming(r.payload, payload) == 1 for r in corrupted)
    assert all(r.payload == payload for r in rels if not r.corrupted)
    positions = {next(i for i, (x, y) in enumerate(zip(r.payload, payload, strict=True)) if x != y)
                 for r in corrupted}  # fmt: skip
    assert positions == set(range(32))  # every byte gets hit


def test_corrupt_bits_flips_several():
    payload = bytes(64)
    ds = run(LinkParams(corrupt=1.0, corrupt_bits=3), 500, payload=payload)
    dists = [hamming(d.releases[0].payload, payload) for d in ds]
    assert set(dists) <= {1, 3} and dists.count(3) > 400


def test_empty_payload_is_never_corrupted():
    (d,) = run(LinkParams(corrupt=1.0), 1, payload=b"")
    assert d.releases[0].payload == b"" and not d.releases[0].corrupted


# --- rate --------------------------------------------------------------------------------


def test_message_rate_spaces_back_to_back_messages():
    # 100 msg/s: each message occupies the link 10 ms; arrivals every 1 ms queue up
    ds = run(LinkParams(delay=DelaySpec(5 * MS), rate=Rate(msgs_per_s=100)), 50)
    times = np.array([d.releases[0].time_ns for d in ds])
    assert times[0] == 5 * MS + 10 * MS
    assert np.all(np.diff(times) == 10 * MS)


def test_byte_rate_uses_size_and_overhead():
    rate = Rate(bytes_per_s=1000.0, overhead_bytes=20)  # 100 + 20 bytes -> 120 ms
    ds = run(LinkParams(rate=rate), 5, spacing_ns=S, payload=bytes(100))
    assert [d.releases[0].time_ns - i * S for i, d in enumerate(ds)] == [120 * MS] * 5
    ds = run(LinkParams(rate=rate), 5, spacing_ns=MS, payload=bytes(100))
    assert np.all(np.diff([d.releases[0].time_ns for d in ds]) == 120 * MS)


def test_rate_limited_link_never_exceeds_the_rate():
    params = LinkParams(delay=DelaySpec(20 * MS, 15 * MS, distribution="normal"),
                        rate=Rate(msgs_per_s=500))  # fmt: skip
    ds = run(params, 5000, spacing_ns=MS // 2)
    times = np.array([d.releases[0].time_ns for d in ds])
    assert np.all(np.diff(times) >= 2 * MS)  # and rate keeps FIFO order (netem)


# --- outage ------------------------------------------------------------------------------


def test_outage_drop():
    params = LinkParams(delay=DelaySpec(50 * MS), outages=(Outage(1 * S, S // 2),))
    ds = run(params, 3000)  # one per ms for 3 s
    dropped = [i for i, d in enumerate(ds) if d.dropped == "outage"]
    assert dropped == list(range(1000, 1500))
    assert all(d.releases[0].time_ns == i * MS + 50 * MS
               for i, d in enumerate(ds) if not d.dropped)  # fmt: skip


def test_outage_stall_releases_a_burst_when_the_link_returns():
    params = LinkParams(delay=DelaySpec(50 * MS), outages=(Outage(1 * S, S // 2),),
                        outage_mode="stall")  # fmt: skip
    ds = run(params, 3000)
    held = [d for d in ds[1000:1500]]
    assert all(d.stalled and d.dropped is None for d in held)
    assert {d.releases[0].time_ns for d in held} == {1500 * MS + 50 * MS}
    assert not any(d.stalled for d in ds[:1000] + ds[1500:])
    assert ds[1500].releases[0].time_ns == 1500 * MS + 50 * MS


def test_stall_burst_behind_a_rate_limit_drains_at_the_rate():
    params = LinkParams(outages=(Outage(0, 100 * MS),), outage_mode="stall",
                        rate=Rate(msgs_per_s=1000))  # fmt: skip
    ds = run(params, 100)
    times = np.array([d.releases[0].time_ns for d in ds])
    assert times[0] == 100 * MS + MS and np.all(np.diff(times) == MS)


def test_periodic_outage_and_epoch():
    params = LinkParams(outages=(Outage(200 * MS, 100 * MS, every_ns=S),))
    model = LinkModel(params, seed=0, epoch_ns=10 * S)
    down = [t for t in range(10_000, 13_000, 10)
            if model.process(t * MS, b"x").dropped == "outage"]  # fmt: skip
    windows = sorted({(t - 10_000) // 1000 for t in down})
    assert windows == [0, 1, 2]
    assert all(200 <= (t - 10_000) % 1000 < 300 for t in down)
    assert len(down) == 30


@pytest.mark.parametrize("kwargs", [
    {"start_ns": -1, "duration_ns": 5},
    {"start_ns": 0, "duration_ns": 0},
    {"start_ns": 0, "duration_ns": 10, "every_ns": 10},
])  # fmt: skip
def test_bad_outage_raises(kwargs):
    with pytest.raises(ValueError):
        Outage(**kwargs)


# --- ordering, seeding, validation ---------------------------------------------------------


def test_in_order_never_reorders_jittered_messages():
    delay = DelaySpec(50 * MS, 20 * MS, distribution="normal")
    plain = [d.releases[0].time_ns for d in run(LinkParams(delay=delay), 3000)]
    fifo = [d.releases[0].time_ns for d in run(LinkParams(delay=delay, in_order=True), 3000)]
    assert any(b < a for a, b in zip(plain[:-1], plain[1:], strict=True))  # jitter reorders (as netem)
    assert all(b >= a for a, b in zip(fifo[:-1], fifo[1:], strict=True))
    assert all(f >= p for f, p in zip(fifo, plain, strict=True))


def test_same_seed_repeats_exactly():
    params = LinkParams(delay=DelaySpec(50 * MS, 10 * MS, 0.3, "pareto"), loss=RandomLoss(0.2),
                        duplicate=0.05, reorder=0.1, corrupt=0.05)  # fmt: skip
    a, b = run(params, 5000, seed=9), run(params, 5000, seed=9)
    assert a == b
    assert run(params, 5000, seed=10) != a


def test_components_have_independent_random_streams():
    # turning on corruption and jitter does not change which messages are lost
    base = run(LinkParams(delay=DelaySpec(10 * MS), loss=RandomLoss(0.2)), 5000)
    more = run(LinkParams(delay=DelaySpec(10 * MS, 5 * MS), loss=RandomLoss(0.2), corrupt=0.3,
                          reorder=0.2), 5000)  # fmt: skip
    assert [d.dropped for d in base] == [d.dropped for d in more]


def test_reorder_needs_delay():
    with pytest.raises(ValueError, match="delay"):
        LinkParams(reorder=0.1)


@pytest.mark.parametrize("kwargs", [
    {"duplicate": 1.2}, {"corrupt": -0.01}, {"gap": 0}, {"corrupt_bits": 0},
    {"outage_mode": "pause"}, {"loss": 0.1}, {"reorder_correlation": 1.0},
])  # fmt: skip
def test_bad_params_raise(kwargs):
    with pytest.raises(ValueError):
        LinkParams(delay=DelaySpec(MS), **kwargs)


@pytest.mark.parametrize("kwargs", [
    {}, {"bytes_per_s": 1.0, "msgs_per_s": 1.0}, {"msgs_per_s": 0}, {"bytes_per_s": float("inf")},
])  # fmt: skip
def test_bad_rate_raises(kwargs):
    with pytest.raises(ValueError):
        Rate(**kwargs)
