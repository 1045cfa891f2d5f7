"""``python -m robustloc``: the ``robustloc`` command (:func:`robustloc.cli.entry`), for an
environment whose scripts folder is not on ``PATH``."""

import sys

from robustloc.cli import entry

if __name__ == "__main__":  # pragma: no cover  (run as a process by the test)
    sys.exit(entry())
