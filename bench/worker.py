#!/usr/bin/env python3
"""The daemon's worker alone: N paper sessions in a ServiceCore on an InMemoryBus (no Zenoh,
no threads, no checkpoints), fed the load of bench/service.py step by step on a simulated
clock; prints the worker's CPU per session-step (process time, message building included),
and per step of all sessions (median, p95, max): work that falls due in the same step for
every session (snapshots, checkpoints) shows as a busiest step far above the median.

What bench/service.py measures minus Zenoh, the callbacks' GIL hand-offs and the disk: the
floor of the per-session-step cost of the Python worker.

With --checkpoints the sessions are checkpointed as in the daemon (every second of the
simulated clock, written by the writer thread to a temporary state dir).

With --epochs distinct every session has an epoch of its own (session i's is i ns later
than session 0's: the same steps, but no two sessions share a tick deadline, as in a fleet
whose robots were configured at different times); by default they share one.

With --stamps t_ns the measurements carry their sample time (``t_ns``, the step's start)
instead of a step number: the path of a robot that stamps in ns (the learned delays of
pd_service.service.robot_time are fed only by such stamps).

Usage: python bench/worker.py [--sessions 200] [--steps 100] [--checkpoints] [--profile]
                              [--epochs shared|distinct] [--stamps step|t_ns]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import shutil
import tempfile
import time

import msgpack
import numpy as np
from gauge import gauge_ms

from pd_service.scenarios.paper import RANGER_DELAY, paper_scenario, simulate_paper
from pd_service.service.config import Settings
from pd_service.service.core import ServiceCore
from pd_service.service.daemon import tune_gc
from pd_service.service.handover.checkpoint_writer import CheckpointWriter
from pd_service.service.spec_store import SpecStore
from pd_service.transport import InMemoryBus
from pd_service.transport.base import Sample
from pd_service.wire import encode, keys

PERIOD_NS = 50_000_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", type=int, default=200)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--every", type=int, default=20,
                    help="the worker runs after every this many sessions' messages (the "
                         "daemon's batches are as large as what arrived meanwhile)")
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--checkpoints", action="store_true",
                    help="checkpoint every simulated second, as the daemon does")
    ap.add_argument("--epochs", choices=("shared", "distinct"), default="shared",
                    help="one epoch for all sessions, or one each (i ns apart)")
    ap.add_argument("--stamps", choices=("step", "t_ns"), default="step",
                    help="measurements stamped with a step number or a time in ns")
    ap.add_argument("--no-gauge", dest="gauge", action="store_false",
                    help="skip the machine gauge (bench/instructions.py runs this under "
                         "valgrind, where it costs a minute and means nothing)")
    args = ap.parse_args()
    n = args.sessions
    every = args.every
    clock = [10**18]
    t = InMemoryBus().transport()
    settings = Settings(instance="w", cpu_budget=1000, config_rate_total=1e6,
                        config_burst_total=10**6, memory_budget_bytes=8 * 2**30,
                        max_sessions=10**5,
                        checkpoint_interval_s=1.0 if args.checkpoints else 0)
    store = SpecStore(tempfile.mkdtemp(prefix="pd-worker-")) if args.checkpoints else None
    core = ServiceCore(t, settings, now_ns=lambda: clock[0], mono_ns=lambda: clock[0],
                       store=store)
    if store is not None:
        core.keeper.writer = CheckpointWriter(store)
    core.start()
    tune_gc()  # as the daemon does after its start
    epoch = clock[0]
    names = [f"w{i:05d}" for i in range(n)]
    d = core.dispatch

    def sample(key: str, payload: bytes) -> Sample:
        return Sample(key, payload, "put", clock[0], clock[0])

    # distinct: i ns apart, far less than session i's send offset in the step (below), so
    # every session's step numbers stay those of the shared epoch
    specs = [encode(paper_scenario().spec(s, epoch + (i if args.epochs == "distinct" else 0),
                                          max_delay=RANGER_DELAY))
             for i, s in enumerate(names)]
    c0 = time.process_time()
    for s, spec_bytes in zip(names, specs, strict=True):
        d.on_config_sample(sample(keys.config_key(s), spec_bytes))
        core.run_once()
    print(f"creation: {1e3 * (time.process_time() - c0) / n:.2f} ms of CPU per session "
          "(decode, admission, estimator, status answer; no state dir)")
    run = simulate_paper(400, np.random.default_rng(1))
    cam = {smp.step: smp.z.tolist() for smp in run.samples if smp.sensor == "camera"}
    x = run.truth
    pack = msgpack.Packer(use_bin_type=True).pack

    def stamp(j: int) -> tuple[str, int]:
        """A measurement's stamp for step ``j``: the step or its start in ns."""
        return ("step", j) if args.stamps == "step" else ("t_ns", epoch + j * PERIOD_NS)

    def step(k: int) -> None:
        """Session i sends at phase 0.9 i / n of step k; the worker runs every --every
        sessions."""
        r = k % 400
        z_r = [float(x[r, 2] - x[r, 0])]
        z_c = cam.get((k - 10) % 400) if (k - 10) % 2 == 0 else None
        u = [0.5 if 0 < (k + 10) % 400 <= 80 else 0.0]
        for i, s in enumerate(names):
            clock[0] = epoch + k * PERIOD_NS + (PERIOD_NS * 9 // 10) * i // n
            d.on_command_sample(sample(keys.command_key(s), pack(
                {"v": 1, "session": s, "seq": k, "step": k + 10, "u": {"shape": [1], "data": u}})))
            d.on_sensor_sample(sample(keys.sensor_key(s, "ranger"), pack(
                {"v": 1, "session": s, "sensor": "ranger", "seq": k, stamp(k - 12)[0]:
                 stamp(k - 12)[1], "z": {"shape": [1], "data": z_r}})))
            if z_c is not None:
                d.on_sensor_sample(sample(keys.sensor_key(s, "camera"), pack(
                    {"v": 1, "session": s, "sensor": "camera", "seq": k, stamp(k - 10)[0]:
                     stamp(k - 10)[1], "z": {"shape": [2], "data": z_c}})))
            if i % every == every - 1:
                core.run_once()
        clock[0] = epoch + k * PERIOD_NS + PERIOD_NS * 96 // 100
        core.run_once()

    for k in range(20):  # warm-up: the window fills
        step(k)
    pub0 = core.counters["published"]
    prof = cProfile.Profile() if args.profile else None
    t0 = time.process_time()
    per_step = []  # the worker's CPU in each step (s): a step's work is due in that step
    if prof:
        prof.enable()
    for k in range(20, 20 + args.steps):
        t_k = time.process_time()
        step(k)
        per_step.append(time.process_time() - t_k)
    if prof:
        prof.disable()
    cpu = time.process_time() - t0
    pubs = (core.counters["published"] - pub0) / (n * args.steps)
    print(f"sessions {n}, steps {args.steps}, worker every {every} sessions: "
          f"{1e6 * cpu / (n * args.steps):.1f} µs of CPU per session-step, "
          f"{pubs:.2f} predictions per session-step, "
          f"late {core.counters['late_total']}")
    ps = sorted(per_step)
    if args.gauge:
        print(f"machine gauge: {gauge_ms():.1f} ms (bench/gauge.py: the same build's figures "
              "scale with it)")
    print(f"CPU per step (ms, all sessions): median {1e3 * ps[len(ps) // 2]:.1f}, "
          f"p95 {1e3 * ps[int(0.95 * (len(ps) - 1))]:.1f}, max {1e3 * ps[-1]:.1f}, "
          f"max / median {ps[-1] / ps[len(ps) // 2]:.2f} (a step's work must fit in its "
          f"{PERIOD_NS / 1e6:.0f} ms)")
    if store is not None:
        core.keeper.close()
        shutil.rmtree(store.dir, ignore_errors=True)
    if prof:
        st = pstats.Stats(prof)
        st.sort_stats("tottime").print_stats(25)
        st.sort_stats("cumulative").print_stats(30)


if __name__ == "__main__":
    main()
