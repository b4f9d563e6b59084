#!/usr/bin/env python3
"""foxglove-sdk's advertise-before-register race, counted: why pd-viz makes every channel
before its WebSocket server starts (docs/visualize.md, "The ros2/* channels").

A foxglove-sdk server (the one pd-viz runs on) with one client connected that subscribes to
each channel the moment it is advertised, as Foxglove, Lichtblick and @foxglove/ws-protocol
clients do; the script then makes ``--channels`` channels one by one, 2 ms apart, and counts
the server's "Unknown channel ID" refusals. ``--hogs N`` runs N busy-loop processes beside it
(nice 19, ended when the run ends) to load the machine. Printed: a table of the refusals per
run, then one JSON line. A count, not a timing: no gauge needed.

Usage: python bench/viz_advertise.py [--channels 1000] [--runs 2] [--hogs 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import threading
import time
from typing import Any

from stamps import cpu_model


def refusals(n: int) -> dict[str, int]:
    """Make ``n`` channels while a client subscribes at once: advertised, refused."""
    import foxglove
    from websockets.sync.client import connect

    ctx = foxglove.Context()
    server = foxglove.start_server(name="viz-advertise", host="127.0.0.1", port=0, context=ctx)
    refused, advertised = [0], [0]
    done = threading.Event()
    with connect(f"ws://127.0.0.1:{server.port}",
                 subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:  # type: ignore[list-item]

        def read() -> None:
            while not done.is_set():
                try:
                    frame = ws.recv(timeout=0.2)
                except TimeoutError:
                    continue
                except Exception:  # the connection closed
                    return
                if not isinstance(frame, str):
                    continue
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    for ch in msg["channels"]:
                        advertised[0] += 1
                        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": advertised[0], "channelId": ch["id"]}]}))
                elif msg.get("op") == "status" and "Unknown channel" in msg.get("message", ""):
                    refused[0] += 1

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        time.sleep(0.5)
        channels: list[Any] = []
        for i in range(n):
            channels.append(foxglove.Channel(f"/t{i}", message_encoding="json", context=ctx))
            time.sleep(0.002)
        time.sleep(1.0)
        done.set()
        reader.join(2.0)
    server.stop()
    return {"channels": n, "advertised": advertised[0], "refused": refused[0]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--channels", type=int, default=1000)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--hogs", type=int, default=0, help="busy-loop processes beside the runs")
    args = ap.parse_args()
    hogs = [subprocess.Popen([sys.executable, "-c", "import os; os.nice(19)\nwhile True: pass"])
            for _ in range(args.hogs)]
    try:
        runs = [refusals(args.channels) for _ in range(args.runs)]
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    print(f"cpu {cpu_model()}  hogs {args.hogs}")
    print(f"{'run':>4} {'channels':>9} {'advertised':>11} {'refused':>8}")
    for i, r in enumerate(runs):
        print(f"{i:>4} {r['channels']:>9} {r['advertised']:>11} {r['refused']:>8}")
    counts = [r["refused"] for r in runs]
    print(json.dumps({"bench": "viz_advertise", "hogs": args.hogs, "channels": args.channels,
                      "refused": counts, "refused_median": statistics.median(counts)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
