"""What sender caches (``Transport.publisher(key, cache=N)``, zenoh-ext advanced publishers)
cost per message, against plain puts and plain declared publishers.

    .venv/bin/python bench/sender_cache.py                       # 300 keys, 20,000 messages
    .venv/bin/python bench/sender_cache.py --keys 30 --messages 20000 --rate 4000
    .venv/bin/python bench/sender_cache.py --keys 1000 --owned 500 --messages 100000 \
        --rate 20000 --modes put --rounds 1

Setup, on loopback: a receiver process (a Zenoh peer listening on a free port) subscribes to
``pd/*/*/sensor/*`` through ``ZenohTransport.subscribe`` with a callback that only counts, as
the daemon's plain live subscription does (its callback is Dispatch's: split, append). This
process connects to it and sends ``--messages`` messages of 80 bytes round-robin over
``--keys`` keys at ``--rate`` messages/s, in three modes:

* ``put``: undeclared ``Transport.put`` (what the SDK did before);
* ``publisher``: one declared plain publisher per key;
* ``cached``: one cached publisher per key (``cache=256``: the SDK's default now), which adds
  a cache, a queryable and a liveliness token per key and a sequence number per sample.

With ``--owned K`` the receiver subscribes to the first K sessions one by one
(``pd/p<k>/<s>/sensor/*``) instead of with one wildcard, and receives only their share: what an
instance that received only the sessions it owns would pay, and what its senders would.

Printed per mode: the sender's µs per put (wall time inside ``put``), and the receiver's
process CPU per received message (getrusage between its first and last message: Zenoh's
threads and the Python callback). The receiver never declares anything cached: the daemon's
per-message path is its plain subscription, and only the declarations it learns (queryables,
tokens) and the samples' extra bytes (sequence numbers) can change its cost.
"""

from __future__ import annotations

import argparse
import json
import resource
import socket
import subprocess
import sys
import time

RECEIVER = r"""
import json, resource, sys, threading, time
from pd_service.transport import ZenohTransport, zenoh_config
from pd_service.wire import keys
port, total, owned = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
t = ZenohTransport(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast=False))
state = {"n": 0, "c0": 0.0, "t0": 0.0}
done = threading.Event()
def cpu():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime
def on(s):
    n = state["n"] = state["n"] + 1
    if n == 1:
        state["c0"], state["t0"] = cpu(), time.monotonic()
    elif n == total:
        state["c1"], state["t1"] = cpu(), time.monotonic()
        done.set()
if owned:  # one subscription per owned session, as an instance receiving only its own
    for i in range(owned):
        t.subscribe(keys.sensors_of(f"b{i:04d}"), on)
else:
    t.subscribe(keys.ALL_SENSORS, on)
print("ready", flush=True)
for line in sys.stdin:
    if line.strip() == "go":
        state["n"] = 0
        done.wait(120)
        print(json.dumps({"n": state["n"], "cpu_s": state.get("c1", 0) - state["c0"],
                          "wall_s": state.get("t1", 0) - state["t0"]}), flush=True)
        done.clear()
t.close()
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--keys", type=int, default=300)
    ap.add_argument("--messages", type=int, default=20_000)
    ap.add_argument("--rate", type=float, default=4000.0, help="messages/s sent")
    ap.add_argument("--cache", type=int, default=256)
    ap.add_argument("--rounds", type=int, default=2, help="modes run this many times, in turn")
    ap.add_argument("--owned", type=int, default=0,
                    help="the receiver subscribes to the first OWNED keys' sessions one by one "
                         "(pd/p<k>/<s>/sensor/*) instead of to all with one wildcard: what an "
                         "instance that received only the sessions it owns would pay")
    ap.add_argument("--modes", default="put,publisher,cached",
                    help="comma-separated; also 'cached-nodetect' (no liveliness token: no "
                         "late-sender detection) and 'cached-ts' (timestamps instead of "
                         "sequence numbers; needs timestamping in the sender's config)")
    args = ap.parse_args(argv)

    from pd_service.transport import ZenohTransport, zenoh_config
    from pd_service.wire.keys import sensor_key

    port = free_port()
    owned = min(args.owned, args.keys)
    # messages go round-robin over the keys: the owned (first) keys' share arrives
    received = sum(1 for i in range(args.messages) if not owned or i % args.keys < owned)
    rx = subprocess.Popen([sys.executable, "-c", RECEIVER, str(port), str(received), str(owned)],
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert rx.stdout is not None and rx.stdin is not None
    assert rx.stdout.readline().strip() == "ready"
    keys = [sensor_key(f"b{i:04d}", "cam") for i in range(args.keys)]
    payload = b"x" * 80
    period = 1.0 / args.rate
    print(f"{args.keys} keys, {args.messages} messages at {args.rate:.0f}/s, 80-byte payload; "
          + (f"receiver subscribes to {owned} sessions one by one ({received} messages)"
             if owned else "receiver subscribes to all with one wildcard"))
    print(f"{'mode':<16} {'sender µs/put':>14} {'receiver µs CPU/msg':>20} "
          f"{'receiver µs CPU/sent':>21}")
    rows: list[dict] = []
    for mode in args.modes.split(",") * args.rounds:
        conf = zenoh_config(mode="peer", listen=[], connect=[f"tcp/127.0.0.1:{port}"],
                            multicast=False)
        if mode == "cached-ts":
            conf.insert_json5("timestamping/enabled", "true")
        t = ZenohTransport(conf)
        if mode == "put":
            puts = [lambda p, k=k, t=t: t.put(k, p) for k in keys]
        elif mode in ("cached-nodetect", "cached-ts"):
            import zenoh.ext as ze
            miss = None if mode == "cached-ts" else ze.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=None)
            advs = [ze.declare_advanced_publisher(
                t.session, k, cache=ze.CacheConfig(max_samples=args.cache),
                publisher_detection=mode == "cached-ts", sample_miss_detection=miss)
                for k in keys]
            puts = [a.put for a in advs]
        else:
            pubs = [t.publisher(k, cache=args.cache if mode == "cached" else 0) for k in keys]
            puts = [p.put for p in pubs]
        time.sleep(1.0 + owned / 250)  # declarations settle (not measured)
        rx.stdin.write("go\n")
        rx.stdin.flush()
        spent = 0.0
        t_next = time.perf_counter()
        for i in range(args.messages):
            t_next += period
            d = t_next - time.perf_counter()
            if d > 0:
                time.sleep(d)
            t0 = time.perf_counter()
            puts[i % len(puts)](payload)
            spent += time.perf_counter() - t0
        res = json.loads(rx.stdout.readline())
        if res["n"] != received:
            raise SystemExit(f"the receiver got {res['n']} of {received} messages (its "
                             "subscriptions had not reached the sender?)")
        print(f"{mode:<16} {spent / args.messages * 1e6:>14.2f} "
              f"{res['cpu_s'] / (received - 1) * 1e6:>20.2f} "
              f"{res['cpu_s'] / args.messages * 1e6:>21.2f}")
        rows.append({"mode": mode, "owned": owned, "sender_us_per_put": spent / args.messages * 1e6,
                     "receiver_us_per_received": res["cpu_s"] / (received - 1) * 1e6,
                     "receiver_us_per_sent": res["cpu_s"] / args.messages * 1e6})
        if mode in ("cached-nodetect", "cached-ts"):
            for a in advs:
                a.undeclare()
        t.close()
        time.sleep(0.5)
    rx.stdin.close()
    rx.wait(10)
    r = resource.getrusage(resource.RUSAGE_SELF)
    print(f"(sender process CPU {r.ru_utime + r.ru_stime:.1f} s)")
    print(json.dumps(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
