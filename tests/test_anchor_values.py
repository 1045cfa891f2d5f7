"""Anchor parameters that only make sense positive are refused with file and line
(issue 15: `n = 0` printed a numpy array, `scale <= 0` named the file but not the line)."""

from __future__ import annotations

import pytest

from robustloc.cli import main


@pytest.mark.parametrize(("header", "rows", "message"), [
    ("anchor,x,y,A,n", ["a,0,0,-60,0", "b,10,0,-60,2", "c,0,10,-60,2"],
     "an.csv:2: path-loss exponent n must be positive, got 0 for anchor 'a'"),
    ("anchor,x,y,bias,scale", ["a,0,0,0,1", "b,10,0,0,-1", "c,0,10,0,1"],
     "an.csv:3: range scale must be positive, got -1 for anchor 'b'"),
    ("anchor,x,y,sigma", ["a,0,0,0.1", "b,10,0,0.2", "c,0,10,0"],
     "an.csv:4: sigma must be positive, got 0 for anchor 'c'"),
])
def test_non_positive_anchor_parameters_name_the_line(tmp_path, capsys, header, rows,
                                                      message):
    (tmp_path / "an.csv").write_text("\n".join([header, *rows]) + "\n")
    value = "rssi" if ",A,n" in header else "range"
    (tmp_path / "m.csv").write_text(f"time,tag,anchor,{value}\n0,t,a,-70\n0,t,b,-70\n"
                                    "0,t,c,-70\n" if value == "rssi" else
                                    f"time,tag,anchor,{value}\n0,t,a,7\n0,t,b,7\n0,t,c,7\n")
    rc = main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "an.csv"),
               "-o", str(tmp_path / "p.csv")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and message in err and "Traceback" not in err
    assert not (tmp_path / "p.csv").exists()
