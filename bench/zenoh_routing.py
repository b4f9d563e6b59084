#!/usr/bin/env python3
"""What Zenoh 1.10 charges per message as per-session declarations pile up on the network,
and what declared keys save: the reason the daemon declares its sessions' keys
(``Transport.declare_keys``, docs/service.md "Declared keys").

A sender process (this one) puts on 1,000 sensor keys ``pd/p<k>/s<i>/sensor/ranger`` in 1 ms
slots of 50 messages (the rate of 1,000 sessions' range finders); a receiver process
subscribes to ``pd/*/*/sensor/*`` as the daemon does (a FIFO drained by its main thread) and,
with ``declared``, declares the 1,000 keys it receives. The sender first declares
``--displays`` subscriptions ``pd/p<k>/s<i>/prediction`` (one display per session, as
``pd_client.Display`` does): exact keys whose chunk ``s<i>`` becomes one more sibling that
Zenoh compares with every undeclared key it routes.

Senders: ``put`` (``session.put`` per message), ``publisher`` (a declared publisher per key)
and ``cached`` (``Transport.publisher(key, cache=256)``: what ``pd_client`` Robot and Operator
declare, zenoh-ext advanced publishers with a cache and a liveliness token each).

Columns: ``put us`` the sending thread's CPU per put (``time.thread_time``); ``rx us`` the
receiver's Zenoh receive threads (``rx-*``, from /proc) per message received; ``proc us``
the whole receiver process (all threads, drain included) per message.

Usage: python bench/zenoh_routing.py [--displays 0,1000] [--messages 30000] [--repeat 2]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from pd_service.wire import keys  # noqa: E402  (after the path)

KEYS = [keys.sensor_key(f"s{i:04d}", "ranger") for i in range(1000)]
CLK = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def threads_cpu(pid: int | str = "self") -> dict[str, float]:
    """CPU seconds (utime + stime) of each thread of ``pid``, by thread id."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                s = f.read()
        except OSError:
            continue
        name = s[s.index("(") + 1 : s.rindex(")")]
        fs = s[s.rindex(")") + 2 :].split()
        out[f"{name}:{tid}"] = (int(fs[11]) + int(fs[12])) / CLK
    return out


def receiver(endpoint: str, declared: bool) -> None:
    """Subscribe as the daemon does; on each line of stdin drain, then print the CPU."""
    import zenoh

    from pd_service.transport import ZenohTransport, zenoh_config

    t = ZenohTransport(zenoh_config(mode="peer", listen=[endpoint]))
    sub = t.session.declare_subscriber(keys.ALL_SENSORS, zenoh.handlers.FifoChannel(1 << 20))
    if declared:
        t.declare_keys(KEYS)
    print("ready", flush=True)
    got = 0
    for _line in sys.stdin:
        while (s := sub.handler.try_recv()) is not None:
            got += 1
            s.payload.to_bytes()
        cpu = threads_cpu()
        rx = sum(v for k, v in cpu.items() if k.startswith("rx-"))
        print(json.dumps({"got": got, "rx": rx, "proc": sum(cpu.values())}), flush=True)
    sub.undeclare()
    t.close()


def one(displays: int, sender: str, declared: bool, messages: int) -> dict:
    import zenoh

    from pd_service.transport import DEFAULT_SENDER_CACHE, ZenohTransport, zenoh_config

    ep = f"tcp/127.0.0.1:{free_port()}"
    rp = subprocess.Popen([sys.executable, __file__, "--receiver", ep]
                          + (["--declared"] if declared else []),
                          stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert rp.stdout is not None and rp.stdin is not None
        if rp.stdout.readline().strip() != "ready":
            raise RuntimeError("receiver did not start")
        t = ZenohTransport(zenoh_config(mode="peer", listen=[], connect=[ep]))
        subs = [t.session.declare_subscriber(keys.prediction_key(f"s{i:04d}"),
                                             zenoh.handlers.RingChannel(1))
                for i in range(displays)]
        if sender == "put":
            puts = [lambda p, k=k: t.put(k, p) for k in KEYS]
        elif sender == "publisher":
            puts = [t.publisher(k).put for k in KEYS]
        else:
            puts = [t.publisher(k, cache=DEFAULT_SENDER_CACHE).put for k in KEYS]
        time.sleep(1.5)  # declarations settle

        def ask() -> dict:
            rp.stdin.write("x\n")
            rp.stdin.flush()
            return json.loads(rp.stdout.readline())

        payload = b"x" * 60
        r0 = ask()
        c0 = time.thread_time()
        sent = 0
        while sent < messages:
            for j in range(50):
                puts[(sent + j) % len(KEYS)](payload)
            sent += 50
            time.sleep(0.001)
        c1 = time.thread_time()
        time.sleep(1.0)
        r1 = ask()
        for s in subs:
            s.undeclare()
        t.close()
        n = r1["got"] - r0["got"]
        return {"displays": displays, "sender": sender, "declared": declared, "sent": sent,
                "received": n, "put_us": 1e6 * (c1 - c0) / sent,
                "rx_us": 1e6 * (r1["rx"] - r0["rx"]) / max(n, 1),
                "proc_us": 1e6 * (r1["proc"] - r0["proc"]) / max(n, 1)}
    finally:
        if rp.stdin is not None:
            rp.stdin.close()
        rp.wait(timeout=10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--displays", default="0,1000")
    ap.add_argument("--messages", type=int, default=30000)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--senders", default="put,publisher,cached")
    ap.add_argument("--receiver", help=argparse.SUPPRESS)
    ap.add_argument("--declared", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.receiver:
        receiver(args.receiver, args.declared)
        return
    print(f"Zenoh routing cost: {args.messages} messages on 1,000 keys per run, "
          f"{args.repeat} run(s) per row, medians (range); {os.cpu_count()} CPUs")
    print(f"{'displays':>8} {'sender':>9} {'receiver':>9} {'put us':>14} {'rx us':>16} "
          f"{'proc us':>16}")
    rows = []
    for d in [int(x) for x in args.displays.split(",")]:
        for sender in args.senders.split(","):
            for declared in (False, True):
                runs = [one(d, sender, declared, args.messages) for _ in range(args.repeat)]
                row = {"displays": d, "sender": sender, "declared": declared,
                       "received_min": min(r["received"] for r in runs),
                       "sent": runs[0]["sent"]}
                cells = []
                for key in ("put_us", "rx_us", "proc_us"):
                    vals = [r[key] for r in runs]
                    row[key] = round(statistics.median(vals), 2)
                    row[key + "_runs"] = [round(v, 2) for v in vals]
                    cells.append(f"{row[key]:.1f} ({min(vals):.1f}-{max(vals):.1f})")
                rows.append(row)
                print(f"{d:>8} {sender:>9} {'declared' if declared else 'wildcard':>9} "
                      f"{cells[0]:>14} {cells[1]:>16} {cells[2]:>16}", flush=True)
    print(json.dumps({"rows": rows}))


if __name__ == "__main__":
    main()
