"""``python -m pd_client.tools <tool> [args]``: the command-line tools without installed scripts.

Tools: ``sim`` (pd-robot-sim), ``operator`` (pd-operator), ``display`` (pd-display),
``record`` (pd-record), ``viz`` (pd-viz), ``replay`` (pd-replay), ``web`` (pd-web),
``admin`` (pd-admin).
"""

from __future__ import annotations

import importlib
import sys

#: sub-command -> module of pd_client.tools with its ``main(argv)``
TOOLS = {"sim": "pd_robot_sim", "operator": "pd_operator", "display": "pd_display",
         "record": "pd_record", "viz": "pd_viz", "replay": "pd_replay",
         "web": "pd_web", "admin": "pd_admin"}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in TOOLS:
        print(f"usage: python -m pd_client.tools {{{','.join(TOOLS)}}} [args...]",
              file=sys.stderr)
        return 2
    module = importlib.import_module(f"pd_client.tools.{TOOLS[argv[0]]}")
    return int(module.main(argv[1:]))


if __name__ == "__main__":
    sys.exit(main())
