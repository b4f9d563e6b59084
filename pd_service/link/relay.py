"""The relay of pd-link on a :class:`~pd_service.transport.base.Transport` (Zenoh, or the
in-memory bus in tests): subscribe, apply the model, release from a heap on time.

Threads::

    transport callbacks --(deque + Event)--> worker --(heap + Condition)--> timer --> publisher.put
    (stamp arrival;                          (route, model.process,         (wait until due:
     never block)                             push releases)                 Condition.wait, then
                                                                             spin the last spin_ns)

:meth:`LinkRelay.step` does what the two threads do, once, on the caller's thread: with
:meth:`LinkRelay.attach` instead of :meth:`LinkRelay.start` and an injected clock, a test drives
the relay deterministically.

* Payload bytes are relayed verbatim (never decoded); encoding and attachment are kept.
* One publisher per output key, declared on its first release and kept in an LRU of
  ``limits.max_keys`` publishers (reliable: it blocks, never drops); the least recently used
  one is undeclared when a new key needs a place.
* Bounded memory (:class:`~pd_service.link.config.Limits`): at most ``max_held_messages``
  messages and ``max_held_bytes`` bytes wait for release, each rule (and the unmatched traffic
  of each direction) at most an equal share of them, ``limits / (rules + 2)``, so a flood under
  one rule never takes another's room (over its share, a message is dropped and counted as
  ``dropped_capacity``, per rule and in total), and at most ``max_keys`` routes,
  per-key models and publishers are kept (LRU; evictions counted as ``keys_evicted``).
* Queryables: :func:`keys.link_rules_key` (GET -> current rules as JSON; GET with a payload ->
  replace the rules, answer the new rules or an error) and :func:`keys.link_stats_key`
  (per-rule counters and delay quantiles as JSON).
* A stats line per active rule is logged every ``stats_interval_s`` at INFO.

Timing: ``clock`` is ``time.monotonic_ns``; a message's arrival time is stamped in the transport
callback, its release time is ``arrival + decided delay``; ``lateness`` = publish time - release
time is what the timer thread could not hit (the benchmark's |applied - configured|).
"""

from __future__ import annotations

import heapq
import itertools
import json
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pd_service.errors import ConfigError
from pd_service.transport.base import (
    DEFAULT_SENDER_CACHE,
    Handle,
    Publisher,
    Query,
    Sample,
    Transport,
)
from pd_service.transport.keyexpr import intersects
from pd_service.wire import keys

from .config import (
    HELD_OVERHEAD_BYTES,
    KeyMapping,
    LinkConfig,
    Rule,
    decode_document,
    parse_config,
)
from .model import Decision, LinkModel

log = logging.getLogger("pd_service.link")
_JSON = "application/json"

_RESERVOIR = 20_000  # delays kept per rule for the quantiles (the most recent ones)


class RuleStats:
    """Counters of one rule (or of the unmatched traffic of one direction).

    Each counter has a single writer thread (worker: received/dropped/duplicated/reordered/
    corrupted/stalled/dropped_capacity; timer: forwarded and the delay samples), so no lock is
    needed for them; ``held``/``held_bytes`` are guarded by the relay's ``_cond``.
    """

    def __init__(self, direction: str, name: str, match: str | None) -> None:
        self.direction = direction
        self.name = name
        self.match = match
        self.received = 0
        self.forwarded = 0
        self.dropped_loss = 0
        self.dropped_outage = 0
        self.duplicated = 0
        self.reordered = 0
        self.corrupted = 0
        self.stalled = 0
        self.dropped_capacity = 0  # over its share of limits.max_held_messages / _bytes
        self.held = 0  # messages of this rule waiting for release (guarded by the relay's _cond)
        self.held_bytes = 0  # their bytes (idem)
        self._lock = threading.Lock()
        self._delay_ns: deque[int] = deque(maxlen=_RESERVOIR)
        self._late_ns: deque[int] = deque(maxlen=_RESERVOIR)

    def record_decision(self, d: Decision) -> None:
        self.received += 1
        if d.dropped == "loss":
            self.dropped_loss += 1
        elif d.dropped == "outage":
            self.dropped_outage += 1
        if d.stalled:
            self.stalled += 1
        for r in d.releases:
            self.duplicated += r.duplicate
            self.reordered += r.reordered
            self.corrupted += r.corrupted

    def record_release(self, applied_ns: int, late_ns: int) -> None:
        self.forwarded += 1
        with self._lock:
            self._delay_ns.append(applied_ns)
            self._late_ns.append(late_ns)

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            delays = np.fromiter(self._delay_ns, dtype=np.float64)
            late = np.fromiter(self._late_ns, dtype=np.float64)

        def q(a: np.ndarray) -> dict[str, float | None]:
            if a.size == 0:
                return {"p50": None, "p99": None}
            p50, p99 = np.percentile(a, [50, 99]) / 1e6
            return {"p50": round(float(p50), 4), "p99": round(float(p99), 4)}

        return {
            "direction": self.direction,
            "name": self.name,
            "match": self.match,
            "received": self.received,
            "forwarded": self.forwarded,
            "dropped": self.dropped_loss + self.dropped_outage + self.dropped_capacity,
            "dropped_loss": self.dropped_loss,
            "dropped_outage": self.dropped_outage,
            "dropped_capacity": self.dropped_capacity,
            "held": self.held,
            "held_bytes": self.held_bytes,
            "duplicated": self.duplicated,
            "reordered": self.reordered,
            "corrupted": self.corrupted,
            "stalled": self.stalled,
            "delay_ms": q(delays),
            "lateness_ms": q(late),
            "samples": int(delays.size),
        }


@dataclass(slots=True)
class _Route:
    """Where one input key goes and what is applied to it (cached per rule generation).
    The output publisher is looked up by ``out_key`` at release time (its own LRU)."""

    out_key: str
    model: LinkModel | None  # None: passthrough (no rule matched)
    stats: RuleStats


@dataclass(slots=True)
class _Generation:
    """One installed rule set.  Replaced wholesale (one reference swap) by the queryable."""

    number: int
    config: LinkConfig
    epoch_ns: int
    stats: dict[tuple[str, int], RuleStats]  # (direction, rule index or -1 for unmatched)
    # LRU (most recent last), each at most limits.max_keys entries
    share: tuple[int, int] = (0, 0)  # what one rule may hold: (messages, bytes)
    routes: OrderedDict[tuple[int, str], _Route | None] = field(default_factory=OrderedDict)
    models: OrderedDict[tuple[str, int, str], LinkModel] = field(default_factory=OrderedDict)
    shared_models: dict[tuple[str, int], LinkModel] = field(default_factory=dict)


def _new_generation(number: int, config: LinkConfig, epoch_ns: int) -> _Generation:
    stats: dict[tuple[str, int], RuleStats] = {}
    for direction in ("downlink", "uplink"):
        for i, rule in enumerate(config.rules(direction)):
            stats[(direction, i)] = RuleStats(direction, rule.name, rule.match)
        stats[(direction, -1)] = RuleStats(direction, "(unmatched)", None)
    # each rule (and the unmatched traffic of each direction) may hold an equal share of the
    # limits, so that a flood under one rule never takes the room of another
    n, lim = len(stats), config.limits
    share = (max(1, lim.max_held_messages // n), max(1, lim.max_held_bytes // n))
    return _Generation(number, config, epoch_ns, stats, share)


class LinkRelay:
    """Relays the configured mappings through the link model on an open transport.

    ``spin_ns``: the timer thread busy-waits (holding the GIL) for the last ``spin_ns`` before
    a release instead of trusting ``Condition.wait`` to wake up on time -- only while releases
    are sparse (more than ``10 * spin_ns`` apart), which bounds the CPU it burns.
    ``express``: Zenoh's express flag on the output publishers (no batching).  Off by default:
    it costs CPU at high rates without lowering the latency (docs/link.md, "Timing").
    ``max_inbox``: messages waiting for the worker beyond this are dropped (and counted as
    ``overflow``).
    ``cache``: the output publishers of keys the service reads (``pd/p<k>/<s>/sensor/<name>``,
    ``pd/p<k>/<s>/cmd``) keep their last ``cache`` samples (0: none), which a restarted service
    reads back (``Transport.publisher(key, cache=...)``): what the link released while no
    service ran is not lost. Memory: at most ``limits.max_keys`` x ``cache`` samples (about
    26 MB for 1,024 keys of 100-byte samples at the default 256).
    """

    def __init__(
        self,
        transport: Transport,
        config: LinkConfig,
        instance: str = "default",
        *,
        spin_ns: int = 100_000,
        stats_interval_s: float = 10.0,
        max_inbox: int = 100_000,
        express: bool = False,
        cache: int = DEFAULT_SENDER_CACHE,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self._transport = transport
        self._cache = cache
        self.instance = keys.check_name(instance, "instance")
        self._clock = clock
        self._spin_ns = int(spin_ns)
        self._stats_interval_ns = int(stats_interval_s * 1e9)
        self._max_inbox = max_inbox
        self._express = express
        self._gen = _new_generation(1, config, clock())
        self._gen_lock = threading.Lock()  # serialises replacements (not the hot path)

        self._inbox: deque[tuple[Any, ...]] = deque()
        self._wake = threading.Event()
        self._heap: list[tuple[Any, ...]] = []
        self._cond = threading.Condition(threading.Lock())
        self._seq = itertools.count()
        self._stopping = False
        self._limits = config.limits
        self._held = 0  # messages in the heap (guarded by _cond)
        self._held_bytes = 0  # their bytes, HELD_OVERHEAD_BYTES each included (idem)
        #: Copies taken from the heap and not yet published (idem): still pending, so that
        #: ``pending == 0`` in the stats means every due copy went out
        self._releasing = 0

        # output publishers, LRU (most recent last); used by the releasing thread only
        self._publishers: OrderedDict[str, Publisher] = OrderedDict()
        self._handles: list[Handle] = []
        self._threads: list[threading.Thread] = []
        self.overflow = 0  # inbox full
        self.unmapped = 0  # key that the mapping cannot translate
        self.loops = 0  # output key would be received again by one of our subscriptions
        self.dropped_capacity = 0  # held messages or bytes at their limit (all rules)
        self.keys_evicted = 0  # routes and per-key models forgotten (LRU over max_keys)
        self.publishers_evicted = 0  # publishers undeclared (LRU over max_keys)
        self._warned: set[str] = set()
        self._started_ns = clock()
        self._last_log_ns = self._started_ns

    # lifecycle ---------------------------------------------------------------------------

    def start(self) -> LinkRelay:
        """Start the threads, then :meth:`attach`."""
        self._threads = [
            threading.Thread(target=self._worker, name="pd-link-worker", daemon=True),
            threading.Thread(target=self._timer, name="pd-link-timer", daemon=True),
        ]
        for t in self._threads:
            t.start()
        return self.attach()

    def attach(self) -> LinkRelay:
        """Declare the queryables and subscribers.  Without :meth:`start` nothing moves until
        :meth:`step` is called."""
        t = self._transport
        self._handles += [
            t.queryable(keys.link_rules_key(self.instance), self._on_rules_query),
            t.queryable(keys.link_stats_key(self.instance), self._on_stats_query),
        ]
        for idx, m in enumerate(self._gen.config.mappings):
            self._handles.append(t.subscribe(m.subscribe, self._callback(idx)))
        log.info(
            "pd-link ready",
            extra={"fields": {
                "instance": self.instance,
                "subscriptions": [m.subscribe for m in self._gen.config.mappings],
                "rules": keys.link_rules_key(self.instance),
                "stats": keys.link_stats_key(self.instance),
            }},
        )  # fmt: skip
        return self

    def close(self) -> None:
        """Undeclare everything and stop the threads; messages still pending are dropped."""
        if self._stopping:
            return
        for h in self._handles:
            try:
                h.close()
            except Exception:  # the transport may already be closed
                pass
        self._handles.clear()
        self._stopping = True
        self._wake.set()
        with self._cond:
            pending = len(self._heap)
            self._heap.clear()
            self._held = self._held_bytes = 0
            self._cond.notify_all()
        for t in self._threads:
            t.join(timeout=5.0)
        for pub in self._publishers.values():
            try:
                pub.close()
            except Exception:
                pass
        self._publishers.clear()
        if pending:
            log.info("pd-link stopped with pending messages dropped",
                     extra={"fields": {"pending": pending}})  # fmt: skip

    def __enter__(self) -> LinkRelay:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # rules and stats ---------------------------------------------------------------------

    @property
    def config(self) -> LinkConfig:
        return self._gen.config

    @property
    def generation(self) -> int:
        return self._gen.number

    def replace_rules(self, doc: dict[str, Any] | LinkConfig) -> LinkConfig:
        """Install a new rule set (raises :class:`ConfigError`); models and stats restart."""
        with self._gen_lock:
            old = self._gen
            cfg = doc if isinstance(doc, LinkConfig) else parse_config(doc, base=old.config)
            if cfg.mappings != old.config.mappings:
                raise ConfigError("mapping cannot be changed at runtime; restart pd-link")
            self._gen = _new_generation(old.number + 1, cfg, self._clock())
        log.info("rules replaced", extra={"fields": {
            "generation": self._gen.number,
            "downlink": [r.name for r in cfg.downlink],
            "uplink": [r.name for r in cfg.uplink],
        }})  # fmt: skip
        return cfg

    def rules_document(self) -> dict[str, Any]:
        gen = self._gen
        return {"instance": self.instance, "generation": gen.number} | gen.config.to_dict()

    def stats(self) -> dict[str, Any]:
        gen = self._gen
        with self._cond:
            pending, held_bytes = len(self._heap) + self._releasing, self._held_bytes
        return {
            "instance": self.instance,
            "generation": gen.number,
            "uptime_s": round((self._clock() - self._started_ns) / 1e9, 3),
            "rules_age_s": round((self._clock() - gen.epoch_ns) / 1e9, 3),
            "pending": pending,
            "pending_bytes": held_bytes,
            "inbox": len(self._inbox),
            "overflow": self.overflow,
            "unmapped": self.unmapped,
            "loops": self.loops,
            "dropped_capacity": self.dropped_capacity,
            "keys": len(gen.routes),
            "keys_evicted": self.keys_evicted,
            "publishers": len(self._publishers),
            "publishers_evicted": self.publishers_evicted,
            "limits": self._limits.to_dict(),
            "rules": [s.snapshot() for s in gen.stats.values()],
        }

    def _on_rules_query(self, query: Query) -> None:
        key = keys.link_rules_key(self.instance)
        try:
            data = query.payload or b""
            if data.strip():
                self.replace_rules(decode_document(data))
            body = json.dumps(self.rules_document()).encode()
            query.reply(key, body, encoding=_JSON)
        except ConfigError as e:
            log.warning("rules replacement refused", extra={"fields": {"error": str(e)}})
            query.reply_err(json.dumps({"error": str(e)}).encode(), encoding=_JSON)
        except Exception as e:  # never let a bad query kill the callback thread
            log.exception("rules query failed")
            try:
                query.reply_err(json.dumps({"error": f"internal error: {e}"}).encode())
            except Exception:
                pass

    def _on_stats_query(self, query: Query) -> None:
        try:
            body = json.dumps(self.stats()).encode()
            query.reply(keys.link_stats_key(self.instance), body, encoding=_JSON)
        except Exception:
            log.exception("stats query failed")

    # hot path: callbacks -> worker -------------------------------------------------------

    def _callback(self, mapping_index: int) -> Callable[[Sample], None]:
        inbox, wake, clock = self._inbox, self._wake, self._clock
        max_inbox = self._max_inbox

        def on_sample(sample: Sample) -> None:
            now = clock()
            if len(inbox) >= max_inbox:
                self.overflow += 1
                return
            inbox.append((
                now,
                mapping_index,
                sample.key,
                sample.payload,
                sample.encoding,
                sample.attachment,
                sample.kind == "delete",
            ))  # fmt: skip
            if not wake.is_set():
                wake.set()

        return on_sample

    def step(self) -> int:
        """Handle every message received so far, then publish every copy due at ``clock()``;
        returns how many were published.  (What the worker and timer threads do.)"""
        self._drain_inbox()
        with self._cond:
            batch = self._pop_due(self._clock())
        self._publish(batch)
        return len(batch)

    def _worker(self) -> None:
        wake = self._wake
        while not self._stopping:
            wake.wait(timeout=1.0)
            wake.clear()
            self._drain_inbox()
            self._maybe_log_stats()

    def _drain_inbox(self) -> None:
        inbox = self._inbox
        while True:
            try:
                item = inbox.popleft()
            except IndexError:
                return
            try:
                self._handle(*item)
            except Exception:
                log.exception("dropping a message after an internal error")

    def _handle(self, arrival_ns: int, mapping_index: int, key: str, payload: bytes,
                encoding: str | None, attachment: bytes | None, is_delete: bool) -> None:  # fmt: skip
        gen = self._gen
        route_key = (mapping_index, key)
        routes = gen.routes
        try:
            route = routes[route_key]
            routes.move_to_end(route_key)
        except KeyError:
            route = self._route(gen, mapping_index, key)
            routes[route_key] = route
            if len(routes) > self._limits.max_keys:
                routes.popitem(last=False)
                self.keys_evicted += 1
        if route is None:
            return
        if route.model is None:  # no rule: forward as is
            route.stats.received += 1
            self._push(arrival_ns, route, payload, encoding, attachment, is_delete, arrival_ns)
            return
        decision = route.model.process(arrival_ns, payload)
        route.stats.record_decision(decision)
        for rel in decision.releases:
            self._push(rel.time_ns, route, rel.payload, encoding, attachment, is_delete,
                       arrival_ns)  # fmt: skip

    def _route(self, gen: _Generation, mapping_index: int, key: str) -> _Route | None:
        mapping: KeyMapping = gen.config.mappings[mapping_index]
        try:
            out_key = mapping.map_key(key)
        except ValueError as e:
            self.unmapped += 1
            self._warn_once(f"unmapped:{key}", "key does not map; dropped",
                            key=key, error=str(e))  # fmt: skip
            return None
        if any(intersects(m.subscribe, out_key) for m in gen.config.mappings):
            self.loops += 1
            self._warn_once(f"loop:{key}", "output key would loop back into pd-link; dropped",
                            key=key, out_key=out_key)  # fmt: skip
            return None
        direction = mapping.direction
        found = gen.config.rule_for(direction, key)
        if found is None:
            return _Route(out_key, None, gen.stats[(direction, -1)])
        index, rule = found
        return _Route(out_key, self._model(gen, direction, index, rule, key),
                      gen.stats[(direction, index)])  # fmt: skip

    def _model(self, gen: _Generation, direction: str, index: int, rule: Rule,
               key: str) -> LinkModel:  # fmt: skip
        if rule.shared:  # one per rule: bounded by the rule count
            model = gen.shared_models.get((direction, index))
            if model is None:
                seed = f"{gen.config.seed}/{direction}/{rule.name}/*"
                model = LinkModel(rule.params, seed=seed, epoch_ns=gen.epoch_ns)
                gen.shared_models[(direction, index)] = model
            return model
        mkey = (direction, index, key)
        models = gen.models
        model = models.get(mkey)
        if model is None:
            seed = f"{gen.config.seed}/{direction}/{rule.name}/{key}"
            model = LinkModel(rule.params, seed=seed, epoch_ns=gen.epoch_ns)
            models[mkey] = model
            if len(models) > self._limits.max_keys:
                models.popitem(last=False)
        else:
            models.move_to_end(mkey)
        return model

    def _push(self, release_ns: int, route: _Route, payload: bytes, encoding: str | None,
              attachment: bytes | None, is_delete: bool, arrival_ns: int) -> None:  # fmt: skip
        size = len(payload) + (len(attachment) if attachment else 0) + HELD_OVERHEAD_BYTES
        item = (release_ns, next(self._seq), route, payload, encoding, attachment, is_delete,
                arrival_ns, size)  # fmt: skip
        limits, st = self._limits, route.stats
        share_msgs, share_bytes = self._gen.share
        with self._cond:
            if (self._held >= limits.max_held_messages
                    or self._held_bytes + size > limits.max_held_bytes
                    or st.held >= share_msgs or st.held_bytes + size > share_bytes):
                full = True
            else:
                full = False
                self._held += 1
                self._held_bytes += size
                st.held += 1
                st.held_bytes += size
                heapq.heappush(self._heap, item)
                if self._heap[0] is item:
                    self._cond.notify()
        if full:
            route.stats.dropped_capacity += 1
            self.dropped_capacity += 1

    # timer: heap -> publish ----------------------------------------------------------------

    def _timer(self) -> None:
        _set_timer_slack_ns(1_000)
        while not self._stopping:
            try:
                self._timer_loop()
            except Exception:  # a bug must not silently stop every release
                log.exception("timer thread error; continuing")

    def _timer_loop(self) -> None:
        heap, cond, clock, spin = self._heap, self._cond, self._clock, self._spin_ns
        last_release = 0
        while True:
            with cond:
                while True:
                    if self._stopping:
                        return
                    if not heap:
                        cond.wait(timeout=1.0)
                        continue
                    due = heap[0][0]
                    now = clock()
                    # Busy-wait the last `spin` ns only while releases are sparse (> 10 spins
                    # apart), so spinning never takes more than ~10% of a core at high rates.
                    margin = spin if now - last_release > 10 * spin else 0
                    remaining = due - now
                    if remaining > margin:
                        cond.wait(timeout=(remaining - margin) / 1e9)
                        continue
                    break
            while clock() < due:  # the last stretch: Condition.wait may wake up late
                pass
            with cond:
                now = clock()
                batch = self._pop_due(now)
            last_release = now
            self._publish(batch)

    def _pop_due(self, now: int) -> list[tuple[Any, ...]]:
        """The heap's items due at ``now``, earliest first (call with ``_cond`` held)."""
        heap, batch = self._heap, []
        while heap and heap[0][0] <= now:
            item = heapq.heappop(heap)
            size, st = item[-1], item[2].stats
            self._held -= 1
            self._held_bytes -= size
            st.held -= 1
            st.held_bytes -= size
            batch.append(item)
        self._releasing += len(batch)
        return batch

    def _publish(self, batch: list[tuple[Any, ...]]) -> None:
        try:
            self._put_all(batch)
        finally:
            with self._cond:
                self._releasing -= len(batch)

    def _put_all(self, batch: list[tuple[Any, ...]]) -> None:
        clock = self._clock
        for release_ns, _, route, payload, encoding, attachment, is_delete, arrival, _n in batch:
            t = clock()
            try:
                publisher = self._publisher(route.out_key)
                if is_delete:
                    publisher.delete(attachment=attachment)
                else:
                    publisher.put(payload, encoding=encoding, attachment=attachment)
            except Exception as e:
                self._warn_once(f"put:{route.out_key}", "publish failed",
                                key=route.out_key, error=str(e))  # fmt: skip
                continue
            route.stats.record_release(t - arrival, t - release_ns)

    def _publisher(self, out_key: str) -> Publisher:
        """The output key's publisher from the LRU, declared on a miss (the least recently
        used one undeclared beyond ``limits.max_keys``).  Releasing thread only."""
        pubs = self._publishers
        pub = pubs.get(out_key)
        if pub is not None:
            pubs.move_to_end(out_key)
            return pub
        if len(pubs) >= self._limits.max_keys:  # undeclare first: never more than max_keys
            _, old = pubs.popitem(last=False)
            self.publishers_evicted += 1
            try:
                old.close()
            except Exception as e:
                self._warn_once("undeclare", "cannot undeclare a publisher", error=str(e))
        cached = intersects(keys.ALL_SENSORS, out_key) or intersects(keys.ALL_COMMANDS, out_key)
        pub = self._transport.publisher(out_key, express=self._express,
                                        cache=self._cache if cached else 0)
        pubs[out_key] = pub
        return pub

    # logging -------------------------------------------------------------------------------

    def _maybe_log_stats(self) -> None:
        now = self._clock()
        if now - self._last_log_ns < self._stats_interval_ns:
            return
        self._last_log_ns = now
        for s in self._gen.stats.values():
            if s.received == 0:
                continue
            snap = s.snapshot()
            log.info("stats", extra={"fields": {
                "generation": self._gen.number,
                "direction": snap["direction"], "rule": snap["name"],
                "received": snap["received"], "forwarded": snap["forwarded"],
                "dropped": snap["dropped"], "dropped_capacity": snap["dropped_capacity"],
                "duplicated": snap["duplicated"],
                "reordered": snap["reordered"], "corrupted": snap["corrupted"],
                "stalled": snap["stalled"],
                "delay_p50_ms": snap["delay_ms"]["p50"], "delay_p99_ms": snap["delay_ms"]["p99"],
                "late_p99_ms": snap["lateness_ms"]["p99"],
            }})  # fmt: skip
        if self.overflow or self.unmapped or self.loops or self.dropped_capacity:
            with self._cond:
                held, held_bytes = self._held, self._held_bytes
            log.warning("refused", extra={"fields": {
                "overflow": self.overflow, "unmapped": self.unmapped, "loops": self.loops,
                "dropped_capacity": self.dropped_capacity, "held": held,
                "held_bytes": held_bytes, "keys_evicted": self.keys_evicted}})

    def _warn_once(self, tag: str, msg: str, **fields: Any) -> None:
        if tag in self._warned or len(self._warned) > 1000:
            return
        self._warned.add(tag)
        log.warning(msg, extra={"fields": fields})



def _set_timer_slack_ns(ns: int) -> None:
    """Linux: let this thread's timed waits wake within ``ns`` of the deadline (default 50 us).

    prctl(PR_SET_TIMERSLACK = 29, ns) applies to the calling thread only; a no-op elsewhere.
    """
    try:
        import ctypes
        import sys

        if sys.platform.startswith("linux"):
            ctypes.CDLL(None, use_errno=True).prctl(29, ctypes.c_ulong(ns), 0, 0, 0)
    except Exception:
        pass


#: Per-rule counters of :meth:`RuleStats.snapshot` exported as pd_link_rule_<name>_total.
RULE_COUNTERS = ("received", "forwarded", "dropped_loss", "dropped_outage", "dropped_capacity",
                 "duplicated", "reordered", "corrupted", "stalled")
#: Relay-wide counters of :meth:`LinkRelay.stats`.
RELAY_COUNTERS = ("overflow", "unmapped", "loops", "dropped_capacity", "keys_evicted",
                  "publishers_evicted")


def link_metrics(relay: LinkRelay) -> list[Any]:
    """pd-link's metric families (``pd-link --metrics``), read from :meth:`LinkRelay.stats`:
    relay counters and levels, and per rule (a bounded set: the rules file's) its counters
    labelled by direction and rule."""
    from pd_service.metrics import counter, counters, gauge

    st = relay.stats()
    out = counters("pd_link", {k: st[k] for k in RELAY_COUNTERS}, "Relay")
    out += [gauge("pd_link_pending", "Messages waiting for their release.", st["pending"]),
            gauge("pd_link_pending_bytes", "Bytes waiting for their release.", st["pending_bytes"]),
            gauge("pd_link_inbox", "Messages received, not yet handled.", st["inbox"]),
            gauge("pd_link_keys", "Input keys with a cached route.", st["keys"]),
            gauge("pd_link_publishers", "Output publishers declared.", st["publishers"]),
            gauge("pd_link_rules_generation", "Rules generation (1 + replacements).",
                  st["generation"]),
            gauge("pd_link_uptime_seconds", "Seconds since the relay started.", st["uptime_s"])]
    for name in RULE_COUNTERS:
        rows: dict[tuple[str, ...], float] = {(str(r["direction"]), str(r["name"])): r[name]
                                              for r in st["rules"]}
        out.append(counter(f"pd_link_rule_{name}", f"Messages {name}, per rule.", rows=rows,
                           label_names=("direction", "rule")))
    return out
