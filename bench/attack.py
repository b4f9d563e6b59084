"""The attack suite: each attack against a real daemon process on loopback, beside an innocent
20 Hz paper session whose predictions are checked against an offline filter.

    .venv/bin/python bench/attack.py                    # every attack, ~2-3 min
    .venv/bin/python bench/attack.py --only spec_flood,idle_2000 --duration 6

Setup, all on loopback: this process is a Zenoh peer listening on a free port; one daemon
(``python -m pd_service``, default settings unless the row says otherwise, its own state
directory) is started per attack and connects to it; the attacker is a separate process
(this file with ``--attacker NAME``) connected to both, so its traffic does not share this
process's interpreter with the innocent session's feed.

The innocent session: the paper scenario (camera + ranger, 10 % loss, the operator's
commands), 50 ms steps, max_delay 60, published on its schedule by this process. Each of its
predictions is checked against :class:`ObserverPredictor` fed the prefix of what was sent
that the prediction's counters say was accepted (one publisher, one link: in order); a
prediction whose counters show a refusal is not checkable.

Per attack: inputs the attacker sent, crashes (daemon exited or did not come up), innocent
predictions per second and the longest gap between two of them (receive times, ms) over the
attack window, checkable predictions exact (and how many), the daemon's RSS growth (VmRSS,
MB, peak during the attack minus before it) and CPU (utime + stime from /proc, % of one
core over the attack window). A final JSON line holds everything.

Bounded loops only; every attack runs ``--duration`` seconds (the idle one longer: its
sessions must first go idle).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pd_service.estimation import ObserverPredictor  # noqa: E402
from pd_service.scenarios.paper import (  # noqa: E402
    paper_command,
    paper_model,
    paper_prior,
    paper_sensors,
    simulate_paper,
)
from pd_service.transport import ZenohTransport, zenoh_config  # noqa: E402
from pd_service.wire import (  # noqa: E402
    LinearModelSpec,
    Prediction,
    SensorSpec,
    SessionSpec,
    encode,
    keys,
)
from tests.service.helpers import (  # noqa: E402
    Collector,
    cmd_bytes,
    meas_bytes,
    paper_spec,
    storm,
)
from tests.service.procs import (  # noqa: E402
    Daemon,
    Presence,
    endpoint,
    free_port,
    query_service_status,
)

PERIOD = 50_000_000  # the innocent session: 20 Hz
MAX_DELAY = 60
INNOCENT = "innocent"
WARMUP_S = 1.5
TAIL_S = 0.5
CLK = os.sysconf("SC_CLK_TCK")

#: Settings raised through the environment for the 2,000-idle-sessions row (the defaults
#: admit 2,000 specs at 20 config changes/s: 100 s; and their nominal CPU exceeds cpu_budget).
IDLE_ENV = {"PD_SERVICE_MAX_SESSIONS": "5000", "PD_SERVICE_CONFIG_RATE_TOTAL": "100000",
            "PD_SERVICE_CONFIG_BURST_TOTAL": "100000", "PD_SERVICE_CPU_BUDGET": "1000",
            "PD_SERVICE_MEMORY_BUDGET_BYTES": str(16 * 2**30)}


# ================================================================== the innocent session ==

class Innocent:
    """The paper run as timed publications, plus what was sent (for the offline check)."""

    def __init__(self, epoch: int, steps: int, seed: int = 11) -> None:
        self.spec = paper_spec(INNOCENT, epoch_ns=epoch, period_ns=PERIOD, max_delay=MAX_DELAY)
        run = simulate_paper(steps, np.random.default_rng(seed), loss=0.1)
        self.schedule: list[tuple[int, str, bytes]] = []
        self.meas: list[tuple[str, int, np.ndarray]] = []
        self.cmds: list[tuple[int, float]] = []
        arrivals: dict[int, list] = {}
        for smp in run.samples:
            if smp.arrival is not None and smp.arrival < steps:
                arrivals.setdefault(smp.arrival, []).append(smp)
        seq = 0
        for k in range(steps):
            t = epoch + k * PERIOD + PERIOD // 10
            j = k + self.spec.lead
            self.schedule.append((t, keys.command_key(INNOCENT),
                                  cmd_bytes(INNOCENT, j, paper_command(j), k)))
            self.cmds.append((j, paper_command(j)))
            for smp in arrivals.get(k, []):
                seq += 1
                self.schedule.append((t, keys.sensor_key(INNOCENT, smp.sensor),
                                      meas_bytes(INNOCENT, smp.sensor, smp.step, smp.z, seq)))
                self.meas.append((smp.sensor, smp.step, smp.z))

    def publish(self, t: ZenohTransport, stop: threading.Event) -> None:
        for when, key, data in self.schedule:
            dt = (when - time.time_ns()) / 1e9
            if dt > 0 and stop.wait(dt):
                return
            t.put(key, data)

    def check(self, preds: list[Prediction]) -> tuple[int, int, int]:
        """(checked, exact, not checkable): each prediction against the offline filter."""
        x0, P0 = paper_prior()
        op = ObserverPredictor(paper_model(), paper_sensors(), x0=x0, P0=P0,
                               lead=self.spec.lead, max_delay=self.spec.max_delay)
        mi = ci = checked = exact = skipped = 0
        for p in sorted(preds, key=lambda p: p.seq):
            now = p.step - self.spec.lead
            c = p.counters
            if c.get("refused", 0) or c["accepted"] > len(self.meas) \
                    or c.get("commands_accepted", 0) > len(self.cmds):
                skipped += 1
                continue
            try:
                while ci < c.get("commands_accepted", 0):
                    j, u = self.cmds[ci]
                    op.add_command(j, np.array([u]), now=now)
                    ci += 1
                while mi < c["accepted"]:
                    sensor, s, z = self.meas[mi]
                    op.add_measurement(sensor, s, z, now=now)
                    mi += 1
                exp = op.predict(now)
            except ValueError:  # e.g. now went backwards: out of order, not checkable
                skipped += 1
                continue
            checked += 1
            if p.newest_step == exp.newest_step and np.allclose(p.x, exp.x, 1e-9, 1e-12) \
                    and np.allclose(p.P, exp.P, 1e-9, 1e-12):
                exact += 1
        return checked, exact, skipped


# ================================================================== /proc ================

def rss_mb(pid: int) -> float:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def cpu_s(pid: int) -> float:
    """utime + stime of the whole process (every thread), seconds."""
    try:
        f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(f[11]) + int(f[12])) / CLK
    except OSError:
        return float("nan")


# ================================================================== attackers =============
# Each runs in its own process, connected to this process and to the daemon; returns the
# number of inputs it sent. Bounded loops; ``deadline`` is a time.monotonic() value.

def big_linear_spec(session: str, seed: int) -> SessionSpec:
    n = 64
    rng = np.random.default_rng(seed)
    return SessionSpec(
        session=session, period_ns=PERIOD, epoch_ns=time.time_ns(),
        model=LinearModelSpec(A=np.eye(n), B=np.eye(n),
                              Q=np.diag(1e-3 + rng.random(n) * 1e-3)),
        x0=np.zeros(n), P0=np.eye(n),
        sensors=[SensorSpec(name="s", R=np.eye(n), delay=0, interval=1, H=np.eye(n))],
        lead=10_000, max_delay=1_000)


def atk_big_spec(t: ZenohTransport, deadline: float) -> int:
    for i in range(4):
        t.put(keys.config_key(f"big{i}"), encode(big_linear_spec(f"big{i}", i)))
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return 4


def atk_spec_flood(t: ZenohTransport, deadline: float) -> int:
    """Its own spec replaced ~750 times/s (each a different max_delay)."""
    n = 0
    base = paper_spec("evil", epoch_ns=time.time_ns())
    specs = [encode(base.model_copy(update={"max_delay": 12 + i})) for i in range(50)]
    t0 = time.monotonic()
    while time.monotonic() < deadline and n < 20_000:
        t.put(keys.config_key("evil"), specs[n % 50])
        n += 1
        ahead = n / 750.0 - (time.monotonic() - t0)
        if ahead > 0:
            time.sleep(ahead)
    return n


def atk_idle(t: ZenohTransport, deadline: float) -> int:
    epoch = time.time_ns()
    for i in range(2000):
        t.put(keys.config_key(f"idle{i:04d}"),
              encode(paper_spec(f"idle{i:04d}", epoch_ns=epoch, period_ns=PERIOD)))
        if i % 100 == 99:
            time.sleep(0.02)
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return 2000


def atk_unscented(t: ZenohTransport, deadline: float) -> int:
    from tests.service.test_nonlinear import omni_spec
    spec = omni_spec("ukf").model_copy(update={"lead": 1000, "period_ns": 1_000_000,
                                              "epoch_ns": time.time_ns()})
    t.put(keys.config_key("ukf"), encode(spec))
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return 1


def atk_huge(t: ZenohTransport, deadline: float) -> int:
    """u = 1e308 and z = 1e308 on its own session, 100 of each per second."""
    epoch = time.time_ns()
    t.put(keys.config_key("evil"), encode(paper_spec("evil", epoch_ns=epoch, max_delay=60)))
    time.sleep(0.3)
    n = 0
    while time.monotonic() < deadline and n < 5000:
        k = max(0, (time.time_ns() - epoch) // PERIOD)
        t.put(keys.sensor_key("evil", "ranger"), meas_bytes("evil", "ranger", k, [1e308], n))
        t.put(keys.command_key("evil"), cmd_bytes("evil", k + 5, [1e308], n))
        n += 2
        time.sleep(0.02)
    return n


def atk_read_only(t: ZenohTransport, deadline: float) -> int:
    """20 creates and 10 deletes on a daemon whose state directory it cannot write."""
    n = 0
    for i in range(20):
        t.put(keys.config_key(f"ro{i}"), encode(paper_spec(f"ro{i}", epoch_ns=time.time_ns())))
        n += 1
    time.sleep(0.5)
    for i in range(10):
        t.delete(keys.config_key(f"ro{i}"))
        n += 1
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return n


def atk_none(t: ZenohTransport, deadline: float) -> int:
    while time.monotonic() < deadline:
        time.sleep(0.05)
    return 0


def atk_status_storm(t: ZenohTransport, deadline: float) -> int:
    """Status queries from 4 threads, as fast as they are answered."""
    sels = [keys.status_key(INNOCENT), keys.ALL_STATUS, keys.service_status_key("atk"),
            keys.status_key("nobody")]
    count = [0]
    lock = threading.Lock()

    def run(i: int) -> None:
        while time.monotonic() < deadline:
            with lock:
                if count[0] >= 50_000:
                    return
                count[0] += 1
            try:
                t.get(sels[count[0] % len(sels)], timeout=1.0)
            except Exception:
                pass

    ths = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for th in ths:
        th.start()
    for th in ths:
        th.join()
    return count[0]


def atk_fake_tokens(t: ZenohTransport, deadline: float) -> int:
    toks = [t.declare_token(keys.service_token_key(f"fake{i}")) for i in range(10)]
    while time.monotonic() < deadline:
        time.sleep(0.05)
    for tok in toks:
        tok.close()
    return 10


def atk_hostile_bytes(t: ZenohTransport, deadline: float) -> int:
    """Random and malformed bytes on its own and unknown sessions' keys, and on the innocent
    session's config key (read-only to nobody on loopback without a router), ~5,000/s."""
    rng = np.random.default_rng(7)
    t.put(keys.config_key("evil"), encode(paper_spec("evil", epoch_ns=time.time_ns())))
    batch = storm("evil", rng) + storm("ghost", rng)
    batch += [(keys.config_key("evil"), rng.bytes(int(k))) for k in rng.integers(0, 300, 20)]
    batch += [(keys.sensor_key(f"u{i}", "s"), rng.bytes(20)) for i in range(50)]
    n = 0
    t0 = time.monotonic()
    while time.monotonic() < deadline and n < 200_000:
        key, data = batch[n % len(batch)]
        t.put(key, data)
        n += 1
        ahead = n / 5000.0 - (time.monotonic() - t0)
        if ahead > 0:
            time.sleep(ahead)
    return n


ATTACKS = {
    "baseline": (atk_none, "no attack: the innocent session alone"),
    "big_spec": (atk_big_spec, "4 x 25 KB linear spec (n=64, lead 10,000, max_delay 1,000), "
                               "distinct Q"),
    "spec_flood": (atk_spec_flood, "its own spec replaced 750 times/s"),
    "idle_2000": (atk_idle, "2,000 idle sessions (1 KB specs; budgets raised by env)"),
    "unscented_1ms": (atk_unscented, "unscented spec, lead 1,000 at a 1 ms period"),
    "huge_values": (atk_huge, "u = 1e308 and z = 1e308, 100/s"),
    "read_only_dir": (atk_read_only, "state dir read-only: 20 creates, 10 deletes"),
    "fifo_symlink": (atk_none, "FIFO, symlink to /dev/zero, FIFO .ckpt and checkpoints.log "
                               "in the state dir at startup"),
    "status_storm": (atk_status_storm, "status queries from 4 threads, flat out"),
    "fake_tokens": (atk_fake_tokens, "10 fake pd/@service/* tokens (standalone daemon)"),
    "hostile_bytes": (atk_hostile_bytes, "malformed / random bytes, 5,000/s"),
}


def attacker_main(name: str, connect: list[str], duration: float) -> None:
    t = ZenohTransport(zenoh_config(mode="peer", connect=connect, multicast=False))
    time.sleep(0.5)  # routes declared
    fn = ATTACKS[name][0]
    n = fn(t, time.monotonic() + duration)
    print(json.dumps({"inputs": n}), flush=True)
    t.close()


# ================================================================== one attack ===========

def run_attack(name: str, duration: float, workdir: Path) -> dict:
    port = free_port()
    main_ep = endpoint(port)
    t = ZenohTransport(zenoh_config(mode="peer", listen=[main_ep], multicast=False))
    col = Collector().attach(t)
    pres = Presence(t)
    state = workdir / name / "state"
    state.mkdir(parents=True)
    env_before = dict(os.environ)
    extra_dur = 0.0
    user_prefix: list[str] = []
    if name == "idle_2000":
        os.environ.update(IDLE_ENV)
        extra_dur = 12.0  # creation, idle_after_s (5 s), then the measured idle time
    if name == "fifo_symlink":
        os.mkfifo(state / "s1.msgpack")
        (state / "s2.msgpack").symlink_to("/dev/zero")
        os.mkfifo(state / "s3.ckpt")
        os.mkfifo(state / "checkpoints.log")
    if name == "read_only_dir" and os.geteuid() == 0:
        # root writes anywhere: run this daemon as nobody over a root-owned 0755 directory
        user_prefix = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
        os.chmod(workdir, 0o755)
        os.chmod(workdir / name, 0o777)  # its log file
        os.chmod(state, 0o755)
    elif name == "read_only_dir":
        os.chmod(state, 0o555)
    d = Daemon("atk", state, [main_ep])
    if user_prefix:
        d.log_path = workdir / name / "atk.log"
    d.start() if not user_prefix else _start_as(d, user_prefix)
    os.environ.clear()
    os.environ.update(env_before)
    row: dict = {"attack": name, "what": ATTACKS[name][1]}
    up = pres.wait("atk", timeout=30)
    assert d.proc is not None
    pid = d.proc.pid
    if not up:
        row.update(crashes=1, detail="daemon did not come up within 30 s "
                                     f"(exit code {d.proc.poll()})")
        d.stop(timeout=5)
        t.close()
        return row
    total_s = WARMUP_S + duration + extra_dur + TAIL_S + 0.5
    steps = int(total_s * 1e9 / PERIOD) + 1
    epoch = time.time_ns() + 300_000_000
    inn = Innocent(epoch, steps)
    t.put(keys.config_key(INNOCENT), encode(inn.spec))
    col.wait_for(lambda c: len(c.statuses[INNOCENT]) > 0, timeout=5)
    recv: list[tuple[float, int]] = []
    col_lock = threading.Lock()

    def on_pred(sample) -> None:
        with col_lock:
            recv.append((time.monotonic(), len(sample.payload)))

    t.subscribe(keys.prediction_key(INNOCENT), on_pred)
    stop = threading.Event()
    feeder = threading.Thread(target=inn.publish, args=(t, stop), daemon=True)
    feeder.start()
    time.sleep(0.3 + WARMUP_S)
    rss0, cpu0, t0 = rss_mb(pid), cpu_s(pid), time.monotonic()
    atk_dur = duration + extra_dur
    atk = subprocess.Popen([sys.executable, __file__, "--attacker", name, "--connect", main_ep,
                            "--connect", d.endpoint, "--duration", str(atk_dur)],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    peak = rss0
    idle_cpu = None
    t_idle = t0 + atk_dur - 6.0  # the last 6 s of the idle row: every session idle
    cpu_idle0 = None
    while atk.poll() is None and time.monotonic() < t0 + atk_dur + 15:
        time.sleep(0.1)
        peak = max(peak, rss_mb(pid))
        if name == "idle_2000" and cpu_idle0 is None and time.monotonic() >= t_idle:
            cpu_idle0, t_idle = cpu_s(pid), time.monotonic()
    if atk.poll() is None:
        atk.kill()
    out = (atk.stdout.read() if atk.stdout else "").strip().splitlines()
    t1, cpu1 = time.monotonic(), cpu_s(pid)
    if cpu_idle0 is not None:
        idle_cpu = 100.0 * (cpu1 - cpu_idle0) / (t1 - t_idle)
    time.sleep(TAIL_S)
    stop.set()
    feeder.join(5)
    alive = d.proc.poll() is None
    st = query_service_status(t, "atk") if alive else None
    with col_lock:
        window = [r for r, _ in recv if t0 <= r <= t1]
    gaps = np.diff([t0] + window + [t1]) * 1e3 if window else np.array([(t1 - t0) * 1e3])
    with col.cond:
        preds = list(col.predictions[INNOCENT])
    checked, exact, skipped = inn.check(preds)
    inputs = json.loads(out[-1])["inputs"] if out else -1
    counters = st.counters if st is not None else {}
    row.update(
        inputs=inputs, crashes=0 if alive else 1,
        pred_per_s=len(window) / (t1 - t0), longest_gap_ms=float(gaps.max()),
        checked=checked, exact=exact, not_checkable=skipped,
        all_exact=checked > 0 and exact == checked,
        rss_growth_mb=peak - rss0, rss_mb=peak, cpu_pct=100.0 * (cpu1 - cpu0) / (t1 - t0),
        refused={k: v for k, v in counters.items() if k in REFUSAL_COUNTERS and v},
        sessions_served=counters.get("sessions_served"),
    )
    if idle_cpu is not None:
        row["idle_cpu_pct"] = idle_cpu
    if name == "read_only_dir":
        details = [s.detail for n, ss in col.statuses.items() if n.startswith("ro") for s in ss]
        row["answers_not_persisted"] = sum("NOT" in x for x in details)
        row["answers"] = len(details)
    rc = d.stop(timeout=10)
    row["exit_code"] = rc
    if rc not in (0, None):
        row["crashes"] = 1
    t.close()
    return row


REFUSAL_COUNTERS = {"refused", "admission_refused", "config_rate_limited", "config_refused",
                    "out_of_range", "commands_out_of_range", "malformed", "commands_malformed",
                    "unknown_session", "untrusted_peer", "persist_failed", "state_dir_unhealthy",
                    "recovered", "internal_error", "flood", "unknown_flood", "bad_key",
                    "key_mismatch", "non_finite", "wrong_dims", "unknown_sensor"}


def _start_as(d: Daemon, prefix: list[str]) -> None:
    args = prefix + [sys.executable, "-m", "pd_service", "--instance", d.instance,
                     "--state-dir", str(d.state_dir), "--listen", d.endpoint]
    for ep in d.connect:
        args += ["--connect", ep]
    env = dict(os.environ, PYTHONUNBUFFERED="1", HOME=str(d.state_dir.parent))
    env.pop("PD_SERVICE_CONFIG", None)
    d._log = open(d.log_path, "ab")  # type: ignore[attr-defined]
    d.proc = subprocess.Popen(args, stdout=d._log, stderr=d._log, env=env,  # type: ignore[attr-defined]
                              cwd=str(ROOT))


# ================================================================== main =================

def table(rows: list[dict]) -> str:
    head = ("| attack | inputs | crashes | innocent pred/s | longest gap ms | exact (checked) "
            "| RSS growth MB | CPU % core |")
    lines = [head, "|" + "---|" * 8]
    for r in rows:
        if "pred_per_s" not in r:
            lines.append(f"| {r['attack']} | - | {r.get('crashes', 1)} | - | - | - | - | - |"
                         f" {r.get('detail', '')}")
            continue
        ex = f"{'yes' if r['all_exact'] else 'NO'} ({r['exact']}/{r['checked']})"
        lines.append(f"| {r['attack']} | {r['inputs']} | {r['crashes']} | "
                     f"{r['pred_per_s']:.1f} | {r['longest_gap_ms']:.0f} | {ex} | "
                     f"{r['rss_growth_mb']:.1f} | {r['cpu_pct']:.0f} |")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=6.0, help="seconds per attack")
    ap.add_argument("--only", default="", help="comma-separated attack names")
    ap.add_argument("--attacker", default="", help=argparse.SUPPRESS)
    ap.add_argument("--connect", action="append", default=[], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.attacker:
        attacker_main(args.attacker, args.connect, args.duration)
        return 0
    names = [n for n in args.only.split(",") if n] or list(ATTACKS)
    work = Path(tempfile.mkdtemp(prefix="pd-attack-"))
    rows = []
    try:
        for name in names:
            row = run_attack(name, args.duration, work)
            rows.append(row)
            print(json.dumps(row), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print()
    print(table(rows))
    ok = {r["attack"]: (r.get("crashes") == 0 and r.get("pred_per_s", 0) >= 18
                        and r.get("longest_gap_ms", 1e9) <= 250 and bool(r.get("all_exact"))
                        and r.get("rss_growth_mb", 1e9) <= 300) for r in rows}
    print(f"\n{os.cpu_count()} CPUs; bars: innocent >= 18 pred/s, no gap > 250 ms, every "
          "checkable prediction exact, RSS growth <= 300 MB, no crash")
    print(json.dumps({"rows": rows, "bars_hold": ok}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
