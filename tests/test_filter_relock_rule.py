"""``--max-rejected``'s two re-lock rules, as ``--help`` and the module docstring say them
(the filter review): the help said only "consecutive rejections before a link re-locks
(default 8)", while a young link re-locks as soon as its rejections in a row outnumber the
samples it has taken (on purpose: a fade at a link's first sample rejected the good ones
after it)."""

from __future__ import annotations

import numpy as np

from robustloc.cli import main
from robustloc.filters import rssi
from robustloc.filters.rssi import RobustRssiFilter


def _relocked_at(n_good: int, max_rejected: int = 8) -> list[int]:
    z = np.r_[np.full(n_good, -50.0), np.full(12, -70.0)]
    static = {"sigma_accel_mps2": 0.0, "init_speed_std_mps": 0.0}  # (filter --static)
    res = RobustRssiFilter(max_rejected=max_rejected, **static).filter_samples(
        np.zeros(z.size, dtype=np.int64), np.arange(z.size, dtype=float), z)
    return np.flatnonzero(res.relocked).tolist()


def test_a_young_link_relocks_when_its_rejections_outnumber_its_samples():
    # 3 samples taken, then the 4th rejection in a row re-locks (not the 8th)
    assert _relocked_at(3) == [3 + 3]
    # an older link waits for the 8th
    assert _relocked_at(20) == [20 + 7]
    assert _relocked_at(3, max_rejected=0) == []  # 0 disables both


def test_the_help_and_the_docstrings_state_the_young_link_rule(capsys):
    assert main(["filter", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "rejections in a row after which a link re-locks" in text
    assert ("a young link re-locks sooner, at the rejection that makes its rejections in a "
            "row outnumber the samples it has taken (weight > 0) since it started or "
            "restarted") in text, text
    for doc in (rssi.__doc__, RobustRssiFilter.__doc__):
        assert "outnumber the samples it has taken" in " ".join(doc.split())
