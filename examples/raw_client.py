"""A complete pd-service client from docs/protocol.md alone: eclipse-zenoh + msgpack, no
project imports. It is what a C++ / Rust / JS integrator translates.

It runs the paper's scenario (Liang et al. 2017: a vehicle chasing an object; state
x = [p1, v1, p2, v2], a camera every 2 steps 10 steps late, a range finder every step 12
steps late, commands acting 10 steps after they are sent):

1. opens a Zenoh session in client mode to the daemon's endpoint, multicast scouting off
   (retrying while nothing listens there yet);
2. waits for readiness: a liveliness token on ``pd/@service/*`` (any daemon instance);
3. computes the session's partition k (protocol.md section 3: FNV-1a-32 of the name mod
   P, P from ``PD_PARTITIONS`` as for every party, default 64), so every key of the session
   is ``pd/p<k>/<session>/...``;
4. puts the SessionSpec on ``pd/p<k>/<session>/config`` and waits for the daemon's
   SessionStatus (state "active") on ``pd/p<k>/<session>/status``;
5. every step, sends the samples that are due (stamped with their sample step) on
   ``pd/p<k>/<session>/sensor/<name>`` and a Command for step now + lead on
   ``pd/p<k>/<session>/cmd``;
   at a few steps it sends a duplicate, a late and a future sample on purpose;
6. prints every Prediction and ErrorReport it receives, and everything it sent, one JSON
   object per line; exits after ``--steps`` steps.

Usage::

    python examples/raw_client.py --connect tcp/127.0.0.1:7447 --session raw --steps 80
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import sys
import threading
import time

import msgpack
import zenoh

# --- the scenario ------------------------------------------------------------------------

D = 0.05  # the model's step, s (the session may run on any wall-clock period)
A = [[1, D, 0, 0], [0, 1, 0, 0], [0, 0, 1, D], [0, 0, 0, 1]]
B = [[0.0], [D], [0.0], [0.0]]
Q = [[0, 0, 0, 0], [0, 0.01**2, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0.01**2]]
CAMERA_H, CAMERA_STD, CAMERA_DELAY, CAMERA_INTERVAL = [[1, 0, 0, 0], [0, 0, 1, 0]], 0.5, 10, 2
RANGER_H, RANGER_STD, RANGER_DELAY = [[-1, 0, 1, 0]], 0.1, 12
LEAD, MAX_DELAY = 10, 16


def array(rows: list[list[float]] | list[float]) -> dict[str, list]:
    """The wire's array map: ``{"shape": [...], "data": [row-major float64 values]}``."""
    if rows and isinstance(rows[0], list):
        return {"shape": [len(rows), len(rows[0])],
                "data": [float(v) for row in rows for v in row]}  # type: ignore[union-attr]
    return {"shape": [len(rows)], "data": [float(v) for v in rows]}  # type: ignore[arg-type]


def session_spec(session: str, period_ns: int, epoch_ns: int) -> dict:
    """The paper's SessionSpec, every field written out (protocol.md section 4)."""
    return {
        "v": 1, "session": session, "period_ns": period_ns, "epoch_ns": epoch_ns,
        "model": {"kind": "linear", "A": array(A), "B": array(B), "Q": array(Q)},
        "x0": array([0.0, 0.0, 0.0, 0.0]),
        "P0": array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 30, 0], [0, 0, 0, 1]]),
        "sensors": [
            {"name": "camera", "H": array(CAMERA_H), "R": array([[0.25, 0], [0, 0.25]]),
             "delay": CAMERA_DELAY, "interval": CAMERA_INTERVAL},
            {"name": "ranger", "H": array(RANGER_H), "R": array([[0.01]]),
             "delay": RANGER_DELAY, "interval": 1},
        ],
        "lead": LEAD, "max_delay": MAX_DELAY, "publish_every": 1, "command_hold": "hold",
    }


def command_at(step: int) -> float:
    """The operator's acceleration: 0.5 for 0 < step <= 80, else 0."""
    return 0.5 if 0 < step <= 80 else 0.0


def mat_vec(m: list[list[float]], x: list[float]) -> list[float]:
    return [sum(a * b for a, b in zip(row, x, strict=True)) for row in m]


# --- keys (key layout 2) -------------------------------------------------------------------

def fnv1a32(data: bytes) -> int:
    """32-bit FNV-1a: h = 2166136261; per byte: h = ((h XOR byte) * 16777619) mod 2^32."""
    h = 2166136261
    for b in data:
        h = ((h ^ b) * 16777619) & 0xFFFFFFFF
    return h


def session_prefix(session: str) -> str:
    """``pd/p<k>/<session>``: k = FNV-1a-32(name) mod P, P the deployment's partition count
    (``PD_PARTITIONS``, default 64; every party must use the same)."""
    partitions = int(os.environ.get("PD_PARTITIONS") or 64)
    return f"pd/p{fnv1a32(session.encode()) % partitions}/{session}"


# --- the client ----------------------------------------------------------------------------

class Client:
    def __init__(self, endpoint: str, session: str, timeout_s: float) -> None:
        conf = {"mode": "client", "connect": {"endpoints": [endpoint]},
                "scouting": {"multicast": {"enabled": False}}}
        # a client's open fails while nothing listens on the endpoint: retry until timeout
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.z = zenoh.open(zenoh.Config.from_json5(json.dumps(conf)))
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise SystemExit(f"raw_client: nothing answers on {endpoint}") from None
                time.sleep(0.2)
        self.session = session
        self.prefix = session_prefix(session)
        self.out_lock = threading.Lock()
        self.active = threading.Event()
        self.seq = 0
        self.subs = [
            self.z.declare_subscriber(f"{self.prefix}/prediction", self._on("prediction")),
            self.z.declare_subscriber(f"{self.prefix}/error", self._on("error")),
            self.z.declare_subscriber(f"{self.prefix}/status", self._on("status")),
        ]

    def emit(self, record: dict) -> None:
        with self.out_lock:
            print(json.dumps(record), flush=True)

    def _on(self, what: str):
        def callback(sample: zenoh.Sample) -> None:
            msg = msgpack.unpackb(sample.payload.to_bytes(), raw=False)
            if msg.get("v") != 1:  # a newer protocol: say so, never guess
                self.emit({"got": "unknown_version", "key": str(sample.key_expr)})
                return
            self.emit({"got": what, "key": str(sample.key_expr), "msg": msg})
            if what == "status" and msg.get("state") == "active":
                self.active.set()
        return callback

    def wait_ready(self, timeout_s: float) -> str:
        """The first daemon instance whose liveliness token ``pd/@service/<instance>`` is up."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for reply in self.z.liveliness().get("pd/@service/*", timeout=1.0):
                if reply.ok is not None:
                    return str(reply.ok.key_expr).rsplit("/", 1)[-1]
            time.sleep(0.1)
        raise SystemExit("raw_client: no pd-service instance is up")

    def put(self, key: str, msg: dict, kind: str, step: int | None = None) -> None:
        self.z.put(key, msgpack.packb(msg, use_bin_type=True))
        self.emit({"sent": kind, "key": key, "msg": msg, "at_step": step})

    def next_seq(self) -> int:
        self.seq += 1
        return self.seq

    def measurement(self, sensor: str, z: list[float], at: int, *, step: int | None = None,
                    t_ns: int | None = None) -> None:
        msg = {"v": 1, "session": self.session, "sensor": sensor, "seq": self.next_seq(),
               "step": step, "t_ns": t_ns, "z": array(z), "R": None}
        self.put(f"{self.prefix}/sensor/{sensor}", msg, "measurement", at)

    def command(self, apply_step: int, u: float, at: int) -> None:
        msg = {"v": 1, "session": self.session, "seq": self.next_seq(), "step": apply_step,
               "issued_ns": None, "u": array([u])}
        self.put(f"{self.prefix}/cmd", msg, "command", at)

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()
        self.z.close()


def run(args: argparse.Namespace) -> int:
    c = Client(args.connect, args.session, args.ready_timeout)
    try:
        instance = c.wait_ready(args.ready_timeout)
        c.emit({"ready": instance})
        period_ns = int(args.period_ms * 1e6)
        # the epoch a little ahead: nothing is published before it, so the first steps of
        # the spec's handshake cannot race the first samples
        epoch_ns = (time.time_ns() // period_ns + 25) * period_ns
        spec = session_spec(args.session, period_ns, epoch_ns)
        c.put(f"{c.prefix}/config", spec, "spec")
        if not c.active.wait(args.ready_timeout):
            raise SystemExit("raw_client: the daemon did not answer the SessionSpec")
        rng = random.Random(args.seed)
        x = [0.0, 0.0, 5.0, 0.5]  # the true state
        pending: list[tuple[int, str, int, list[float]]] = []  # (send step, sensor, step, z)
        for k in range(args.steps + 1):
            if k % CAMERA_INTERVAL == 0:
                z = [v + rng.gauss(0.0, CAMERA_STD) for v in mat_vec(CAMERA_H, x)]
                pending.append((k + CAMERA_DELAY, "camera", k, z))
            if abs(x[2] - x[0]) <= 3.0:
                z = [v + rng.gauss(0.0, RANGER_STD) for v in mat_vec(RANGER_H, x)]
                pending.append((k + RANGER_DELAY, "ranger", k, z))
            # pace on the shared clock: a tenth into step k
            wait_s = (epoch_ns + k * period_ns + period_ns // 10 - time.time_ns()) / 1e9
            if wait_s > 0:
                time.sleep(wait_s)
            for item in [p for p in pending if p[0] <= k]:
                pending.remove(item)
                c.measurement(item[1], item[3], k, step=item[2])
                if k == args.steps // 2 and item[1] == "camera":  # a duplicate, on purpose
                    c.measurement("camera", [v + 1.0 for v in item[3]], k, step=item[2])
            if k == args.steps // 2 + 1:  # a late and a future sample, on purpose
                c.measurement("ranger", [1.0], k, step=max(0, k - MAX_DELAY - 5))
                c.measurement("ranger", [1.0], k, t_ns=epoch_ns + (k + 5) * period_ns)
            c.command(k + LEAD, command_at(k + LEAD), k)
            # the truth moves on: x(k+1) = A x(k) + B u(k) + w, w ~ N(0, Q)
            u, ax = command_at(k), mat_vec(A, x)
            x = [ax[i] + B[i][0] * u + (rng.gauss(0.0, math.sqrt(Q[i][i])) if Q[i][i] else 0.0)
                 for i in range(4)]
        time.sleep(max(0.5, 5 * args.period_ms / 1000))  # the last predictions and reports
        c.emit({"done": args.steps})
        return 0
    finally:
        c.close()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the daemon's endpoint")
    p.add_argument("--session", default="raw")
    p.add_argument("--steps", type=int, default=80)
    p.add_argument("--period-ms", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--ready-timeout", type=float, default=20.0)
    return run(p.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
