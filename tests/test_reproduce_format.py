"""The numbers of the reproduction report's tables: 3 significant digits (trailing zeros
kept), counts as integers, no column of row numbers -- in report.md, report.html and on
stdout alike (the report review: ``.3g`` printed 1.2 for 1.196 and 2.33e+03 for a count of
2329; stdout printed ``%.3f`` with the pandas index)."""

from __future__ import annotations

import types

import numpy as np
import pandas as pd
import pytest

import robustloc.reproduce as rep
from robustloc.reproduce import Context, Section, render, run_all
from robustloc.reproduce._format import fmt_num, format_frame, text_table


@pytest.mark.parametrize("value, text", [
    (1.196, "1.20"), (1.997, "2.00"), (0.5, "0.500"), (-0.5, "-0.500"), (-3.31, "-3.31"),
    (0.00292, "0.00292"), (0.0, "0.00"), (100.0, "100"), (99.96, "100"), (74.7, "74.7"),
    (671.3, "671"), (999.7, "1000"), (2329.4, "2330"), (-1234.5, "-1230"),
    (671234.5, "671000"), (6500.0, "6500"), (2329.0, "2329"), (1.23e-5, "1.23e-05"),
    (2329, "2329"), (np.int64(2329), "2329"), (np.float32(1.5), "1.50"),
    (float("nan"), ""), (None, ""), (pd.NA, ""), (float("inf"), "inf"),
    (-float("inf"), "-inf"), (True, "True"), ("115/120", "115/120"),
])
def test_fmt_num(value, text):
    assert fmt_num(value) == text


def _frame() -> pd.DataFrame:
    # a count column made float by a NaN-padded reference row (s60's dwm1001 table)
    return pd.DataFrame([
        {"run": "LOS", "method": "authors ESKF", "rms": 1.196, "n": 2329, "missing": 0},
        {"run": "LOS", "method": "reference", "rms": 0.766},
        {"run": "LOS", "method": "track", "rms": 0.00292, "n": 59, "missing": 3},
    ])


def test_format_frame_counts_and_no_row_numbers():
    f = _frame()
    assert f["n"].dtype == float  # the NaN made it float
    out = format_frame(f)
    assert list(out.columns) == ["run", "method", "rms", "n", "missing"]
    assert list(out["n"]) == ["2329", "", "59"]
    assert list(out["missing"]) == ["0", "", "3"]
    assert list(out["rms"]) == ["1.20", "0.766", "0.00292"]
    # a meaningful index (a pivot's) is the first column; a default range index is dropped
    piv = pd.DataFrame({"a": [1.5]}, index=pd.Index(["office"], name="room"))
    assert list(format_frame(piv).columns) == ["room", "a"]
    assert list(format_frame(piv.reset_index(drop=True)).columns) == ["a"]


def test_stdout_table_has_no_index_and_the_same_numbers():
    txt = text_table(_frame())
    lines = txt.splitlines()
    assert lines[0].split() == ["run", "method", "rms", "n", "missing"]
    assert lines[1].split() == ["LOS", "authors", "ESKF", "1.20", "2329", "0"]
    assert "2.33e+03" not in txt and "2329.000" not in txt and "0.003 " not in txt


def test_report_tables_use_the_formatter(tmp_path):
    sec = Section("t")
    sec.table("cap", _frame())
    sec.headline("000", "h", "-", "ours", "-", "v")
    md, html = render([sec], tmp_path, {})
    text = md.read_text()
    assert "| run | method | rms | n | missing |" in text
    assert "| LOS | authors ESKF | 1.20 | 2329 | 0 |" in text
    assert "| LOS | reference | 0.766 |  |  |" in text
    assert "2.33e+03" not in text
    page = html.read_text()
    assert "<td>2329</td>" in page and "<td>1.20</td>" in page and "2.33e+03" not in page
    assert "<th></th>" not in page  # no index column


def test_run_all_prints_the_same_table(tmp_path, monkeypatch, capsys):
    def run(ctx):
        sec = Section("fake")
        sec.table("cap", _frame())
        return sec

    mod = types.SimpleNamespace(KEY="fake", TITLE="fake", run=run)
    monkeypatch.setattr(rep, "section_modules", lambda only=None: [mod])
    run_all(Context(out_dir=tmp_path / "r", data_dir=None))
    out = capsys.readouterr().out
    assert "\ncap\n" + text_table(_frame()) in out
