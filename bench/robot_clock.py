#!/usr/bin/env python3
"""Issue 43's acceptance run, simulated in process: a robot with its own clock (offset, drift,
a step change mid-run) that applies commands on arrival, over an emulated link with
asymmetric delays, jitter and loss, served by the daemon's core on the in-memory bus.

Every party runs on injected clocks driven by one event queue (no wall time, no sleeps): the
figures are the same on any machine, so this is a simulation, not a timing benchmark. The
link is emulated here (not by pd-link): per message a delay of ``base +- jitter`` (uniform)
and a loss draw; probes (the daemon's queries of the robot's clock) see the same delays, their
four timestamps handed to the core's probe queue directly (the in-memory query is
synchronous, so the link's delay cannot act on it).

Runs (each the same truth, noise and delays; ``--scenario`` paper by default):

- ``reference``: a perfect shared clock, a robot that holds each command to its apply step;
- ``today``: the robot's clock off, commands applied on arrival, the spec as before
  (``robot_clock: shared``, ``command_timing: stamped``);
- ``issue43``: the same robot, the spec with ``robot_clock: estimated`` and ``command_timing:
  echoed`` (probes once a second, echoes of every command);
- ``ref-loop``, ``loopback``: ``reference`` and ``issue43`` over a link of 100 +- 30 µs each
  way (the offset error figure);
- ``perfect``: ``issue43``'s robot and link with a shared clock (``robot_clock: shared``,
  ``command_timing: echoed``): what the uplink's jitter and the on-arrival robot cost when the
  clock is known exactly (the bound of ``issue43``'s RMS ratio: no clock estimate does better);
- ``asym``: ``issue43`` with the spec's ``clock_asymmetry_ns`` set to the link's nominal
  asymmetry (the fastest way up minus the fastest way down), which no timestamp shows.

Printed per run: samples refused as future / late after the first 5 s; the offset error
after 10 s (max and median |estimate - truth| at the once-a-second probes, leaving out the 5 s
after the step change) with the reported uncertainty; the samples put in at the latest
instant they may have been taken at (late only by how far the clock's estimate moved while
they flew, ``stamps_remapped``); when the step was detected (s after it;
the probe cadence, 1 s, bounds this reading); the prediction RMS (position, against the truth
at each predicted step, after 10 s; also leaving out the 5 s after the step change) and its
ratio to the reference on the same link; the learned max_delay, the smallest window W* that
refuses at most 0.1 % of the run's samples as late, their ratio, and the share the learned
one refuses. A final JSON line.

Usage: python bench/robot_clock.py [--scenario paper] [--seconds 60] [--offset-s 10]
       [--seed 1] [--step-s 0.2]
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "clients" / "python"))

from pd_client.robot import CommandSchedule  # noqa: E402
from pd_client.tools.robot_clock import RobotClock  # noqa: E402
from pd_service.estimation.delay_learning import LATE_SHARE  # noqa: E402
from pd_service.scenarios import ScenarioSim, get_scenario  # noqa: E402
from pd_service.service import ServiceCore, Settings, SpecStore  # noqa: E402
from pd_service.transport import InMemoryBus  # noqa: E402
from pd_service.wire import (  # noqa: E402
    Command,
    CommandEcho,
    Measurement,
    Prediction,
    SessionSpec,
    decode,
    encode,
    keys,
)

S = 1_000_000_000
EPOCH = 1_700_000_000 * S


@dataclass(frozen=True)
class Link:
    """One way's delay (s): base +- jitter (uniform), and a loss probability."""

    base_s: float
    jitter_s: float
    loss: float = 0.0

    def delay_ns(self, rng: np.random.Generator) -> int | None:
        if self.loss and rng.random() < self.loss:
            return None
        return round((self.base_s + rng.uniform(-self.jitter_s, self.jitter_s)) * S)


#: up 500 ms, down 600 ms (the camera's 500 ms as in the paper), +- 50 ms; the demo's loss
#: (another scenario's sensors: as the ranger)
FIELD = {"up": Link(0.5, 0.05), "echo": Link(0.6, 0.05, 0.02), "probe_down": Link(0.6, 0.05),
         "camera": Link(0.5, 0.05, 0.038), "ranger": Link(0.6, 0.05, 0.02)}
LOOPBACK = {k: Link(100e-6, 30e-6, v.loss) for k, v in FIELD.items()}


def nominal_asymmetry_ns(links: dict[str, Link], sensors: list[str]) -> int:
    """The link's fastest way up minus its fastest way down (the robot's stamps: its
    ``sensors``, echoes, probe answers), from the nominal delays less their jitter (ns)."""
    names = [*sensors, "echo", "probe_down"]
    down = min(links.get(n, links["ranger"]).base_s - links.get(n, links["ranger"]).jitter_s
               for n in names)
    return round((links["up"].base_s - links["up"].jitter_s - down) * S)


@dataclass
class Result:
    name: str
    future: int = 0
    late: int = 0
    offset_err_max_ms: float | None = None  # after 10 s, outside 5 s after the step
    offset_err_median_ms: float | None = None
    step_seen_after_s: float | None = None  # the step change's detection, s after it
    uncertainty_ms: float | None = None
    rms: float = float("nan")
    rms_outside_step: float = float("nan")  # leaving out the 5 s after the step change
    learned_max_delay: int | None = None
    smallest_window: int | None = None
    learned_late_share: float | None = None
    steps_detected: int = 0
    remapped: int = 0  # samples late only by the clock estimate's move: at their latest instant
    counters: dict[str, int] = field(default_factory=dict)


def run(name: str, scenario_name: str, seconds: float, offset_s: float, seed: int,
        clock_off: bool, hold: bool, estimated: bool, links: dict[str, Link],
        echoed: bool | None = None, asymmetry: bool = False, step_s: float = 0.2) -> Result:
    """One run (module docstring); ``echoed``: the spec's command_timing "echoed" (default:
    with an estimated clock); ``asymmetry``: the spec's clock_asymmetry_ns set to the link's
    nominal one (the fastest way up minus the fastest way down); ``step_s``: the robot
    clock's step mid-run (s)."""
    echoed = estimated if echoed is None else echoed
    sc = get_scenario(scenario_name)
    per_s = sc.period_s
    worst = max(v.base_s + v.jitter_s for v in FIELD.values())
    # the field link's delays set the window and the lead (the same spec on every link)
    spec0 = sc.spec("s1", EPOCH, lead=round(FIELD["up"].base_s / per_s),
                    max_delay=int(np.ceil(worst / per_s)) + 2)
    spec = SessionSpec.model_validate({**spec0.model_dump(),
                                       "robot_clock": "estimated" if estimated else "shared",
                                       "command_timing": "echoed" if echoed else "stamped",
                                       "clock_asymmetry_ns": nominal_asymmetry_ns(links, sc.sensor_names)
                                       if asymmetry else 0})
    P = spec.period_ns
    steps = int(seconds * S // P)
    robot_clock = (RobotClock(offset_s, 100.0, [(seconds / 2, step_s)], base=lambda: 0, t0_ns=EPOCH)
                   if clock_off else RobotClock(base=lambda: 0, t0_ns=EPOCH))
    rng = np.random.default_rng(seed + 1000)  # the link's draws (the same in every run)
    sim = ScenarioSim(sc, seed)
    now = [EPOCH - 1]
    bus = InMemoryBus()
    with tempfile.TemporaryDirectory() as tmp:
        # the nominal CPU budgets do not matter on simulated time (a 600 ms window of the
        # diff-drive UKF needs 0.27 of a core nominally)
        core = ServiceCore(bus.transport(), Settings(instance="bench", probe_interval_s=0,
                                                     expire_s=1e6, max_session_cpu=2.0,
                                                     cpu_budget=2.0),
                           store=SpecStore(Path(tmp) / "a"), now_ns=lambda: now[0],
                           run_clock_ns=lambda: 0, spawn=lambda fn: fn())
        core.start()
        op = bus.transport()
        preds: dict[int, np.ndarray] = {}
        op.subscribe(keys.prediction_key("s1"),
                     lambda smp: preds.__setitem__((p := decode(smp.payload, Prediction)).step,
                                                   p.x))
        op.put(keys.config_key("s1"), encode(spec))
        core.run_once()
        schedule = CommandSchedule(sc.nu)
        events: list[tuple[int, int, str, object]] = []
        n = [0]

        def push(t: int, kind: str, data: object) -> None:
            n[0] += 1
            heapq.heappush(events, (t, n[0], kind, data))

        for k in range(steps):
            push(EPOCH + k * P, "step", k)
            push(EPOCH + k * P + P // 10, "issue", k)
            push(EPOCH + k * P + P // 2, "tick", k)
        for j in range(int(seconds)):
            push(EPOCH + j * S + 3 * P // 10, "probe", j)
        truth: dict[int, np.ndarray] = {}
        # the robot that applies on arrival: step -> [(offset s, u)], and the u it holds
        arrived: dict[int, list[tuple[float, np.ndarray]]] = {}
        u_robot = np.zeros(sc.nu)
        flows = sc.nonlinear is not None and sc.nonlinear.flow is not None
        seq = dict.fromkeys(sc.sensor_names, 0)
        at5: dict[str, int] = {}
        offset_errs: list[float] = []
        uncertainty = None
        step_seen: float | None = None
        while events:
            t, _, kind, data = heapq.heappop(events)
            now[0] = t
            if kind == "step":
                k = int(data)  # type: ignore[call-overload]
                if k > 0 and hold:
                    sim.advance(schedule.u_at(k - 1))
                elif k > 0:  # on arrival: each command from its instant inside step k - 1
                    cuts = sorted(arrived.pop(k - 1, []), key=lambda c: c[0])
                    if flows:
                        sim.advance(u_robot, cuts)
                    u_robot = cuts[-1][1] if cuts else u_robot
                    if not flows:  # every cut at the step's start: the last one arrived
                        sim.advance(u_robot)
                truth[k] = sim.x.copy()
                for d in sim.sample():
                    dl = links.get(d.sensor, links["ranger"]).delay_ns(rng)  # others: 600 ms
                    if dl is not None:
                        m = Measurement(session="s1", sensor=d.sensor, seq=seq[d.sensor],
                                        t_ns=robot_clock.at(t), z=d.z)
                        push(t + dl, "meas", m)
                    seq[d.sensor] += 1
                if k == int(5 * S // P):
                    st = core.session_status("s1")
                    at5 = dict(st.counters) if st is not None else {}
                continue
            if kind == "issue":
                k = int(data)  # type: ignore[call-overload]
                u = np.asarray(sc.command(k + spec.lead), dtype=float).reshape(sc.nu)
                cmd = Command(session="s1", seq=k, issued_ns=t, u=u)
                op.put(keys.command_key("s1"), encode(cmd))
                up = links["up"].delay_ns(rng)
                if up is not None:
                    push(t + up, "arrive", cmd)
            elif kind == "arrive":
                assert isinstance(data, Command)
                if hold:
                    schedule.add(spec.step_of(data.issued_ns or 0) + spec.lead, data.u)
                else:
                    # applied on arrival: at that instant where the model flows over part of
                    # a step, else at the robot's next control tick (a discrete model)
                    j = spec.step_of(t)
                    at = t if flows else spec.time_of(j + 1)
                    ja = spec.step_of(at)
                    arrived.setdefault(ja, []).append(((at - spec.time_of(ja)) / S, data.u))
                    dn = links["echo"].delay_ns(rng)
                    if dn is not None:
                        push(at + dn, "echo", CommandEcho(session="s1", seq=data.seq,
                                                          applied_ns=robot_clock.at(at),
                                                          sent_ns=robot_clock.at(at)))
            elif kind == "meas":
                assert isinstance(data, Measurement)
                op.put(keys.sensor_key("s1", data.sensor), encode(data))
            elif kind == "echo":
                assert isinstance(data, CommandEcho)
                op.put(keys.echo_key("s1"), encode(data))
            elif kind == "probe":
                up, down = links["up"].delay_ns(rng), links["probe_down"].delay_ns(rng)
                if up is not None and down is not None and estimated:
                    t2 = robot_clock.at(t + up)
                    push(t + up + 20_000 + down, "answer", (t, t2, t2 + 20_000))
                st = core.session_status("s1") if estimated else None
                if st is not None and st.clock is not None and st.clock.known:
                    el = (t - EPOCH) / S
                    if st.clock.steps and step_seen is None and el >= seconds / 2:
                        step_seen = el - seconds / 2
                    if el >= 10 and not seconds / 2 <= el < seconds / 2 + 5:
                        offset_errs.append((st.clock.offset_ns - robot_clock.offset_ns(t)) / 1e6)
                        if st.clock.uncertainty_ns is not None:
                            uncertainty = st.clock.uncertainty_ns / 1e6
            elif kind == "answer":
                t1, t2, t3 = data  # type: ignore[misc]
                core.robot_io.answers.append(("s1", t1, t2, t3, t))
                core.wake.set()
            core.run_once()
        st = core.session_status("s1")
        assert st is not None
        c = dict(st.counters)
        res = Result(name, counters=c)
        res.future = c.get("future", 0) - at5.get("future", 0)
        res.late = c.get("late", 0) - at5.get("late", 0)
        res.remapped = c.get("stamps_remapped", 0) - at5.get("stamps_remapped", 0)
        if offset_errs:
            errs = np.abs(offset_errs)
            res.offset_err_max_ms = float(errs.max())
            res.offset_err_median_ms = float(np.median(errs))
            res.uncertainty_ms = uncertainty
        if st.clock is not None:
            res.steps_detected = st.clock.steps
        res.step_seen_after_s = step_seen
        pos = [i for i, nm in enumerate(sc.state_names) if nm in ("p1", "p2", "x", "y")]
        sq = {s: float(np.sum((x[pos] - truth[s][pos]) ** 2)) for s, x in preds.items()
              if s in truth and s * P >= 10 * S}
        res.rms = float(np.sqrt(np.mean(list(sq.values())))) if sq else float("nan")
        half = seconds / 2 * S
        out = [v for s, v in sq.items() if not half <= s * P < half + 5 * S]
        res.rms_outside_step = float(np.sqrt(np.mean(out))) if out else float("nan")
        route = core._routes.get("s1")  # noqa: SLF001 (the bench reads the learned window)
        if route is not None and route.sess is not None:
            samples = route.sess.robot.samples
            res.learned_max_delay = samples.recommended_window(LATE_SHARE)
            res.smallest_window = samples.smallest_window(LATE_SHARE)
            if res.learned_max_delay is not None:
                res.learned_late_share = samples.share_above(res.learned_max_delay)
        core.close()
    return res


def clock_cells(r: Any) -> tuple[str, str, str, str]:
    """A run's table cells (this bench's and bench/robot_clock_live.py's): offset error
    max / median (ms), reported uncertainty (ms), learned window / W*, share refused late (%)."""
    off = (f"{r.offset_err_max_ms:8.3f}/{r.offset_err_median_ms:<8.3f}"
           if r.offset_err_max_ms is not None and r.offset_err_median_ms is not None
           else f"{'-':>19}")
    unc = f"{r.uncertainty_ms:8.3f}" if r.uncertainty_ms is not None else f"{'-':>8}"
    ratio = (f"{r.learned_max_delay / r.smallest_window:5.2f}"
             if r.learned_max_delay and r.smallest_window else f"{'-':>5}")
    share = (f"{100 * r.learned_late_share:7.3f}" if r.learned_late_share is not None
             else f"{'-':>7}")
    return off, unc, ratio, share


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--offset-s", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--step-s", type=float, default=0.2, help="the robot clock's step mid-run")
    args = ap.parse_args()
    common = dict(scenario_name=args.scenario, seconds=args.seconds, offset_s=args.offset_s,
                  seed=args.seed, step_s=args.step_s)
    runs = [
        run("reference", clock_off=False, hold=True, estimated=False, links=FIELD, **common),
        run("today", clock_off=True, hold=False, estimated=False, links=FIELD, **common),
        run("issue43", clock_off=True, hold=False, estimated=True, links=FIELD, **common),
        run("ref-loop", clock_off=False, hold=True, estimated=False, links=LOOPBACK, **common),
        run("loopback", clock_off=True, hold=False, estimated=True, links=LOOPBACK, **common),
        run("perfect", clock_off=False, hold=False, estimated=False, echoed=True, links=FIELD,
            **common),
        run("asym", clock_off=True, hold=False, estimated=True, links=FIELD, asymmetry=True,
            **common),
    ]
    refs = {"reference": runs[0], "today": runs[0], "issue43": runs[0], "ref-loop": runs[3],
            "loopback": runs[3], "perfect": runs[0], "asym": runs[0]}
    print(f"scenario {args.scenario}, {args.seconds:g} s, robot clock {args.offset_s:+g} s, "
          f"100 ppm, {args.step_s * 1e3:+g} ms step at {args.seconds / 2:g} s; commands on "
          f"arrival (reference: "
          f"held to their step, shared clock); "
          f"PD_SERVICE_PURE={os.environ.get('PD_SERVICE_PURE', '')}")
    head = (f"{'run':<10} {'future':>7} {'late':>5} {'off.err max/med ms':>19} {'unc. ms':>8} "
            f"{'RMS':>8} {'/ref':>6} {'w/o step':>8} {'/ref':>6} {'learned W':>9} {'W*':>4} "
            f"{'W/W*':>5} {'late %':>7} {'steps':>5} {'seen s':>6} {'remap':>5}")
    print(head)
    for r in runs:
        off, unc, ratio, share = clock_cells(r)
        ref = refs[r.name]
        print(f"{r.name:<10} {r.future:>7} {r.late:>5} {off:>19} {unc} {r.rms:8.4f} "
              f"{r.rms / ref.rms:6.3f} {r.rms_outside_step:8.4f} "
              f"{r.rms_outside_step / ref.rms_outside_step:6.3f} {r.learned_max_delay!s:>9} "
              f"{r.smallest_window!s:>4} "
              f"{ratio} {share} {r.steps_detected:>5} "
              f"{'-' if r.step_seen_after_s is None else round(r.step_seen_after_s, 2)!s:>6} "
              f"{r.remapped:>5}")
    print(json.dumps({"scenario": args.scenario, "seconds": args.seconds,
                      "offset_s": args.offset_s, "seed": args.seed, "step_s": args.step_s,
                      "runs": {r.name: {k: v for k, v in r.__dict__.items() if k != "counters"}
                               for r in runs}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
