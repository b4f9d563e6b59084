"""``pd-link``: run the link emulator.

    pd-link --config deploy/link-paper.toml                       # peer, connects to the daemon
    pd-link --config link.toml --connect tcp/127.0.0.1:7447 --instance lab --seed 3
    pd-link --config link.toml --zenoh-config zenoh.json5

Default Zenoh configuration (without ``--zenoh-config``): peer mode, multicast scouting off,
listening on ``tcp/127.0.0.1:0`` (loopback only), connecting to ``tcp/127.0.0.1:7447`` (where the
pd-service daemon listens by default) unless ``--connect``/``--listen`` are given.
Exit codes: 0 after SIGINT/SIGTERM, 2 for a bad command line or configuration, 1 if Zenoh
cannot be opened.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

from pd_service.wire import keys

from .config import ConfigError, load_config
from .model import loss_theory

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
DEFAULT_LISTEN = "tcp/127.0.0.1:0"

log = logging.getLogger("pd_service.link")


class LogfmtFormatter(logging.Formatter):
    """``ts=... level=INFO logger=... msg="..." key=value ...`` (fields from ``extra={"fields":
    {...}}``)."""

    def format(self, record: logging.LogRecord) -> str:
        parts = {
            "ts": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(record.created))
            + f".{int(record.msecs):03d}",
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        parts.update(getattr(record, "fields", {}) or {})
        text = " ".join(f"{k}={_logfmt_value(v)}" for k, v in parts.items())
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


class JsonFormatter(logging.Formatter):
    """One JSON object per line."""

    def format(self, record: logging.LogRecord) -> str:
        out: dict[str, Any] = {
            "ts": record.created,
            "level": record.levelname,
            "logger": record.name,
            "msg": record.getMessage(),
        }
        out.update(getattr(record, "fields", {}) or {})
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def _logfmt_value(v: Any) -> str:
    if isinstance(v, str) and v and not any(c in v for c in ' "=\n'):
        return v
    if isinstance(v, int | float | bool) or v is None:
        return json.dumps(v)
    return json.dumps(v if isinstance(v, str) else json.loads(json.dumps(v, default=str)),
                      separators=(",", ":"))  # fmt: skip


def setup_logging(level: str, fmt: str) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if fmt == "json" else LogfmtFormatter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pd-link",
        description="netem-style link emulator between robot-side and operator-side Zenoh keys",
    )
    p.add_argument("--config", required=True, help="rules file (.toml or .json)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help=f"Zenoh endpoint to connect to (repeatable; default {DEFAULT_CONNECT})")
    p.add_argument("--listen", action="append", metavar="ENDPOINT",
                   help=f"Zenoh endpoint to listen on (repeatable; default {DEFAULT_LISTEN})")
    p.add_argument("--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config file (then --connect/--listen are added to it)")
    p.add_argument("--mode", choices=("peer", "client"), default=None,
                   help="Zenoh mode (default: peer, or the config file's)")
    p.add_argument("--instance", default="default",
                   help="instance name for pd/@link/<instance>/{rules,stats}")
    p.add_argument("--seed", type=int, default=None, help="override the config file's seed")
    p.add_argument("--spin-us", type=int, default=100,
                   help="busy-wait this long before a release while releases are sparse")
    p.add_argument("--switch-interval-us", type=int, default=1000,
                   help="Python thread switch interval (the timer thread waits at most this "
                        "for the GIL); 0 keeps Python's default of 5000")
    p.add_argument("--express", action=argparse.BooleanOptionalAction, default=False,
                   help="publish with Zenoh's express flag (no batching; about twice the CPU "
                        "at high rates, no latency gain measured on loopback)")
    p.add_argument("--stats-interval", type=float, default=10.0, metavar="S",
                   help="log per-rule statistics every S seconds")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.add_argument("--log-format", default="text", choices=("text", "json"))
    return p  # fmt: skip


def zenoh_config(args: argparse.Namespace) -> Any:
    """Build the ``zenoh.Config`` from the command line (see the module docstring)."""
    import zenoh

    if args.zenoh_config:
        conf = zenoh.Config.from_file(args.zenoh_config)
    else:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(args.mode or "peer"))
        conf.insert_json5("scouting/multicast/enabled", "false")
        if not args.listen and (args.mode or "peer") == "peer":
            conf.insert_json5("listen/endpoints", json.dumps([DEFAULT_LISTEN]))
        if not args.connect and not args.listen:
            conf.insert_json5("connect/endpoints", json.dumps([DEFAULT_CONNECT]))
    if args.zenoh_config and args.mode:
        conf.insert_json5("mode", json.dumps(args.mode))
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    return conf


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, args.log_format)
    try:
        keys.check_name(args.instance, "instance")
        config = load_config(args.config)
    except (ConfigError, ValueError) as e:
        log.error("bad configuration", extra={"fields": {"error": str(e)}})
        return 2
    if args.seed is not None:
        config = replace(config, seed=args.seed)
    for rule in (*config.downlink, *config.uplink):
        if rule.params.loss is not None:
            rate, burst = loss_theory(rule.params.loss)
            log.info("loss model", extra={"fields": {
                "rule": rule.name, "expected_loss_rate": round(rate, 6),
                "expected_mean_burst": round(burst, 3)}})  # fmt: skip
    if args.switch_interval_us > 0:
        sys.setswitchinterval(args.switch_interval_us / 1e6)

    import zenoh

    from .relay import LinkRelay

    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal received, stopping", extra={"fields": {"signal": signum}})
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        conf = zenoh_config(args)
    except Exception as e:
        log.error("bad Zenoh configuration", extra={"fields": {"error": str(e)}})
        return 2
    try:
        session_cm = zenoh.open(conf)
    except Exception as e:
        log.error("cannot open Zenoh session", extra={"fields": {"error": str(e)}})
        return 1
    with session_cm as session:
        relay = LinkRelay(session, config, args.instance, spin_ns=args.spin_us * 1000,
                          stats_interval_s=args.stats_interval,
                          express=args.express)  # fmt: skip
        relay.start()
        try:
            while not stop.wait(timeout=0.5):
                pass
        finally:
            relay.close()
            log.info("pd-link stopped", extra={"fields": {"instance": args.instance}})
    return 0


if __name__ == "__main__":
    sys.exit(main())
