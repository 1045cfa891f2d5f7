"""The live map's Tags table shows tag ids and statuses in full (the new-user walkthrough).

Fixed column widths (282 px of a 370 px panel) left the tag column about 20 px at window
widths of 1200 and 1800 px: every tag id read "…" and "fault_detected" read
"fault_det…".  Measured here in headless Chromium (Debian's, driven by Playwright) on a
real server: a cell shows its text in full when its ``scrollWidth`` is at most its
``clientWidth`` (the browser's own measure of the text against the cell).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("starlette")
httpx = pytest.importorskip("httpx")
sync_api = pytest.importorskip("playwright.sync_api")

from test_service import wait_for  # noqa: E402
from test_service_browser import ARGS, CHROMIUM  # noqa: E402  (skips without chromium)

from robustloc.service.launch import ServerProcess  # noqa: E402

#: Six anchors along a 25 m x 4 m corridor (as the other page tests).
ANCHORS = [(str(i + 1), 5.0 * i, 0.0 if i % 2 == 0 else 4.0) for i in range(6)]
#: Tags posted as range rows (solved by the server) and tags pushed into the page's
#: WebSocket with the statuses of longer names (a fault detected; no fix at all).
SOLVED = {"S1": (3.0, 2.0), "tag-000123": (12.0, 1.5)}
PUSHED = {"forklift-0012": "fault_detected", "gate-7": "insufficient_anchors"}


def _rows(tag: str, pt: tuple[float, float], t: float) -> list[dict]:
    return [{"time": float(t), "tag": tag, "anchor": a,
             "range": float(np.hypot(x - pt[0], y - pt[1]) + 0.01 * (i % 3))}
            for i, (a, x, y) in enumerate(ANCHORS)]


def _pushed_rows() -> list[dict]:
    base = {"method": "nls", "n_used": 6, "sigma0": 0.01, "excluded": "", "cov_xx": 0.01,
            "cov_yy": 0.01, "cov_xy": 0.0, "time": 2.0}
    out = []
    for tag, status in PUSHED.items():
        fix = status != "insufficient_anchors"
        out.append(dict(base, tag=tag, status=status, x=20.0 if fix else None,
                        y=2.0 if fix else None, hpl=4.5 if fix else None))
    return out


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    d = tmp_path_factory.mktemp("newusermap")
    anchors = d / "anchors.csv"
    anchors.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n" for a, x, y in ANCHORS))
    srv = ServerProcess(["--anchors", str(anchors), "--idle-flush", "0.3"])
    try:
        srv.start()
        rows = [r for t in range(3) for tag, pt in SOLVED.items() for r in _rows(tag, pt, t)]
        r = httpx.post(srv.url + "/api/measurements", json=rows, timeout=30)
        assert r.status_code == 202 and not r.json()["rejected"], r.text
        wait_for(lambda: set(SOLVED) <= {x["tag"] for x in httpx.get(
            srv.url + "/api/latest", timeout=30).json()} or None, what="the tags solved")
        yield srv
    finally:
        srv.stop()


def _cells(srv: ServerProcess, width: int, height: int = 800) -> tuple[list[list], dict]:
    """The Tags table at a ``width`` x ``height`` window: per row its tag and, for the tag
    and status cells, ``[text, shown in full, title]``; and the panel's widths."""
    socks: list = []

    def through(ws):  # noqa: ANN001, ANN202 - the page's own socket, passed through
        ws.connect_to_server()
        socks.append(ws)
    pw = sync_api.sync_playwright().start()
    try:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.route_web_socket("**/ws/positions*", through)
            page.goto(srv.url + "/")
            page.wait_for_function("window.robustloc && window.robustloc.ready "
                                   "&& window.robustloc.connected", timeout=30_000)
            socks[-1].send(json.dumps(_pushed_rows()))
            n = len(SOLVED) + len(PUSHED)
            page.wait_for_function(f"document.querySelectorAll('#tagtable tr').length == {n}",
                                   timeout=15_000)
            page.wait_for_timeout(1200)  # one table refresh (every second) after the rows
            rows = page.evaluate(
                "() => [...document.querySelectorAll('#tagtable tr')].map(r => [r.dataset.tag,"
                " ...[0, 4].map(i => [r.cells[i].textContent.trim(), r.cells[i].scrollWidth"
                " <= r.cells[i].clientWidth, r.cells[i].title])])")
            panel = page.evaluate(
                "() => { const a = document.querySelector('aside'), t = document."
                "getElementById('tags-table'), last = [...document.querySelectorAll("
                "'#tagtable tr')].map(r => r.cells[5].getBoundingClientRect().right);"
                " return {sw: a.scrollWidth, cw: a.clientWidth, right: a.getBoundingClientRect()"
                ".right, table: t.getBoundingClientRect().right, last: Math.max(...last)}; }")
            return rows, panel
        finally:
            browser.close()
    finally:
        pw.stop()


def test_tag_ids_and_statuses_in_full_at_1200_and_1800_px_and_narrow_still_works(served):
    """At 1200 and 1800 px every tag id (12 characters and more) and every status name of
    the table is shown in full, with its text in its tooltip; the panel never scrolls
    sideways.  At 400 px (a phone: the panel under the map) the table still fits the
    panel, its last column visible, a short id is never cut, and a cell that must be cut
    keeps its full text in its tooltip."""
    for width in (1200, 1800):
        rows, panel = _cells(served, width)
        assert sorted(r[0] for r in rows) == sorted([*SOLVED, *PUSHED])
        for tag, (tag_text, tag_full, tag_title), (st_text, st_full, st_title) in rows:
            assert tag_text == tag and tag_title == tag
            assert tag_full, f"tag {tag!r} cut at {width} px"
            assert st_full, f"status {st_text!r} cut at {width} px"
            assert st_title == st_text
        statuses = {r[0]: r[2][0] for r in rows}
        assert {t: statuses[t] for t in PUSHED} == PUSHED
        assert panel["sw"] <= panel["cw"], (width, panel)
    rows, panel = _cells(served, 400)
    assert panel["sw"] <= panel["cw"] and panel["last"] <= panel["right"] + 0.5, panel
    assert panel["table"] <= panel["right"] + 0.5, panel
    for tag, (_, _, tag_title), (st_text, _, st_title) in rows:
        assert tag_title == tag and st_title == st_text
    assert any(r[0] == "S1" and r[1][1] for r in rows)
