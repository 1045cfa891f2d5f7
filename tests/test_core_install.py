"""The command line works on a core install (no [serve] or [dask] extras): every
command's --help and the command list, with the optional packages made unimportable.
(A core wheel once failed on `robustloc --help`: serve's options imported the ASGI app.)"""

from __future__ import annotations

import subprocess
import sys

import pytest

OPTIONAL = ("anyio", "starlette", "uvicorn", "paho", "httpx", "websockets", "dask",
            "distributed", "playwright")

BLOCK = f"""
import sys
class _Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {OPTIONAL!r}:
            raise ImportError('blocked optional package ' + name)
        return None
sys.meta_path.insert(0, _Block())
from robustloc.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.parametrize("command", ["", "locate", "track", "serve", "replay", "partition",
                                     "filter", "spp", "evaluate", "calibrate", "reproduce"])
def test_help_without_optional_extras(command):
    argv = [sys.executable, "-c", BLOCK] + ([command] if command else []) + ["--help"]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "usage: robustloc" in r.stdout
