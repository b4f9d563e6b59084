#!/usr/bin/env python3
"""Health check of a pd-service container: exit status 0 when healthy, 1 when not.

    healthcheck.py --zenoh-config /etc/pd-service/zenoh/service.json5 \\
                   --query pd/@service/pd-a/status            # the daemon answers
    healthcheck.py --zenoh-config /etc/pd-service/zenoh/link.json5 \\
                   --query pd/@link/paper/stats               # the link emulator answers
    healthcheck.py --zenoh-config /etc/pd-service/zenoh/robot.json5   # router + login only

It opens a Zenoh session with the role's own configuration file, which checks that the
router is reachable and accepts the role's user/password.  With ``--query`` it also asks that
selector through the router and needs at least one good reply within ``--timeout`` seconds:
that checks that the process itself is alive and reachable under the router's access control
(the role's user must be allowed to query the key; see deploy/zenoh/router.json5).

One line goes to stdout (``healthy: ...`` or ``unhealthy: ...``), which ``docker inspect``
shows in the container's health log.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="healthcheck.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--zenoh-config", required=True, metavar="FILE",
                   help="the role's Zenoh client configuration (JSON5)")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="override the file's connect endpoints (repeatable)")
    p.add_argument("--query", metavar="SELECTOR",
                   help="also query this selector and require a good reply")
    p.add_argument("--timeout", type=float, default=5.0,
                   help="seconds for connecting and for the query (default 5)")
    return p


def check(zenoh_config_file: str, query: str | None, timeout: float,
          connect: Sequence[str] = ()) -> tuple[bool, str]:
    """(healthy, reason).  Never raises for an unhealthy target: the reason says why."""
    from pd_service.transport import ZenohTransport, zenoh_config

    try:
        conf = zenoh_config(file=zenoh_config_file, connect=list(connect))
        # do not wait for the router longer than the health check may take (ms)
        conf.insert_json5("connect/timeout_ms", json.dumps(int(timeout * 1000)))
    except Exception as exc:
        return False, f"bad Zenoh configuration {zenoh_config_file}: {exc}"
    try:
        transport = ZenohTransport(conf)
    except Exception as exc:
        return False, f"cannot open a Zenoh session (router down or login refused): {exc}"
    with transport:
        if query is None:
            return True, "router reachable, login accepted"
        try:
            replies = transport.get(query, timeout=timeout)
        except Exception as exc:
            return False, f"query {query} failed: {exc}"
        good = [r for r in replies if r.ok]
        if not good:
            return False, f"no good reply to {query} within {timeout:g} s ({len(replies)} errors)"
        return True, f"{len(good)} reply(ies) to {query}"


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if not args.timeout > 0:
        print("unhealthy: --timeout must be > 0")
        return 1
    ok, reason = check(args.zenoh_config, args.query, args.timeout, args.connect or ())
    print(("healthy: " if ok else "unhealthy: ") + reason)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
