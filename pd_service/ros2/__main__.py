"""``pd-ros2`` / ``python -m pd_service.ros2``: run the ROS 2 bridge (docs/ros2.md).

    pd-ros2                                        # client of tcp/127.0.0.1:7447, domain 0
    pd-ros2 --connect tcp/127.0.0.1:7447 --domain-id 3 --namespace /robot1
    pd-ros2 --key-format bridge_ros2dds --session s1 --session s2

The Zenoh flags are the shared group (:mod:`pd_service.transport.options`, role ``TOOL``):
without ``--zenoh-config``, client mode connecting to ``tcp/127.0.0.1:7447`` (the daemon's
default endpoint, and rmw_zenohd's port), multicast scouting off.
Exit codes: 0 after SIGINT/SIGTERM, 2 for a bad command line or setting, 1 if Zenoh cannot be
opened.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

from pd_service.cli import (
    EXIT_NO_ZENOH,
    add_metrics_arg,
    open_zenoh,
    stop_on_signals,
    wait_serving_metrics,
)
from pd_service.errors import ConfigError
from pd_service.logs import add_logging_args, level_of, setup_logging
from pd_service.transport.options import (
    TOOL,
    add_connect_wait_arg,
    add_zenoh_args,
    options_from_args,
)

if TYPE_CHECKING:
    from .bridge import BridgeSettings

log = logging.getLogger("pd_service.ros2")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pd-ros2",
        description="Bridge between ROS 2 topics (rmw_zenoh or zenoh-bridge-ros2dds keys, CDR) "
                    "and pd-service sessions whose spec has ros2 bindings")
    r = p.add_argument_group("ROS 2")
    r.add_argument("--domain-id", dest="domain_id", type=int, default=None,
                   help="ROS domain id (default $ROS_DOMAIN_ID, else 0)")
    r.add_argument("--namespace", default="/",
                   help="ROS namespace of the node; relative topics resolve under it (default /)")
    r.add_argument("--key-format", dest="key_format", choices=("rmw_zenoh", "bridge_ros2dds"),
                   default="rmw_zenoh",
                   help="rmw_zenoh (ROS 2 Jazzy on rmw_zenoh_cpp, default) or bridge_ros2dds "
                        "(DDS robots behind zenoh-bridge-ros2dds)")
    r.add_argument("--node-name", dest="node_name", default="pd_service",
                   help="ROS node name announced in the graph (default pd_service)")
    r.add_argument("--attachment-layout", dest="attachment_layout",
                   choices=("positional", "keyed"), default="positional",
                   help="rmw_zenoh attachment written on outputs: positional (Jazzy >= 0.2.4, "
                        "default) or keyed (0.2.0..0.2.3); both are read")
    p.add_argument("--session", action="append", metavar="NAME",
                   help="bridge only this session (repeatable; default every session whose "
                        "spec has ros2 bindings)")
    p.add_argument("--instance", default="default",
                   help="instance name for pd/@ros2/<instance>/status (default 'default')")
    p.add_argument("--role", choices=("operator", "robot"), default="operator",
                   help="operator (default): bridge ROS topics and native keys; robot: run "
                        "beside the robot, echo each command as applied on arrival and answer "
                        "clock probes, on the robot's clock (docs/ros2.md)")
    p.add_argument("--echo-via-link", dest="echo_via_link", action="store_true",
                   help="robot role: echo on robot/p<k>/<s>/echo for pd-link to carry down")
    add_metrics_arg(p)
    add_zenoh_args(p, TOOL)
    add_connect_wait_arg(p)
    add_logging_args(p)
    return p


def settings_from_args(args: argparse.Namespace) -> BridgeSettings:
    """The bridge settings of a parsed command line; raises ConfigError."""
    from .bridge import BridgeSettings
    from .keys import domain_id

    return BridgeSettings(domain_id=domain_id(args.domain_id), namespace=args.namespace,
                          key_format=args.key_format, node_name=args.node_name,
                          sessions=frozenset(args.session) if args.session else None,
                          instance=args.instance, attachment_layout=args.attachment_layout,
                          role=args.role, echo_via_link=args.echo_via_link)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(level_of(args) or "INFO", args.log_format)
    try:
        from .bridge import Ros2Bridge, bridge_metrics
    except ImportError as exc:  # rosbags / xxhash: the ros2 extra
        log.error("pd-ros2 needs the ros2 extra: pip install 'pd-service[ros2]'",
                  extra={"fields": {"error": str(exc)}})
        return 2
    try:
        settings = settings_from_args(args)
        conf = options_from_args(args).config(TOOL)
    except (ConfigError, ValueError, OSError) as exc:
        log.error("bad configuration", extra={"fields": {"error": str(exc)}})
        return 2

    stop = stop_on_signals(log)
    transport = open_zenoh(conf, log, args.connect_wait, stop)
    if transport is None:
        return EXIT_NO_ZENOH
    with transport:
        bridge = Ros2Bridge(transport, settings)
        bridge.start()
        try:
            code = wait_serving_metrics(stop, args.metrics, lambda: bridge_metrics(bridge), log)
        finally:
            bridge.close()
            log.info("pd-ros2 stopped", extra={"fields": {"instance": settings.instance}})
    return code


if __name__ == "__main__":
    sys.exit(main())
