"""``python -m pd_service``: run the daemon (same as the ``pd-service`` command)."""

import sys

from pd_service.service.__main__ import main

if __name__ == "__main__":
    sys.exit(main())
