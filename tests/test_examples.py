"""Every script in examples/ runs from a fresh interpreter, outside the checkout's folder,
and prints what its docstring promises (the numbers come from the shipped excerpts)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCRIPTS = sorted(EXAMPLES.glob("*.py"))
#: A line each script's output must contain.
EXPECT = {
    "gnss_spp.py": "G11 +20 m",
    "locate_wifi_rtt.py": "rms_impr_pct",
    "selfcal_then_locate.py": "self-calibrated  RMS",
}


def test_every_example_is_listed():
    assert {p.name for p in SCRIPTS} == set(EXPECT)


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_example_runs(script, tmp_path):
    res = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    assert EXPECT[script.name] in res.stdout
    assert "Traceback" not in res.stderr
