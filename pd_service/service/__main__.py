"""``pd-service`` / ``python -m pd_service``: run the predictive-display daemon.

Examples::

    pd-service                                   # peer on tcp/127.0.0.1:7447, no router needed
    pd-service --connect tcp/10.0.0.2:7447       # join a zenohd router (or other peers)
    pd-service --zenoh-config deploy/zenoh/client.json5 --instance pd-a --shard 0/2
    pd-service --print-config                    # show the effective settings and exit
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any

from pd_service.errors import ConfigError
from pd_service.logs import add_logging_args, setup_logging
from pd_service.transport.options import DAEMON, add_zenoh_args, error_text

from .config import Settings, load_settings


def _field_help(name: str) -> str:
    """A flag's help: the setting's description and its default, both read from
    :class:`Settings` (so the help cannot drift from what the daemon applies)."""
    field = Settings.model_fields[name]
    default = field.get_default(call_default_factory=False)
    shown = "none" if default is None else default
    text = f"{(field.description or '').rstrip('.')} (default {shown})"
    return text.replace("%", "%%")  # argparse formats help with %


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="pd-service",
        description="Predictive-display daemon: one observer-predictor per session over Zenoh. "
                    "Settings: defaults < --config file (TOML/JSON) < PD_SERVICE_* env < flags.")
    p.add_argument("--config", metavar="FILE", help="settings file (.toml, else JSON)")
    p.add_argument("--instance", help="instance id (default pd-<hostname>)")
    p.add_argument("--state-dir", dest="state_dir", metavar="DIR",
                   help="where session specs are persisted (default "
                        "$XDG_STATE_HOME/pd-service/<instance>, else "
                        "~/.local/state/pd-service/<instance>)")
    add_zenoh_args(p, DAEMON)
    s = p.add_argument_group("sessions")
    s.add_argument("--shard", metavar="I/N", help=_field_help("shard"))
    s.add_argument("--expire-s", dest="expire_s", type=float, metavar="S",
                   help=_field_help("expire_s"))
    s.add_argument("--peer", dest="peers", action="append", metavar="INSTANCE",
                   help="an instance to share sessions with (repeatable; default: none, "
                        "standalone)")
    s.add_argument("--tick-phase", dest="tick_phase", type=float, metavar="F",
                   help=_field_help("tick_phase"))
    s.add_argument("--inbox-size", dest="inbox_size", type=int, metavar="N",
                   help=_field_help("inbox_size"))
    s.add_argument("--batch-budget", dest="batch_budget", type=int, metavar="N",
                   help=_field_help("batch_budget"))
    s.add_argument("--error-rate", dest="error_rate", type=float, metavar="R",
                   help=_field_help("error_rate"))
    p.add_argument("--metrics", metavar="HOST:PORT", help=_field_help("metrics"))
    add_logging_args(p, default_level=None,
                     default_shown="INFO, or the settings file's / $PD_SERVICE_LOG_LEVEL")
    p.add_argument("--print-config", action="store_true", help="print the settings and exit")
    return p


def settings_from_args(argv: Sequence[str] | None = None) -> tuple[Settings, bool]:
    args = build_parser().parse_args(argv)
    flags = {k: v for k, v in vars(args).items()
             if k not in ("config", "print_config", "verbose")}
    if args.verbose:
        flags["log_level"] = "DEBUG"
    return load_settings(flags, config_file=args.config), args.print_config


def settings_in_force(settings: Settings) -> dict[str, Any]:
    """The settings as JSON values, with the defaults the daemon applies filled in: the Zenoh
    mode, listen / connect endpoints and multicast of the DAEMON role (left as given when a
    --zenoh-config file decides them) and the state directory; the password masked."""
    shown = settings.model_dump(mode="json")
    z = settings.zenoh.resolved(DAEMON)
    if z.config_file is None:
        shown.update(mode=z.mode, listen=list(z.listen), connect=list(z.connect),
                     multicast=z.multicast)
    shown["state_dir"] = str(settings.effective_state_dir)
    if shown.get("password"):
        shown["password"] = "***"
    return shown


def main(argv: Sequence[str] | None = None) -> int:
    try:
        settings, print_only = settings_from_args(argv)
    except ConfigError as exc:
        print(f"pd-service: {exc}", file=sys.stderr)
        return 2
    if print_only:
        print(json.dumps(settings_in_force(settings), indent=2))
        return 0
    setup_logging(settings.log_level, settings.log_format)
    from .daemon import Daemon  # imports zenoh: only when actually running

    try:
        return Daemon(settings).run_forever()
    except KeyboardInterrupt:  # pragma: no cover - signal handler normally catches it
        return 0
    except Exception as exc:
        print(f"pd-service: {type(exc).__name__}: {error_text(exc)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
