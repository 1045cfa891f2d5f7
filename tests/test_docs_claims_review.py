"""Claims of the help texts that the docs review (2026-12-06) found false, kept true."""

from __future__ import annotations

import json

from robustloc.cli import main


def _help(capsys, *cmd: str) -> str:
    try:
        main([*cmd, "--help"])
    except SystemExit:
        pass
    return " ".join(capsys.readouterr().out.split())


def test_simulate_wifi_room_help_states_the_memory_per_row(capsys):
    # (it printed the unexpanded ":data:`BYTES_PER_ROW`")
    from robustloc.sim import wifi_room

    text = _help(capsys, "simulate", "wifi-room")
    assert f"about {wifi_room.BYTES_PER_ROW} bytes" in text
    assert ":data:" not in text


def test_evaluate_json_is_what_its_help_says(tmp_path, capsys):
    # (the help said "JSON records": it is an object holding them)
    assert "n_unmatched" in _help(capsys, "evaluate")
    pos = tmp_path / "p.csv"
    pos.write_text("time,tag,x,y,method,status\n0,t,1,1,ls,ok\n", encoding="utf-8")
    truth = tmp_path / "t.csv"
    truth.write_text("time,tag,x,y\n0,t,1,2\n", encoding="utf-8")
    assert main(["evaluate", str(pos), "--truth", str(truth), "--json", "-q"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"n_unmatched", "rows"} and isinstance(out["rows"], list)
