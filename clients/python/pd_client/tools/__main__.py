"""``python -m pd_client <tool> [args]``: the command-line tools without installed scripts.

Tools: ``sim`` (pd-robot-sim), ``operator`` (pd-operator), ``display`` (pd-display),
``record`` (pd-record).
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    tools = {"sim": "sim", "operator": "operate", "display": "watch", "record": "record"}
    if not argv or argv[0] not in tools:
        print(f"usage: python -m pd_client {{{','.join(tools)}}} [args...]", file=sys.stderr)
        return 2
    import importlib

    module = importlib.import_module(f"pd_client.{tools[argv[0]]}")
    return int(module.main(argv[1:]))


if __name__ == "__main__":
    sys.exit(main())
