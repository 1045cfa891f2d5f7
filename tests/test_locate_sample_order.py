"""``locate``'s first pass (the per-anchor noise scale of ``--robust-scale log``) takes
the same sample of epochs whatever the chunking and the epochs' order.

A log of more than ``2 LOG_SAMPLE_CAP`` epochs is sampled (step k > 1).  When more rows
share one time than a chunk holds, the streaming reader hands that time's epochs on in the
file's order; the sample used to be "every k-th epoch by position", so ``--chunk-rows`` or
the order of the tags within the time changed the sample, the scale, and thousands of
fixes (the input review, 2026-12-04: 24 805 of 25 000 x values).  Now epochs are sampled
by a hash of (time, tag) and the sample is taken in the order (time, tag).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.pipelines.locate import LOG_SAMPLE_CAP, epoch_hash, log_sample_step

ANCHORS = np.array([[0, 0], [20, 0], [0, 20], [20, 20], [10, 25]], dtype=float)
N_EPOCHS = 2 * LOG_SAMPLE_CAP + 2_000 + 100_000 // len(ANCHORS)  # > 100 000 rows at time 0


def _log(path: Path, order: np.ndarray) -> None:
    rng = np.random.default_rng(7)
    pos = rng.random((N_EPOCHS, 2)) * 20
    d = np.hypot(pos[:, None, 0] - ANCHORS[None, :, 0], pos[:, None, 1] - ANCHORS[None, :, 1])
    d += rng.normal(0, 0.1, d.shape) * (1 + rng.random(len(ANCHORS)))
    d += (rng.random(d.shape) < 0.05) * rng.uniform(2, 8, d.shape)  # 5 % long ranges
    tags = np.array([f"T{i:05d}" for i in range(N_EPOCHS)])
    i = np.repeat(order, len(ANCHORS))
    a = np.tile(np.arange(len(ANCHORS)), N_EPOCHS)
    pd.DataFrame({"time": 0.0, "tag": tags[i], "anchor": [f"A{k}" for k in a],
                  "range": np.round(d[i, a], 4)}).to_csv(path, index=False)


@pytest.fixture(scope="module")
def anchors(tmp_path_factory) -> Path:
    p = tmp_path_factory.mktemp("anc") / "anchors.csv"
    pd.DataFrame({"anchor": [f"A{k}" for k in range(len(ANCHORS))], "x": ANCHORS[:, 0],
                  "y": ANCHORS[:, 1]}).to_csv(p, index=False)
    return p


def _locate(log: Path, anchors: Path, out: Path, *extra: str) -> pd.DataFrame:
    assert main(["locate", str(log), "--anchors", str(anchors), "-o", str(out), "--quiet",
                 *extra]) == 0
    return pd.read_csv(out).sort_values("tag").reset_index(drop=True)


def test_fixes_do_not_depend_on_chunking_or_epoch_order(tmp_path, anchors):
    assert log_sample_step(N_EPOCHS) > 1  # the log is sampled
    rng = np.random.default_rng(3)
    one, other = tmp_path / "one.csv", tmp_path / "other.csv"
    _log(one, rng.permutation(N_EPOCHS))
    _log(other, rng.permutation(N_EPOCHS))  # the same epochs, the tags in another order
    ref = _locate(one, anchors, tmp_path / "p1.csv")
    pd.testing.assert_frame_equal(_locate(one, anchors, tmp_path / "p2.csv",
                                          "--chunk-rows", "20000"), ref)
    pd.testing.assert_frame_equal(_locate(other, anchors, tmp_path / "p3.csv"), ref)


def test_epoch_hash_sample_is_nested_and_about_one_in_k():
    t = np.repeat(np.arange(400.0), 50)
    tags = np.tile(np.array([f"T{i}" for i in range(50)], dtype=object), 400)
    h = epoch_hash(t, tags)
    assert np.array_equal(h, epoch_hash(t.copy(), tags.astype(str)))  # str or object
    assert np.array_equal(epoch_hash([0.0], ["a"]), epoch_hash([-0.0], ["a"]))
    kept = {k: (h & np.uint64(k - 1)) == 0 for k in (1, 2, 4, 8, 16)}
    n = len(h)
    for k, sel in kept.items():
        # binomial(n, 1/k): within 4 standard deviations
        assert abs(sel.sum() - n / k) <= 4 * np.sqrt(n / k * (1 - 1 / k)), (k, sel.sum())
        if k > 1:
            assert not (sel & ~kept[k // 2]).any()  # a larger step keeps a subset
