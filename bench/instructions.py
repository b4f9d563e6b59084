#!/usr/bin/env python3
"""The worker's instructions per session-step, counted by valgrind (callgrind): a figure that
does not move with the machine's speed, for comparing two builds and for the profile.

The CPU-time benchmarks swing by up to 2x from hour to hour on the shared 2-core machine
(bench/gauge.py), which hides any change smaller than that. Instructions executed do not
depend on the machine's load: the same build gives the same count, to a few tenths of a
percent (allocation addresses and the garbage collector's timing move it slightly).

How: ``bench/worker.py`` (N paper sessions on an InMemoryBus, the load of bench/service.py
step by step) runs under ``valgrind --tool=callgrind``, counting only inside
``ServiceCore.run_once`` (the worker's whole loop: dispatch, decode, estimator, predict,
encode, put to the in-memory bus). It runs twice, with two step counts; the difference of the
two counts divided by N x (difference of steps) is the cost of one session-step in steady
state: session creation and the warm-up (where the window fills and samples stamped before
the epoch are refused) cancel out. The same difference per function gives the profile:
inclusive instructions per session-step of the worker's main functions.

Not counted: Zenoh (its threads, the put), the GIL hand-offs, the disk, the load generator.
Instructions are not time (a cache miss costs more than an add); bench/service.py and
bench/worker.py measure time. Needs valgrind (Debian: ``apt-get install valgrind``) and the
compiled build (``make venv``): the count is taken in the compiled ``run_once``.

Usage: python bench/instructions.py [--sessions 100] [--steps 10,30] [--compare DIR] [--top 30]
                                   [--keep DIR] [--epochs shared|distinct] [--checkpoints]
                                   [--every 20] [--stamps step|t_ns]
  --checkpoints   the sessions are checkpointed as in the daemon (bench/worker.py
                  --checkpoints: every simulated second); counted are the worker's export and
                  encoding, not the writer thread's file writes
  --compare DIR   a second checkout (e.g. a ``git worktree`` of the baseline, built with
                  ``setup.py build_ext --inplace``): both builds side by side, with the ratio
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: The function callgrind counts in (its C name in the mypyc build).
RUN_ONCE = "CPyDef_core___ServiceCore___run_once"
_LINE = re.compile(r"^\s*([\d,]+) \([\s\d.]+%\)\s+(?:\S*?:)?([A-Za-z_][\w.']*)(?: \[.*\])?\s*$")
#: Functions shown in the profile besides the compiled ones (CPyDef_*): the libraries and the
#: interpreter the worker calls into.
_LIBRARY = {
    "__pyx_pw_7msgpack_9_cmsgpack_3unpackb": "msgpack.unpackb",
    "__pyx_pw_7msgpack_9_cmsgpack_6Packer_7pack": "msgpack Packer.pack",
    "advance_impl": "_kalman.c step",
    "apply_packets": "_kalman.c update",
    "jump_impl": "_kalman.c jump",
    "gc_collect_main": "garbage collector",
    "PyArray_NewFromDescr_int": "numpy array creation",
    "ufunc_generic_fastcall": "numpy ufuncs",
}


def status(root: Path) -> str:
    """pd_service.native.STATUS of the build in ``root``."""
    out = subprocess.run(
        [sys.executable, "-c", "import pd_service.native as n; print(n.STATUS)"],
        cwd=root, env={**os.environ, "PYTHONPATH": str(root)}, capture_output=True,
        text=True, check=True)
    return out.stdout.strip()


def counts(root: Path, sessions: int, steps: int, out_dir: Path, epochs: str,
           extra: list[str]) -> tuple[int, dict[str, int]]:
    """Instructions inside run_once for one run of this checkout's bench/worker.py on the
    pd_service of ``root``: the total and the inclusive count per function."""
    out = out_dir / f"callgrind.{steps}.out"
    cmd = ["valgrind", "--tool=callgrind", f"--toggle-collect={RUN_ONCE}",
           f"--callgrind-out-file={out}", sys.executable, str(HERE / "worker.py"),
           "--sessions", str(sessions), "--steps", str(steps), "--epochs", epochs,
           "--no-gauge", *extra]
    env = {**os.environ, "PYTHONPATH": str(root), "PYTHONHASHSEED": "0",
           "OPENBLAS_NUM_THREADS": "1"}
    run = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
    if run.returncode != 0:
        sys.exit(f"valgrind failed in {root} (exit {run.returncode}):\n{run.stderr[-2000:]}")
    total = re.search(r"Collected : (\d+)", run.stderr)
    if total is None:
        sys.exit(f"no 'Collected' line from callgrind in {root}:\n{run.stderr[-2000:]}")
    ann = subprocess.run(["callgrind_annotate", "--inclusive=yes", "--threshold=100", str(out)],
                         capture_output=True, text=True, check=True).stdout
    per: dict[str, int] = {}
    for line in ann.splitlines():
        m = _LINE.match(line)
        if m:
            name = m.group(2).split("'")[0]  # f'2: a recursive call's second level
            per[name] = max(per.get(name, 0), int(m.group(1).replace(",", "")))
    return int(total.group(1)), per


def measure(root: Path, sessions: int, steps: tuple[int, int], keep: str, epochs: str,
            extra: list[str]) -> tuple[float, dict[str, float]]:
    """Instructions per session-step in steady state, in all of run_once and per function.
    ``keep``: a directory to leave callgrind's files in (else a temporary one)."""
    with tempfile.TemporaryDirectory(prefix="pd-instr-") as tmp:
        out_dir = Path(keep) / root.name if keep else Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        runs = []
        for s in steps:
            print(f"  {root}: {sessions} sessions, {s} steps under callgrind ...",
                  file=sys.stderr, flush=True)
            runs.append(counts(root, sessions, s, out_dir, epochs, extra))
    (t_a, f_a), (t_b, f_b) = runs
    div = sessions * (steps[1] - steps[0])
    per_fn = {k: (f_b[k] - f_a.get(k, 0)) / div for k in f_b}
    return (t_b - t_a) / div, per_fn


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--sessions", type=int, default=100)
    ap.add_argument("--steps", default="10,30", help="two step counts, e.g. 10,30")
    ap.add_argument("--compare", default="", help="second checkout, built")
    ap.add_argument("--top", type=int, default=30, help="rows of the profile")
    ap.add_argument("--epochs", choices=("shared", "distinct"), default="shared",
                    help="bench/worker.py's sessions share one epoch or have one each")
    ap.add_argument("--keep", default="", metavar="DIR",
                    help="leave callgrind's files in DIR/<checkout name>/ (read them with "
                         "callgrind_annotate --inclusive=yes --tree=calling)")
    ap.add_argument("--checkpoints", action="store_true",
                    help="checkpoint every simulated second, as the daemon does")
    ap.add_argument("--every", type=int, default=20,
                    help="bench/worker.py --every: the worker runs after every this many "
                         "sessions' messages (smaller: more rounds, each with fewer sessions)")
    ap.add_argument("--stamps", choices=("step", "t_ns"), default="step",
                    help="bench/worker.py --stamps: measurements stamped with a step or in ns")
    args = ap.parse_args()
    extra = ((["--checkpoints"] if args.checkpoints else []) + ["--every", str(args.every)]
             + ["--stamps", args.stamps])
    if shutil.which("valgrind") is None or shutil.which("callgrind_annotate") is None:
        sys.exit("valgrind is not installed (Debian: apt-get install valgrind)")
    steps_a, steps_b = (int(v) for v in args.steps.split(","))
    if not 0 < steps_a < steps_b:
        sys.exit("--steps: two step counts a,b with 0 < a < b")
    roots = [HERE.parent] + ([Path(args.compare).resolve()] if args.compare else [])
    results = []
    for root in roots:
        st = status(root)
        if not st.startswith("compiled"):
            sys.exit(f"{root}: the build is not compiled ({st}); run `make venv` (or "
                     "`setup.py build_ext --inplace` in a worktree)")
        total, per_fn = measure(root, args.sessions, (steps_a, steps_b), args.keep,
                                args.epochs, extra)
        results.append((root, st, total, per_fn))

    print(f"\nworker instructions per session-step ({args.sessions} sessions, {args.epochs} "
          f"epochs, {'checkpoints every second, ' if args.checkpoints else ''}"
          f"a round every {args.every} sessions, {args.stamps} stamps, "
          f"steps {steps_b} minus {steps_a}; inside ServiceCore.run_once)")
    head = "| function | " + " | ".join(str(r[0]) for r in results)
    print(head + (" | ratio |" if len(results) == 2 else " |"))
    print("|---" * (len(results) + 1 + (len(results) == 2)) + "|")

    def row(label: str, values: list[float]) -> None:
        cells = " | ".join(f"{v:,.0f}" for v in values)
        ratio = f" | {values[1] / values[0]:.2f} |" if len(values) == 2 and values[0] else " |"
        print(f"| {label} | {cells}{ratio}")

    row("**run_once (all)**", [r[2] for r in results])
    base = results[0][3]
    names = sorted((k for k in base if k.startswith("CPyDef_") or k in _LIBRARY),
                   key=lambda k: -base[k])
    for k in [k for k in names if k != RUN_ONCE][: args.top]:
        label = _LIBRARY.get(k, k.removeprefix("CPyDef_").replace("___", "."))
        row(label, [r[3].get(k, 0.0) for r in results])
    print(json.dumps({"bench": "instructions", "sessions": args.sessions, "epochs": args.epochs,
                      "checkpoints": args.checkpoints, "every": args.every,
                      "stamps": args.stamps,
                      "steps": [steps_a, steps_b],
                      "builds": [{"root": str(r[0]), "status": r[1],
                                  "instructions_per_session_step": round(r[2])}
                                 for r in results]}))


if __name__ == "__main__":
    main()
