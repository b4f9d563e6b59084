"""``pd-link``: run the link emulator.

    pd-link --config deploy/link-paper.toml                       # peer, connects to the daemon
    pd-link --config link.toml --connect tcp/127.0.0.1:7447 --instance lab --seed 3
    pd-link --config link.toml --zenoh-config zenoh.json5

The Zenoh flags are the shared group (:mod:`pd_service.transport.options`, role ``LINK``):
without ``--zenoh-config``, peer mode, multicast scouting off, listening on
``tcp/127.0.0.1:0`` (loopback only) and connecting to ``tcp/127.0.0.1:7447`` (where the
pd-service daemon listens by default), each unless its flag is given.
Exit codes: 0 after SIGINT/SIGTERM, 2 for a bad command line or configuration, 1 if Zenoh
cannot be opened.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from dataclasses import replace

from pd_service.cli import (
    EXIT_NO_ZENOH,
    add_metrics_arg,
    open_zenoh,
    stop_on_signals,
    wait_serving_metrics,
)
from pd_service.errors import ConfigError
from pd_service.logs import add_logging_args, level_of, setup_logging
from pd_service.transport.base import DEFAULT_SENDER_CACHE
from pd_service.transport.options import LINK, add_zenoh_args, options_from_args
from pd_service.wire import keys

from .config import load_config
from .model import loss_theory

log = logging.getLogger("pd_service.link")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pd-link",
        description="netem-style link emulator between robot-side and operator-side Zenoh keys",
    )
    p.add_argument("--config", required=True, help="rules file (.toml or .json)")
    p.add_argument("--instance", default="default",
                   help="instance name for pd/@link/<instance>/{rules,stats}")
    p.add_argument("--seed", type=int, default=None, help="override the config file's seed")
    p.add_argument("--spin-us", type=int, default=100,
                   help="busy-wait this long before a release while releases are sparse")
    p.add_argument("--switch-interval-us", type=int, default=1000,
                   help="Python thread switch interval (the timer thread waits at most this "
                        "for the GIL); 0 keeps Python's default of 5000")
    p.add_argument("--cache", type=int, default=0, metavar="N",
                   help="samples each output publisher of a key the service reads (sensors, "
                        "commands) keeps for a restarted service to read back (e.g. "
                        f"{DEFAULT_SENDER_CACHE}); 0: none (default: none: each cached key "
                        "declares a queryable and a token, which made 20,000 churned keys "
                        "stall the other streams for seconds, bench/link_flood.py)")
    p.add_argument("--express", action=argparse.BooleanOptionalAction, default=False,
                   help="publish with Zenoh's express flag (no batching; about twice the CPU "
                        "at high rates, no latency gain measured on loopback)")
    p.add_argument("--stats-interval", type=float, default=10.0, metavar="S",
                   help="log per-rule statistics every S seconds (default 10)")
    add_metrics_arg(p)
    add_zenoh_args(p, LINK)
    add_logging_args(p)
    return p  # fmt: skip


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(level_of(args) or "INFO", args.log_format)
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

    from .relay import LinkRelay, link_metrics

    stop = stop_on_signals(log)
    try:
        conf = options_from_args(args).config(LINK)
    except Exception as e:
        log.error("bad Zenoh configuration", extra={"fields": {"error": str(e)}})
        return 2
    transport = open_zenoh(conf, log)
    if transport is None:
        return EXIT_NO_ZENOH
    with transport:
        relay = LinkRelay(transport, config, args.instance, spin_ns=args.spin_us * 1000,
                          stats_interval_s=args.stats_interval,
                          express=args.express, cache=max(0, args.cache))  # fmt: skip
        relay.start()
        try:
            code = wait_serving_metrics(stop, args.metrics, lambda: link_metrics(relay), log)
        finally:
            relay.close()
            log.info("pd-link stopped", extra={"fields": {"instance": args.instance}})
    return code


if __name__ == "__main__":
    sys.exit(main())
