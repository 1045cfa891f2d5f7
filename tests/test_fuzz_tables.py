"""Fuzz harness for the table inputs (issue 15, deliver 7): hypothesis-generated CSV and
Parquet measurements and anchors files -- malformed, NaN, huge, unknown ids, shuffled,
duplicate headers, binary garbage -- through the real command line.

For every input it asserts: no traceback; exit code 0 or 2; on 0, exactly one output row
per input epoch and method, each with a known status; on 2, an ``error: `` message and no
file (nor temporary file) at the final path.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robustloc import status as st_codes
from robustloc.cli import main

ENV = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
CLI = [sys.executable, "-m", "robustloc.cli"]
METHODS = ("ls", "nls")
GOOD_ANCHORS = "anchor,x,y\na,0,0\nb,20,0\nc,0,20\nd,20,20\n"

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
wild = st.one_of(
    finite,
    st.sampled_from([float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1e200, 0.0,
                     -0.0, 5e-324, 1e13, -60.0, -500.0, 50.0]),
)
ids = st.sampled_from(["a", "b", "c", "d", "zz", " a", "NA", ""])
tags = st.sampled_from(["T", "U", "V", "NA", "é", " T"])


@st.composite
def measurement_rows(draw):
    n = draw(st.integers(1, 25))
    times = draw(st.lists(st.one_of(st.sampled_from([0.0, 0.5, 1.0, 2.0]), wild),
                          min_size=n, max_size=n))
    return pd.DataFrame({
        "time": times,
        "tag": draw(st.lists(tags, min_size=n, max_size=n)),
        "anchor": draw(st.lists(ids, min_size=n, max_size=n)),
        "value": draw(st.lists(st.one_of(st.floats(0.5, 40), wild), min_size=n, max_size=n)),
    })


@st.composite
def measurement_file(draw):
    """(bytes or frame, format, the rows if the file is clean)."""
    df = draw(measurement_rows())
    value = draw(st.sampled_from(["range", "rssi"]))
    header = ["time", "tag", "anchor", value]
    header_kind = draw(st.sampled_from(["ok"] * 6 + ["dup", "missing", "both", "extra"]))
    if header_kind == "dup":
        header = header + [value]
        df["dup"] = df["value"]
    elif header_kind == "missing":
        header = header[:2] + header[3:]
        df = df.drop(columns=["anchor"])
    elif header_kind == "both":
        header = header + ["rssi" if value == "range" else "range"]
        df["other"] = df["value"]
    elif header_kind == "extra":
        header = header + ["note"]
        df["note"] = "x"
    if draw(st.booleans()):
        df = df.sample(frac=1, random_state=draw(st.integers(0, 100)))
    fmt = draw(st.sampled_from(["csv", "csv", "parquet"]))
    if fmt == "parquet":
        if header_kind == "dup":
            fmt = "csv"
        else:
            out = df.copy()
            out.columns = header
            return out, "parquet", (header_kind in ("ok", "extra"))
    lines = [",".join(header)]
    for row in df.itertuples(index=False):
        lines.append(",".join(repr(v) if isinstance(v, float) else str(v) for v in row))
    text = ("\n".join(lines) + "\n").encode()
    corrupt = draw(st.sampled_from(["none"] * 5 + ["garbage", "bytes", "truncate", "ragged",
                                                   "empty", "header"]))
    if corrupt == "garbage":
        text = draw(st.binary(min_size=1, max_size=300))
    elif corrupt == "bytes":
        pos = draw(st.integers(0, len(text)))
        text = text[:pos] + draw(st.binary(min_size=1, max_size=8)) + text[pos:]
    elif corrupt == "truncate":
        text = text[: draw(st.integers(0, len(text)))]
    elif corrupt == "ragged":
        text = text + b"1,2\n"
    elif corrupt == "empty":
        text = b""
    elif corrupt == "header":
        text = text.split(b"\n", 1)[0] + b"\n"
    return text, "csv", (corrupt == "none" and header_kind in ("ok", "extra"))


@st.composite
def anchors_file(draw):
    kind = draw(st.sampled_from(["good"] * 6 + ["fuzzed", "garbage", "dup", "parquet"]))
    if kind == "good":
        return GOOD_ANCHORS.encode(), "csv"
    if kind == "garbage":
        return draw(st.binary(max_size=200)), "csv"
    if kind == "dup":
        return (GOOD_ANCHORS + "b,5,5\n").encode(), "csv"
    n = draw(st.integers(1, 5))
    df = pd.DataFrame({
        "anchor": draw(st.lists(ids, min_size=n, max_size=n)),
        "x": draw(st.lists(wild, min_size=n, max_size=n)),
        "y": draw(st.lists(wild, min_size=n, max_size=n)),
    })
    if kind == "parquet":
        return df, "parquet"
    lines = ["anchor,x,y"] + [f"{a},{x!r},{y!r}" for a, x, y in df.itertuples(index=False)]
    return ("\n".join(lines) + "\n").encode(), "csv"


def _write(folder: Path, name: str, content, fmt: str) -> Path:
    p = folder / f"{name}.{fmt}"
    if fmt == "parquet":
        content.to_parquet(p, index=False)
    else:
        p.write_bytes(content)
    return p


def _expected_epochs(frame: pd.DataFrame) -> int | None:
    """Distinct (time, tag) of a clean generated frame, as a reader would see them."""
    t = pd.to_numeric(frame["time"], errors="coerce")
    if t.isna().any() or np.isinf(t).any():
        return None
    tag = frame["tag"].astype(str).str.strip()
    return len(set(zip(t.to_numpy(dtype=float).tolist(), tag)))


def _check(rc: int, err: str, out: Path, meas_frame) -> None:
    assert "Traceback" not in err, err
    assert rc in (0, 2), (rc, err)
    if out.parent.exists():
        assert not [f for f in out.parent.iterdir() if f.name.endswith(".tmp")]
    if rc == 2:
        assert err.startswith("error: ") or "error: argument" in err, err
        assert not out.exists()
        return
    pos = pd.read_csv(out, dtype={"tag": str}, keep_default_na=False,
                      na_values={c: ["", "nan"] for c in ("x", "y", "sigma0")})
    assert set(pos["status"]) <= set(st_codes.ALL)
    per = pos.groupby("method").size()
    assert set(per.index) == set(METHODS) and per.nunique() == 1
    assert not pos.duplicated(["time", "tag", "method"]).any()
    if meas_frame is not None:
        n = _expected_epochs(meas_frame)
        if n is not None:
            assert per.iloc[0] == n


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(meas=measurement_file(), anchors=anchors_file(), chunk=st.sampled_from([3, 500_000]))
def test_fuzz_locate_in_process(tmp_path_factory, capsys, meas, anchors, chunk):
    d = tmp_path_factory.mktemp("fz")
    m = _write(d, "m", meas[0], meas[1])
    a = _write(d, "a", anchors[0], anchors[1])
    out = d / "out" / "p.csv"
    capsys.readouterr()
    rc = main(["locate", str(m), "--anchors", str(a), "-o", str(out), "--method",
               ",".join(METHODS), "--chunk-rows", str(chunk), "--quiet"])
    err = capsys.readouterr().err
    frame = None
    if meas[2] and isinstance(anchors[0], bytes) and anchors[0] == GOOD_ANCHORS.encode():
        frame = meas[0] if meas[1] == "parquet" else pd.read_csv(
            m, dtype={"tag": str}, keep_default_na=False, skipinitialspace=True)
    _check(rc, err, out, frame)


@settings(max_examples=30, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(meas=measurement_file())
def test_fuzz_evaluate_in_process(tmp_path_factory, capsys, meas):
    """The same generated files as positions and as truth for evaluate: 0 or 2, no
    traceback, no file at -o after a failure."""
    d = tmp_path_factory.mktemp("fe")
    m = _write(d, "m", meas[0], meas[1])
    out = d / "stats.csv"
    capsys.readouterr()
    rc = main(["evaluate", str(m), "--truth", str(m), "-o", str(out)])
    err = capsys.readouterr().err
    assert "Traceback" not in err and rc in (0, 2), err
    if rc == 2:
        assert not out.exists()


@pytest.mark.parametrize("content", [
    b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR" + bytes(range(256)),
    b"time,tag,anchor,range\n" + b"0,T,a,1e308\n0,T,b,nan\n",
    b"time,tag,anchor,range\n" + b"".join(b"%d,T,a,1e400\n" % i for i in range(5)),
    b"time,tag,anchor,range,range\n0,T,a,1,1\n",
    b"PAR1garbage",
])
def test_fuzz_regressions_real_process(tmp_path, content):
    (tmp_path / "a.csv").write_text(GOOD_ANCHORS)
    (tmp_path / "m.csv").write_bytes(content)
    out = tmp_path / "p.csv"
    r = subprocess.run(CLI + ["locate", str(tmp_path / "m.csv"), "--anchors",
                              str(tmp_path / "a.csv"), "-o", str(out), "--quiet"],
                       capture_output=True, text=True, env=ENV, timeout=300)
    assert "Traceback" not in r.stderr
    assert r.returncode == 2 and r.stderr.startswith(f"error: {tmp_path / 'm.csv'}")
    assert not out.exists()
