"""The live map page in real headless Chromium (Debian's, driven by Playwright).

Loads ``/`` from a real server, replays a short log, and checks that each tag's marker
sits where ``/api/latest`` says the tag is: both in the marker's world coordinates and in
screen pixels computed here independently from the SVG viewBox (preserveAspectRatio
"xMidYMid meet").  Also checks the per-anchor health table and the floor-plan image, that
nothing is fetched from another origin, and takes a screenshot (into the test's temporary
folder; into docs/img/serve.png, the README's picture, when ROBUSTLOC_UPDATE_SCREENSHOT=1).
"""

from __future__ import annotations

import os
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("starlette")
httpx = pytest.importorskip("httpx")
sync_api = pytest.importorskip("playwright.sync_api")

from test_service import _cli, wait_for  # noqa: E402

from robustloc.service.launch import ServerProcess  # noqa: E402

CHROMIUM = os.environ.get("ROBUSTLOC_CHROMIUM", "/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
        "--disable-component-update", "--disable-sync", "--no-first-run"]
SCREENSHOT = Path(__file__).resolve().parents[1] / "docs" / "img" / "serve.png"

if not Path(CHROMIUM).exists() and not shutil.which("chromium"):
    pytest.skip("Debian chromium missing (apt-get install chromium; .ci/install-system)",
                allow_module_level=True)


def _origin(page) -> tuple[float, float]:
    """The world point the page draws at SVG (0, 0): it draws relative to a local origin
    (single-precision SVG geometry would lose projected coordinates' decimetres)."""
    svg = page.locator("svg#map")
    return (float(svg.get_attribute("data-origin-x") or 0),
            float(svg.get_attribute("data-origin-y") or 0))


def _view(page) -> tuple[float, float, float, float]:
    """The viewBox in world coordinates: x0, y1 (top), width, height."""
    vx, vy, vw, vh = map(float, page.get_attribute("svg#map", "viewBox").split())
    ox, oy = _origin(page)
    return vx + ox, -vy + oy, vw, vh


def _screen(page, x: float, y: float) -> tuple[float, float]:
    """Where world (x, y) is on the screen, computed here independently of the page's
    drawing: from the viewBox, the local origin and the SVG's box (meet, centred)."""
    vx, vy, vw, vh = map(float, page.get_attribute("svg#map", "viewBox").split())
    orx, ory = _origin(page)
    box = page.locator("svg#map").bounding_box()
    s = min(box["width"] / vw, box["height"] / vh)
    ox = box["x"] + (box["width"] - vw * s) / 2
    oy = box["y"] + (box["height"] - vh * s) / 2
    return ox + (x - orx - vx) * s, oy + (-(y - ory) - vy) * s


def _floorplan(path: Path, extent: tuple[float, float, float, float]) -> None:
    """A simple corridor plan: rooms above and below a corridor (PNG, matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x0, y0, x1, y1 = extent
    fig = plt.figure(figsize=(8, 8 * (y1 - y0) / (x1 - x0)), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.axis("off")
    ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, color="#f3efe6"))
    ax.add_patch(plt.Rectangle((0, 0), 30, 4, color="#ffffff"))
    for x in np.arange(0, 31, 6):
        ax.plot([x, x], [y0, 0], color="#9a8f7a", lw=2)
        ax.plot([x, x], [4, y1], color="#9a8f7a", lw=2)
    ax.plot([0, 30], [0, 0], color="#6b604c", lw=3)
    ax.plot([0, 30], [4, 4], color="#6b604c", lw=3)
    fig.savefig(path)
    plt.close(fig)


def test_map_page_shows_tags_where_the_api_says(tmp_path):
    from robustloc.commands.replay import replay

    d = tmp_path / "ble"
    _cli("simulate", "ble-corridor", "--seed", "1", "--out", str(d))
    meas = pd.read_csv(d / "measurements.csv", dtype={"tag": str, "anchor": str})
    short = d / "short.csv"
    meas[meas["time"] < 25].to_csv(short, index=False)
    extent = (-1.0, -3.0, 31.0, 7.0)
    plan = tmp_path / "plan.png"
    _floorplan(plan, extent)
    token = "browser-token"
    srv = ServerProcess(["--anchors", str(d / "anchors.csv"), "--idle-flush", "0.3",
                         "--floorplan", str(plan),
                         "--floorplan-extent=" + ",".join(map(str, extent))],
                        env={"ROBUSTLOC_TOKEN": token})
    foreign: list[str] = []
    try:
        srv.start()
        with sync_api.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 720})
                page.on("request", lambda r: None if r.url.startswith(srv.url.replace(
                    "http", "ws")) or r.url.startswith(srv.url) or r.url.startswith(
                    ("blob:", "data:")) else foreign.append(r.url))
                page.goto(f"{srv.url}/#token={token}")
                page.wait_for_function("window.robustloc && window.robustloc.ready "
                                       "&& window.robustloc.connected", timeout=30_000)
                assert page.locator("path.anchor-marker").count() == 10
                # the plan is fetched after the anchors are drawn (asynchronously)
                page.wait_for_selector("#floorplan-image", state="attached", timeout=30_000)
                assert page.locator("#floorplan-image").count() == 1
                res = replay(str(short), srv.url, speed=20, token=token)
                assert res["accepted"] == res["rows"]
                auth = {"Authorization": f"Bearer {token}"}
                n_epochs = len(meas[meas["time"] < 25].groupby(["time", "tag"]))
                wait_for(lambda: len(httpx.get(srv.url + "/api/positions",
                                               headers=auth).json()) == n_epochs or None,
                         what="all epochs solved")
                latest = {r["tag"]: r for r in httpx.get(srv.url + "/api/latest",
                                                         headers=auth).json()}
                assert sorted(latest) == ["S1", "S2", "S3"]
                for tag, row in latest.items():
                    sel = f'circle.tag-marker[data-tag="{tag}"]'
                    page.wait_for_function(
                        "([s, x]) => { const e = document.querySelector(s); return e && "
                        "Math.abs(parseFloat(e.getAttribute('data-x')) - x) < 1e-9; }",
                        arg=[sel, row["x"]], timeout=15_000)
                    marker = page.locator(sel)
                    assert float(marker.get_attribute("data-x")) == pytest.approx(row["x"],
                                                                                  abs=1e-9)
                    assert float(marker.get_attribute("data-y")) == pytest.approx(row["y"],
                                                                                  abs=1e-9)
                    assert marker.get_attribute("data-status") == row["status"]
                    # screen position, from the viewBox and the SVG's box (meet, centred)
                    want = _screen(page, row["x"], row["y"])
                    mb = marker.bounding_box()
                    got = (mb["x"] + mb["width"] / 2, mb["y"] + mb["height"] / 2)
                    assert abs(got[0] - want[0]) < 1.5 and abs(got[1] - want[1]) < 1.5, (
                        tag, got, want)
                    assert page.locator(f'ellipse.tag-ellipse[data-tag="{tag}"]').count() == 1
                # per-anchor health: last heard and rejection rate in the side table
                page.wait_for_function(
                    "document.querySelectorAll('#anchortable tr').length == 10", timeout=10_000)
                # the panels refresh every 2 s (index.html: setInterval(refreshPanels,
                # 2000)): wait for a refresh after the replay, at most five of them
                # (cells: anchor, last heard, rows, rejection rate)
                page.wait_for_function(
                    "() => { const r = document.querySelector("
                    "'#anchortable tr[data-anchor=\"1\"]'); if (!r) return false; "
                    "const c = r.cells; return c.length == 4 && c[3].innerText == '0.0 %' "
                    "&& /^(now|[0-9]+ s ago)$/.test(c[1].innerText); }", timeout=10_000)
                row1 = page.locator('#anchortable tr[data-anchor="1"]').inner_text()
                assert "0.0 %" in row1 and ("now" in row1 or "s ago" in row1)
                shot = (SCREENSHOT if os.environ.get("ROBUSTLOC_UPDATE_SCREENSHOT") == "1"
                        else tmp_path / "serve.png")
                shot.parent.mkdir(parents=True, exist_ok=True)
                page.screenshot(path=str(shot))
            finally:
                browser.close()
    finally:
        srv.stop()
    assert not foreign, f"the page fetched from elsewhere: {foreign}"
    assert shot.stat().st_size > 10_000


# -- the page's behaviour over time (review of the map page) --------------------------------
# Each test below starts real servers (127.0.0.1, free port) and Debian's Chromium, and
# stops both whatever happens.  Anchors: six along a 25 m x 4 m corridor, range rows.

ANCHORS = [(str(i + 1), 5.0 * i, 0.0 if i % 2 == 0 else 4.0) for i in range(6)]


def _write_anchors(path: Path, shift: float = 0.0) -> Path:
    path.write_text("anchor,x,y\n" + "".join(f"{a},{x + shift},{y}\n" for a, x, y in ANCHORS))
    return path


def _rows(tag: str, pt: tuple[float, float], t: float, shift: float = 0.0,
          which: tuple[str, ...] | None = None, noise: bool = True) -> list[dict]:
    return [{"time": float(t), "tag": tag, "anchor": a,
             "range": float(np.hypot(x + shift - pt[0], y - pt[1]) + (0.01 * (i % 3) if noise
                                                                       else 0.0))}
            for i, (a, x, y) in enumerate(ANCHORS) if which is None or a in which]


def _post(srv: ServerProcess, rows: list[dict], token: str | None = None) -> None:
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    r = httpx.post(srv.url + "/api/measurements", json=rows, headers=auth, timeout=30)
    assert r.status_code == 202 and not r.json()["rejected"], r.text


def _latest(srv: ServerProcess, token: str | None = None) -> dict[str, dict]:
    auth = {"Authorization": f"Bearer {token}"} if token else {}
    return {r["tag"]: r for r in httpx.get(srv.url + "/api/latest", headers=auth,
                                           timeout=30).json()}


class _Chromium:
    """Debian's Chromium via Playwright; ``with _Chromium() as browser``: always closed."""

    def __enter__(self):
        self.pw = sync_api.sync_playwright().start()
        try:
            self.browser = self.pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        except BaseException:
            self.pw.stop()
            raise
        return self.browser

    def __exit__(self, *exc: object) -> None:
        try:
            self.browser.close()
        finally:
            self.pw.stop()


def _open(browser, url: str, width: int = 1280, height: int = 720, log: list | None = None):
    page = browser.new_page(viewport={"width": width, "height": height})
    if log is not None:
        page.on("console", lambda m: log.append(("console", m.type, m.text))
                if m.type == "error" else None)
        page.on("response", lambda r: log.append(("http", r.status, r.url))
                if r.status >= 400 else None)
        page.on("pageerror", lambda e: log.append(("pageerror", str(e))))
    page.goto(url)
    _ready(page)
    return page


def _ready(page, timeout: float = 30_000) -> None:
    page.wait_for_function("window.robustloc && window.robustloc.ready "
                           "&& window.robustloc.connected", timeout=timeout)


def _wait_marker_x(page, tag: str, x: float, timeout: float = 15_000) -> None:
    page.wait_for_function(
        "([t, x]) => { const e = document.querySelector(`circle.tag-marker[data-tag='${t}']`);"
        " return e && Math.abs(parseFloat(e.getAttribute('data-x')) - x) < 1e-6; }",
        arg=[tag, x], timeout=timeout)


def _table(page) -> dict[str, dict]:
    return {r["tag"]: r for r in page.evaluate(
        "() => [...document.querySelectorAll('#tagtable tr')].map(r => ({tag: r.dataset.tag,"
        " cells: [...r.cells].map(c => c.textContent.trim()), cls: r.className}))")}


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """One memory-only server shared by the tests that only add their own tags."""
    d = tmp_path_factory.mktemp("mappage")
    srv = ServerProcess(["--anchors", str(_write_anchors(d / "anchors.csv")),
                         "--idle-flush", "0.3"])
    try:
        srv.start()
        yield srv
    finally:
        srv.stop()


def test_map_page_does_not_move_a_tag_to_a_late_epochs_fix(live):
    """A late epoch's fix (every row of it came after later epochs were solved) is
    published with ``late`` true: history, not where the tag is.  The page took it as the
    tag's clock going back: the marker jumped to it and the trail restarted."""
    from robustloc.service.launch import read_metric

    with _Chromium() as browser:
        page = _open(browser, live.url + "/")
        for t in range(7):
            _post(live, _rows("LATE", (5, 2), t))
        x = wait_for(lambda: _latest(live).get("LATE", {}).get("time") == 6
                     and _latest(live)["LATE"]["x"], what="LATE at time 6")
        _wait_marker_x(page, "LATE", x)
        before = read_metric(live.url, "robustloc_late_epochs_solved_total")
        _post(live, _rows("LATE", (20, 2), 2.5))  # every row late, the fix far away
        wait_for(lambda: read_metric(live.url, "robustloc_late_epochs_solved_total")
                 > before, what="the late epoch solved")
        time.sleep(1.0)  # (its row reaches the page over the WebSocket)
        got = float(page.get_attribute('circle.tag-marker[data-tag="LATE"]', "data-x"))
        assert got == pytest.approx(x, abs=1e-6)
        trail = page.get_attribute('polyline.tag-trail[data-tag="LATE"]', "points")
        ox, _ = _origin(page)
        pts = [float(p.split(",")[0]) + ox for p in trail.split()]
        assert len(pts) >= 2 and all(abs(v - 5) < 1 for v in pts), trail


def test_map_page_follows_a_tag_whose_clock_went_back(tmp_path):
    """The server re-bases a tag whose clock restarts (--time-jump): the marker follows."""
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--idle-flush", "0.3", "--time-jump", "5"])
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            for t in range(100, 104):
                _post(srv, _rows("T", (5, 2), t))
            x = wait_for(lambda: _latest(srv).get("T", {}).get("time") == 103
                         and _latest(srv)["T"]["x"], what="T at time 103")
            _wait_marker_x(page, "T", x)
            for t in range(6):  # the device restarted: its clock from 0, and it moved
                _post(srv, _rows("T", (20, 2), t))
                time.sleep(0.6)
            row = wait_for(lambda: (r := _latest(srv)["T"])["time"] == 5 and r, what="time 5")
            _wait_marker_x(page, "T", row["x"])
            trail = page.get_attribute('polyline.tag-trail[data-tag="T"]', "points")
            ox, _ = _origin(page)
            assert all(float(p.split(",")[0]) + ox > 15 for p in trail.split()), trail
    finally:
        srv.stop()


def test_map_page_retries_a_floor_plan_that_failed_to_load(tmp_path):
    """The first request for the floor plan fails (a dropped connection): the page tries
    again on its next resync instead of staying without its plan, and draws it once."""
    extent = (-2.0, -2.0, 32.0, 12.0)
    plan = tmp_path / "plan.png"
    _floorplan(plan, extent)
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--floorplan", str(plan),
                         "--floorplan-extent=" + ",".join(map(str, extent))])
    fetched: list[str] = []
    try:
        srv.start()
        with _Chromium() as browser:
            page = browser.new_page(viewport={"width": 1280, "height": 720})

            def first_fails(route):
                fetched.append(route.request.url)
                if len(fetched) == 1:
                    route.abort("connectionreset")
                else:
                    route.continue_()

            page.route("**/floorplan", first_fails)
            page.goto(srv.url + "/")
            _ready(page)
            page.wait_for_selector("#floorplan-image", state="attached", timeout=30_000)
            assert len(fetched) >= 2
            assert page.locator("#floorplan-image").count() == 1
            img = page.locator("#floorplan-image")
            ox, oy = _origin(page)
            assert [float(img.get_attribute(k)) for k in ("x", "y", "width", "height")] == [
                extent[0] - ox, -(extent[3] - oy), extent[2] - extent[0], extent[3] - extent[1]]
    finally:
        srv.stop()


def test_map_page_follows_a_restarted_server_with_new_anchors(tmp_path):
    """A memory-only server restarted on the same port with other anchors, and a replay
    from time 0: the page redraws the anchors, and the tags restart (no line from the old
    run to the new)."""
    first = _write_anchors(tmp_path / "a.csv")
    moved = _write_anchors(tmp_path / "moved.csv", shift=40.0)
    srv = ServerProcess(["--anchors", str(first), "--idle-flush", "0.3"])
    srv2 = ServerProcess(["--anchors", str(moved), "--idle-flush", "0.3"], port=srv.port)
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            _post(srv, [r for t in range(10, 14) for r in _rows("T", (5, 2), t)])
            _wait_marker_x(page, "T", wait_for(lambda: _latest(srv).get("T", {}).get("x"),
                                               what="T"))
            srv.stop()
            page.wait_for_function("!window.robustloc.connected", timeout=15_000)
            srv2.start()
            _post(srv2, [r for t in range(4) for r in _rows("T", (45, 2), t, shift=40.0)])
            x = wait_for(lambda: _latest(srv2).get("T", {}).get("x"), what="T again")
            _ready(page)
            _wait_marker_x(page, "T", x)
            xs = page.evaluate("() => [...document.querySelectorAll('path.anchor-marker')]"
                               ".map(e => parseFloat(e.getAttribute('data-x')))")
            assert sorted(xs) == [40.0 + a[1] for a in ANCHORS]
            vx, _, vw, _ = _view(page)
            assert vx < 40 and vx + vw > 65
            trail = page.get_attribute('polyline.tag-trail[data-tag="T"]', "points")
            ox, _ = _origin(page)
            assert all(float(p.split(",")[0]) + ox > 35 for p in trail.split()), trail
    finally:
        srv2.stop()
        srv.stop()


def test_map_page_loads_what_was_published_while_it_reconnected(live):
    """Positions solved while the page's WebSocket was down reach the map on reconnect."""
    with _Chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        gate = {"open": True}
        routes = []

        def handler(ws):  # the page's WebSocket, passed through while the gate is open
            if gate["open"]:
                ws.connect_to_server()
                routes.append(ws)
            else:
                ws.close()
        page.route_web_socket("**/ws/positions*", handler)
        page.goto(live.url + "/")
        _ready(page)
        _post(live, [r for t in range(4) for r in _rows("GAP", (5, 2), t)])
        _wait_marker_x(page, "GAP", wait_for(lambda: _latest(live).get("GAP", {}).get("x"),
                                             what="GAP"))
        gate["open"] = False
        for ws in routes:
            ws.close()
        page.wait_for_function("!window.robustloc.connected", timeout=15_000)
        _post(live, [r for t in range(4, 8) for r in _rows("GAP", (20, 2), t)])
        x = wait_for(lambda: (r := _latest(live)["GAP"])["time"] == 7 and r["x"],
                     what="GAP at time 7")
        time.sleep(1)
        gate["open"] = True
        _ready(page)
        _wait_marker_x(page, "GAP", x)


def test_map_page_says_when_the_server_stops_answering(tmp_path):
    """A hung server (SIGSTOP: the connection stays open, nothing answers) is not "live"."""
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv"))])
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.getElementById('conn').textContent == 'live'")
            os.kill(srv.proc.pid, signal.SIGSTOP)
            try:
                page.wait_for_function(
                    "/no answer for \\d+ s/.test(document.getElementById('conn').textContent)",
                    timeout=15_000)
                assert not page.evaluate("window.robustloc.live")
            finally:
                os.kill(srv.proc.pid, signal.SIGCONT)
            page.wait_for_function("document.getElementById('conn').textContent == 'live'",
                                   timeout=15_000)
    finally:
        if srv.proc is not None and srv.proc.poll() is None:
            os.kill(srv.proc.pid, signal.SIGCONT)
        srv.stop()


def test_map_page_knows_every_status_and_shows_hpl(live):
    """Every status of robustloc.status has a colour and a legend entry, the page's usable
    set is status.USABLE; hpl in the table (finite, infinite, none) and as a circle."""
    from robustloc import status

    rows = []
    for t in range(3):
        rows += _rows("H", (5, 2), t)  # ok, finite hpl
        rows += _rows("U", (5, 2), t, which=("1", "2", "3"), noise=False)  # unverified
        rows += _rows("I", (5, 2), t, which=("1",))  # insufficient_anchors: no hpl
    _post(live, rows)
    latest = wait_for(lambda: (r := _latest(live)) and all(k in r for k in "HUI") and r,
                      what="H, U, I")
    assert (latest["U"]["status"], latest["I"]["status"]) == ("unverified",
                                                              "insufficient_anchors")
    with _Chromium() as browser:
        page = _open(browser, live.url + "/")
        consts = page.evaluate("() => ({colors: Object.keys(COLORS), usable: [...USABLE]})")
        assert sorted(consts["colors"]) == sorted(status.ALL)
        assert sorted(consts["usable"]) == sorted(status.USABLE)
        legend = page.evaluate("() => [...document.querySelectorAll('#legend [data-status]')]"
                               ".map(e => e.dataset.status)")
        assert sorted(legend) == sorted(status.ALL)
        page.wait_for_function("document.querySelectorAll('#tagtable tr').length >= 3")
        rows = _table(page)
        head = page.evaluate("() => [...document.querySelectorAll('#tagtable')[0]"
                             ".closest('table').tHead.rows[0].cells].map(c => c.textContent)")
        hpl = head.index("hpl (m)")
        assert rows["H"]["cells"][hpl] == f"{latest['H']['hpl']:.2f}"
        assert rows["U"]["cells"][hpl] == "∞"
        assert rows["I"]["cells"][hpl] == "—"
        circle = page.locator('circle.tag-hpl[data-tag="H"]')
        assert circle.is_visible() or latest["H"]["hpl"] < 0.5
        assert float(circle.get_attribute("r")) == pytest.approx(latest["H"]["hpl"])
        assert not page.locator('circle.tag-hpl[data-tag="U"]').is_visible()
        assert "protection level" in page.inner_text("#note")
        # the age column stays in the panel, next to a long status name
        box = page.locator('#tagtable tr[data-tag="I"] td:last-child').bounding_box()
        aside = page.locator("aside").bounding_box()
        assert box["x"] + box["width"] <= aside["x"] + aside["width"]


def test_map_page_ages_tags_by_when_the_server_solved_them(tmp_path):
    """A tag's age on the map is the time since the server solved its latest row
    (``solved_at``), whatever its device's clock says: it was the device's time, so a
    gateway clock 30 s behind made a tag updated every half second "silent" and faded,
    and a page opened now showed a tag silent for 25 s as fresh when the others were
    silent too (the map review).  Here: OLD solved 4 s before NEW; SKEW's times are
    Unix seconds 30 s behind and DEVICE's small device times, both solved now."""
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--idle-flush", "0.3"])
    try:
        srv.start()
        _post(srv, [r for k in range(3) for r in _rows("OLD", (3, 2), k)])
        wait_for(lambda: len(_latest(srv)) == 1, what="OLD solved")
        time.sleep(4)
        now = time.time()
        rows = []
        for k in range(3):
            rows += _rows("SKEW", (8, 2), now - 30 + k) + _rows("DEVICE", (13, 2), 5 + k)
        _post(srv, rows)
        wait_for(lambda: len(_latest(srv)) == 3, what="three tags")
        latest = _latest(srv)
        assert latest["OLD"]["solved_at"] < latest["SKEW"]["solved_at"] - 3.5
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.querySelectorAll('#tagtable tr').length == 3")
            ages = page.evaluate("() => Object.fromEntries([...window.robustloc.tags.values()]"
                                 ".map(t => [t.tag, (Date.now() - t.seen) / 1000]))")
            assert ages["OLD"] == pytest.approx(time.time() - latest["OLD"]["solved_at"],
                                                abs=1.5)
            assert ages["OLD"] >= 4
            # each tag's age is the time since the server solved it (as OLD's above), not
            # its device clock's (SKEW's reads 30 s behind); "< 3 s" also timed the page's
            # opening, 3.3 s on a loaded machine (a full suite beside a report run)
            t_eval = time.time()
            for tag in ("SKEW", "DEVICE"):
                assert ages[tag] == pytest.approx(t_eval - latest[tag]["solved_at"], abs=1.5)
                assert ages[tag] < ages["OLD"] - 3.5
            table = _table(page)
            assert "stale" not in table["SKEW"]["cls"]
            assert page.get_attribute('circle.tag-marker[data-tag="SKEW"]',
                                      "data-stale") == "0"
            # live rows too: SKEW's next row (30 s behind on its clock) is current
            t_new = round(time.time() - 27, 3)
            _post(srv, _rows("SKEW", (8.5, 2), t_new))
            page.wait_for_function("t => window.robustloc.tags.get('SKEW').last.time === t",
                                   arg=t_new, timeout=15_000)
            age = page.evaluate("() => (Date.now() - window.robustloc.tags.get('SKEW').seen)"
                                " / 1000")
            assert age < 3
    finally:
        srv.stop()


def test_map_page_points_to_tags_outside_the_view(live):
    """A usable fix outside the anchors' area gets an arrow at the edge of the map."""
    _post(live, [r for t in range(3) for r in _rows("FAR", (60, 2), t)])
    wait_for(lambda: _latest(live).get("FAR"), what="FAR")
    with _Chromium() as browser:
        page = _open(browser, live.url + "/")
        arrow = page.locator('g.offmap-marker[data-tag="FAR"]')
        arrow.wait_for(state="visible", timeout=10_000)
        box, svg = arrow.bounding_box(), page.locator("svg#map").bounding_box()
        assert svg["x"] <= box["x"] and box["x"] + box["width"] <= svg["x"] + svg["width"]
        assert box["x"] > svg["x"] + svg["width"] / 2  # on the right, towards x = 60 m
        assert "FAR" in arrow.text_content()


def test_map_page_token_from_the_address_does_not_lock_out(tmp_path):
    """A wrong #token= is stored and removed from the address: the typed token wins."""
    token = "s3cret"
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv"))],
                        env={"ROBUSTLOC_TOKEN": token})
    try:
        srv.start()
        with _Chromium() as browser:
            page = browser.new_page()
            page.goto(srv.url + "/#token=wrong")
            page.locator("#login").wait_for(state="visible", timeout=15_000)
            assert "token=" not in page.url
            page.fill("#tokeninput", token)
            page.click("#login button")
            _ready(page)
            assert not page.is_visible("#login")
            page.reload()  # the typed token is kept for the tab
            _ready(page)
    finally:
        srv.stop()


def test_map_page_tag_table_sorts_naturally_and_says_when_cut(live):
    """Tags in natural order (T2 before T10); more than 200: "200 of N shown"."""
    _post(live, [r for k in range(205) for r in _rows(f"N{k}", (1 + k % 24, 2), 0)])
    wait_for(lambda: sum(t.startswith("N") for t in _latest(live)) == 205, what="205 tags")
    tags = list(_latest(live))
    with _Chromium() as browser:
        page = _open(browser, live.url + "/")
        page.wait_for_function("document.querySelectorAll('#tagtable tr').length == 200")
        shown = page.evaluate("() => [...document.querySelectorAll('#tagtable tr')]"
                              ".map(r => r.dataset.tag)")

        def natural(s: str) -> list:
            import re
            return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]
        assert shown == sorted(tags, key=natural)[:200]
        assert shown.index("N2") < shown.index("N10")
        assert page.inner_text("#ntags") == f"(200 of {len(tags)} shown)"


def test_map_page_loads_cleanly_with_a_scale_and_fits_a_phone(live):
    """No failed request or console error on load (the favicon), a scale bar in metres,
    and at 390 px the map takes the width with the panel below it."""
    log: list = []
    with _Chromium() as browser:
        page = _open(browser, live.url + "/", log=log)
        time.sleep(2.5)  # a panel refresh and a heartbeat
        assert not log, log
        scale = page.inner_text("#scalebar")
        assert scale.endswith(" m") and float(scale[:-2]) > 0
        width = page.evaluate("document.querySelector('#scalebar .bar').getBoundingClientRect()"
                              ".width")
        assert 40 < width < 300
        phone = _open(browser, live.url + "/", width=390, height=844)
        svg = phone.locator("svg#map").bounding_box()
        aside = phone.locator("aside").bounding_box()
        assert svg["width"] >= 380 and svg["height"] >= 300
        assert aside["y"] >= svg["y"] + svg["height"] - 1


# -- a hostile review of the map page: each test below failed on the page before ---------

def _state(page, expr: str):
    return page.evaluate(f"() => {expr}")


def _errors(log: list) -> list:
    """Page errors and console errors (a failed request's console line aside)."""
    return [e for e in log if e[0] == "pageerror" or (e[0] == "console" and not
            e[2].startswith("Failed to load resource"))]


def test_map_page_refuses_a_token_it_cannot_send(tmp_path):
    """A token with a character outside ISO-8859-1 (or a NUL) cannot travel in a header:
    fetch() threw, the page died for good (the token stayed in the tab).  Now it is a
    wrong token: never sent nor kept, the login form says why, a reload recovers."""
    token = "s3cret"
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv"))],
                        env={"ROBUSTLOC_TOKEN": token})
    open_srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "b.csv"))])
    log: list = []
    try:
        srv.start()
        open_srv.start()
        with _Chromium() as browser:
            page = browser.new_page()
            page.on("pageerror", lambda e: log.append(("pageerror", str(e))))
            page.goto(srv.url + "/#token=p%C3%A4ss%E2%82%AC")
            page.locator("#login").wait_for(state="visible", timeout=15_000)
            assert "cannot hold" in page.inner_text("#loginerr")
            assert "token=" not in page.url
            assert _state(page, "sessionStorage.getItem('robustloc-token')") is None
            page.reload()  # nothing bad kept: the form again, no error
            page.locator("#login").wait_for(state="visible", timeout=15_000)
            for typed in ("pass€word", "a\x00b"):  # typed: refused at once, not stored
                page.fill("#tokeninput", typed)
                page.click("#login button")
                page.wait_for_function("/cannot hold/.test(document.getElementById("
                                       "'loginerr').textContent)", timeout=5_000)
                assert page.is_visible("#login")
                assert _state(page, "sessionStorage.getItem('robustloc-token')") is None
            page.fill("#tokeninput", token)
            page.click("#login button")
            _ready(page)
            # a server without a token: the page works, the bad token is not sent
            page2 = browser.new_page()
            page2.on("pageerror", lambda e: log.append(("pageerror", str(e))))
            page2.goto(open_srv.url + "/#token=a%00b")
            _ready(page2)
            assert "cannot hold" in page2.inner_text("#tokenmsg")
            assert not page2.is_visible("#login")
    finally:
        open_srv.stop()
        srv.stop()
    assert not log, log


def test_map_page_start_up_retries_until_the_server_answers(live):
    """The first /api/latest gets no answer (slower than the page's 4 s limit): the page
    said "error: signal is aborted" and stayed dead.  Now it says it retries, and goes
    live when the server answers."""
    held: list = []

    def first_hangs(route):
        if not held:
            held.append(route)  # never answered: the page aborts it after 4 s
        else:
            route.continue_()
    with _Chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.route("**/api/latest", first_hangs)
        page.goto(live.url + "/")
        page.wait_for_function(
            "/server not answering .*retrying in \\d+ s/.test("
            "document.getElementById('conn').textContent)", timeout=15_000)
        _ready(page, timeout=20_000)
        _post(live, [r for t in range(3) for r in _rows("LATE", (7, 2), t)])
        _wait_marker_x(page, "LATE", wait_for(lambda: _latest(live).get("LATE", {}).get("x"),
                                              what="LATE"))
        page.wait_for_function("document.getElementById('conn').textContent == 'live'",
                               timeout=10_000)


UTM0 = (500_000.0, 5_400_000.0)
UTM = [(a, UTM0[0] + x, UTM0[1] + y) for a, x, y in ANCHORS]


def _rows_at(anchors, tag: str, pt: tuple[float, float], t: float) -> list[dict]:
    return [{"time": float(t), "tag": tag, "anchor": a,
             "range": float(np.hypot(x - pt[0], y - pt[1]) + 0.01 * (i % 3))}
            for i, (a, x, y) in enumerate(anchors)]


def _write(path: Path, anchors) -> Path:
    path.write_text("anchor,x,y\n" + "".join(f"{a},{x!r},{y!r}\n" for a, x, y in anchors))
    return path


def test_map_page_draws_projected_coordinates_precisely(tmp_path):
    """UTM-like anchors (x ~ 5e5, y ~ 5.4e6 m): drawn in world coordinates, single-
    precision SVG put markers up to 13 px off and flattened the anchors.  Now every marker
    is within 1 px of where it should be, anchors are triangles, the grid is there and
    the table shows whole numbers."""
    srv = ServerProcess(["--anchors", str(_write(tmp_path / "utm.csv", UTM)),
                         "--idle-flush", "0.3"])
    try:
        srv.start()
        pts = {f"U{k}": (UTM0[0] + 1.0 + 2.3 * k, UTM0[1] + 1.0 + 0.2 * k) for k in range(10)}
        _post(srv, [r for t in range(3) for tag, p in pts.items()
                    for r in _rows_at(UTM, tag, p, t)])
        latest = wait_for(lambda: (r := _latest(srv)) and len(r) == 10 and r, what="10 tags")
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            for tag, row in latest.items():
                _wait_marker_x(page, tag, row["x"])
            worst = 0.0
            for tag, row in latest.items():
                want = _screen(page, row["x"], row["y"])
                mb = page.locator(f'circle.tag-marker[data-tag="{tag}"]').bounding_box()
                got = (mb["x"] + mb["width"] / 2, mb["y"] + mb["height"] / 2)
                worst = max(worst, float(np.hypot(got[0] - want[0], got[1] - want[1])))
            assert worst < 1.0, worst
            for a in page.locator("path.anchor-marker").all():
                b = a.bounding_box()
                assert 10 < b["height"] < 16 and 12 < b["width"] < 16, b
            assert page.locator("#gridg line").count() >= 4
            page.wait_for_function("document.querySelectorAll('#tagtable tr').length == 10")
            cells = page.evaluate(
                "() => [...document.querySelectorAll('#tagtable tr')].map(r => [r.dataset.tag,"
                " ...[1, 2].map(i => [r.cells[i].textContent, r.cells[i].scrollWidth <= "
                "r.cells[i].clientWidth, r.cells[i].title])])")
            for tag, (xs, xfits, xtitle), (ys, yfits, ytitle) in cells:
                assert xs == f"{latest[tag]['x']:.2f}" and ys == f"{latest[tag]['y']:.2f}"
                assert xfits and yfits, (tag, xs, ys)
                assert float(xtitle) == latest[tag]["x"] and float(ytitle) == latest[tag]["y"]
    finally:
        srv.stop()


def test_map_page_survives_anchors_far_out(tmp_path):
    """Anchors at x ~ 1e17 m (finite, accepted): the grid loop `x += step` never ended and
    froze the tab.  Now the page loads, draws a bounded grid and keeps answering."""
    far = [(a, 1e17 + 16.0 * i, y) for i, (a, _, y) in enumerate(ANCHORS)]
    srv = ServerProcess(["--anchors", str(_write(tmp_path / "far.csv", far))])
    try:
        srv.start()
        with _Chromium() as browser:
            page = browser.new_page(viewport={"width": 1280, "height": 720})
            page.goto(srv.url + "/", wait_until="commit")
            _ready(page, timeout=20_000)
            assert 0 < page.locator("#gridg line").count() <= 400
            assert page.locator("path.anchor-marker").count() == 6
            page.wait_for_function("document.getElementById('conn').textContent == 'live'",
                                   timeout=10_000)
    finally:
        srv.stop()


@pytest.mark.parametrize("extent", ["0,0,40,25", "0,0,1e7,5e6"])
def test_map_page_labels_keep_their_size_on_a_huge_map(tmp_path, extent):
    """Labels were sized in metres (10 px times the metres per pixel): past ~1 000 m per
    pixel (a mistyped --floorplan-extent) Chromium's cap on a font size shrank them to
    1 px (the map review).  Drawn at their size in pixels and scaled, the axis labels are
    about 11 px high and the anchors' about 13 px, whatever the map's scale."""
    plan = tmp_path / "plan.png"
    _floorplan(plan, tuple(float(v) for v in extent.split(",")))
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--floorplan", str(plan), f"--floorplan-extent={extent}"])
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.querySelector('#axes text') && "
                                   "document.querySelector('.anchor-label')", timeout=10_000)
            px = page.evaluate("() => [document.querySelector('#axes text'), "
                               "document.querySelector('.anchor-label')]"
                               ".map(e => e.getBoundingClientRect().height)")
            assert 9 <= px[0] <= 14 and 11 <= px[1] <= 16, px
    finally:
        srv.stop()


def test_map_page_keeps_trails_when_the_floor_plan_fails(tmp_path):
    """The plan's file is deleted after the start (the server answers 404): every failed
    load reset the page's idea of the map, and the next panel refresh wiped every tag's
    trail.  Now the plan is retried without touching the trails, and said missing."""
    extent = (-2.0, -2.0, 27.0, 6.0)
    plan = tmp_path / "plan.png"
    _floorplan(plan, extent)
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--idle-flush", "0.3", "--floorplan", str(plan),
                         "--floorplan-extent=" + ",".join(map(str, extent))])
    try:
        srv.start()
        plan.unlink()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            for t in range(6):
                _post(srv, _rows("W", (2 + 3 * t, 2), t))
                time.sleep(0.3)
            x = wait_for(lambda: (r := _latest(srv).get("W", {})).get("time") == 5 and r["x"],
                         what="W at time 5")
            _wait_marker_x(page, "W", x)
            n = []
            for _ in range(10):  # several panel refreshes and plan retries, no new data
                n.append(_state(page, "window.robustloc.tags.get('W').trail.length"))
                time.sleep(0.5)
            assert min(n) == max(n) >= 5, n
            points = page.get_attribute('polyline.tag-trail[data-tag="W"]', "points")
            assert len(points.split()) == n[-1]
            msg = page.inner_text("#planmsg")
            assert "Floor plan missing" in msg and "404" in msg, msg
    finally:
        srv.stop()


def test_map_page_reconnects_a_silently_dead_websocket(live):
    """The positions WebSocket dies without a close (a proxy dropped it): the page said
    "live" while positions stopped.  Now it notices (the server's position count grows,
    nothing arrives), reconnects, says so, and the marker follows again."""
    servers: list = []

    def handler(ws):
        s = ws.connect_to_server()
        s.on_close(lambda code, reason: None)  # the page is not told when it closes
        servers.append(s)
    with _Chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.route_web_socket("**/ws/positions*", handler)
        page.goto(live.url + "/")
        _ready(page)
        _post(live, [r for t in range(3) for r in _rows("HALF", (3, 2), t)])
        _wait_marker_x(page, "HALF", wait_for(lambda: _latest(live).get("HALF", {}).get("x"),
                                              what="HALF"))
        servers[0].close()  # gone, and the page does not know
        end = time.monotonic() + 25
        for t in range(3, 100):  # the tag walks on: one fix every 0.5 s
            _post(live, _rows("HALF", (3 + 0.3 * (t - 2), 2), t))
            # (waiting through Playwright: its WebSocket route handler runs meanwhile)
            page.wait_for_timeout(500)
            x = _latest(live)["HALF"]["x"]
            if len(servers) > 1 and page.evaluate(
                    "(x) => Math.abs(parseFloat(document.querySelector('circle.tag-marker"
                    "[data-tag=HALF]').getAttribute('data-x')) - x) < 1e-6", x):
                break
            assert time.monotonic() < end, "the page never reconnected"
        assert _state(page, "window.robustloc.reconnects") >= 1
        assert "stopped arriving" in page.inner_text("#connnote")
        page.wait_for_function("document.getElementById('conn').textContent == 'live'",
                               timeout=10_000)


def test_map_page_handles_thousands_of_tags(tmp_path):
    """3 000 tags (the page used to stall seconds at 5 000): all drawn where the API says
    after the load and after a live block moving every tag.  Timing is printed, not
    asserted (see /work/fuzz_map/r07_many_tags.py for the measurement)."""
    n = 3000
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--idle-flush", "0.3"])

    def block(t: int) -> list[dict]:
        return [r for k in range(n) for r in _rows(
            f"M{k}", (1 + (k % 230) * 0.1 + t * 0.05, 0.5 + (k // 230) * 0.2), t)]
    check = """(want) => { let bad = 0;
        for (const [tag, x, y] of want) {
          const e = document.querySelector(`circle.tag-marker[data-tag="${tag}"]`);
          if (!e || Math.abs(parseFloat(e.getAttribute('data-x')) - x) > 1e-6 ||
              Math.abs(parseFloat(e.getAttribute('data-y')) - y) > 1e-6) bad++; }
        return bad; }"""
    try:
        srv.start()
        _post(srv, block(0))
        wait_for(lambda: len(_latest(srv)) == n, timeout=60, what=f"{n} tags")
        with _Chromium() as browser:
            t0 = time.monotonic()
            page = _open(browser, srv.url + "/")
            page.wait_for_function(f"document.querySelectorAll('circle.tag-marker').length"
                                   f" == {n}", timeout=30_000)
            print(f"{n} tags: all markers {time.monotonic() - t0:.1f} s after opening")
            want = [[r["tag"], r["x"], r["y"]] for r in _latest(srv).values()]
            assert page.evaluate(check, want) == 0
            t1 = time.monotonic()
            _post(srv, block(1))
            wait_for(lambda: all(r["time"] == 1 for r in _latest(srv).values()), timeout=60,
                     what="block 1 solved")
            want = [[r["tag"], r["x"], r["y"]] for r in _latest(srv).values()]
            page.wait_for_function(check.replace("return bad;", "return bad == 0;"),
                                   arg=want, timeout=30_000)
            print(f"live block of {n} tags drawn {time.monotonic() - t1:.1f} s after posting")
            assert page.inner_text("#ntags") == f"(200 of {n} shown)"
    finally:
        srv.stop()


def test_map_page_marks_a_tag_without_a_fix(live):
    """A tag whose latest row has no position (insufficient_anchors) was drawn at its old
    place as if current.  Now: hollow grey at its last fix, "no fix, last fix N s ago"
    beside the name; the table gives the status and that fix's coordinates and age."""
    with _Chromium() as browser:
        page = _open(browser, live.url + "/")
        _post(live, [r for t in range(3) for r in _rows("ANOFIX", (5, 2), t)])
        fix = wait_for(lambda: (r := _latest(live).get("ANOFIX", {})).get("time") == 2 and r,
                       what="ANOFIX fix")
        _wait_marker_x(page, "ANOFIX", fix["x"])
        for t in range(3, 6):  # walked away: one anchor hears it
            _post(live, _rows("ANOFIX", (20, 2), t, which=("5",)))
        row = wait_for(lambda: (r := _latest(live)["ANOFIX"])["time"] == 5 and r,
                       what="ANOFIX no fix")
        assert row["status"] == "insufficient_anchors" and row["x"] is None
        marker = 'circle.tag-marker[data-tag="ANOFIX"]'
        page.wait_for_function(f"document.querySelector('{marker}')"
                               ".getAttribute('data-look') == 'nofix'", timeout=10_000)
        assert float(page.get_attribute(marker, "data-x")) == pytest.approx(fix["x"])
        assert page.get_attribute(marker, "data-status") == "insufficient_anchors"
        assert page.get_attribute(marker, "fill") == "#fff"
        label = page.evaluate("() => [...document.querySelectorAll('text.tag-label')]"
                              ".map(e => e.textContent).find(t => t.startsWith('ANOFIX'))")
        assert "no fix, last fix" in label
        page.wait_for_function("(document.querySelector('#tagtable tr[data-tag=ANOFIX]') || "
                               "{}).className == 'nofix'", timeout=5_000)
        cells = _table(page)["ANOFIX"]["cells"]
        assert cells[1] == f"{fix['x']:.2f}" and cells[4] == "insufficient_anchors"
        assert page.locator('#looks [data-look="nofix"]').count() == 1
        assert "no fix" in page.inner_text("#note")
        # a page opened now draws it the same (its snapshot had only the latest row:
        # no marker, and "no fix yet"; the map review)
        assert _latest(live)["ANOFIX"]["fix_x"] == pytest.approx(fix["x"])
        fresh = _open(browser, live.url + "/")
        fresh.wait_for_function(f"(document.querySelector('{marker}') || "
                                "{getAttribute: () => null}).getAttribute('data-look') == "
                                "'nofix'", timeout=10_000)
        assert float(fresh.get_attribute(marker, "data-x")) == pytest.approx(fix["x"])
        cells = _table(fresh)["ANOFIX"]["cells"]
        assert cells[1] == f"{fix['x']:.2f}" and cells[-1] != "—"


def test_map_page_anchor_table_fits_long_ids_and_is_accessible(tmp_path):
    """128-character anchor ids pushed the anchor table's columns out of the panel.  Also
    the basics of accessibility: the map is an image with a name, the connection state is
    announced, the token field has a label."""
    ids = [(f"{i + 1}-" + "anchor-on-the-second-floor-east-wing-" * 4)[:128]
           for i in range(len(ANCHORS))]
    long = [(ids[i], x, y) for i, (_, x, y) in enumerate(ANCHORS)]
    srv = ServerProcess(["--anchors", str(_write(tmp_path / "long.csv", long))])
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.querySelectorAll('#anchortable tr').length == 6")
            geo = page.evaluate(
                "() => ({aside: document.querySelector('aside').getBoundingClientRect().right,"
                " sw: document.querySelector('aside').scrollWidth, cw: document.querySelector("
                "'aside').clientWidth, right: [...document.querySelectorAll('#anchortable tr')]"
                ".map(r => r.cells[3].getBoundingClientRect().right), title: document."
                "querySelector('#anchortable td').title})")
            assert max(geo["right"]) <= geo["aside"], geo
            assert geo["sw"] <= geo["cw"], geo
            assert geo["title"] == ids[0]
            a11y = page.evaluate(
                "() => ({role: document.getElementById('map').getAttribute('role'),"
                " label: document.getElementById('map').getAttribute('aria-label'),"
                " live: document.getElementById('conn').getAttribute('aria-live'),"
                " input: !!document.querySelector('label[for=tokeninput]')})")
            assert a11y["role"] == "img" and a11y["label"]
            assert a11y["live"] == "polite" and a11y["input"]
    finally:
        srv.stop()


def test_map_page_ignores_odd_values_from_the_server(live):
    """Rows that are not objects, covariances that are not covariances or overflow, and
    coordinates of 1e308 (pushed into the page's real WebSocket): the table stopped
    updating (an exception every second) and SVG attributes got NaN.  Now such rows are
    ignored and counted, such ellipses not drawn, such coordinates kept finite."""
    import json
    socks: list = []

    def handler(ws):
        ws.connect_to_server()
        socks.append(ws)
    base = {"method": "nls", "n_used": 6, "sigma0": 0.01, "excluded": "", "cov_xy": 0.0}
    odd = [None, 5, "str", [1, 2], {"tag": None, "time": 1.0},
           dict(base, time=1.0, tag="ODD_H", x=1e308, y=-1e308, status="extrapolated",
                hpl=1e308, cov_xx=1.0, cov_yy=1.0),
           dict(base, time=1.0, tag="ODD_C", x=5.0, y=2.0, status="ok", hpl=1.0,
                cov_xx=1e300, cov_yy=1e300, cov_xy=1e300),
           dict(base, time=1.0, tag="ODD_N", x=6.0, y=2.0, status="ok", hpl=1.0,
                cov_xx=-4.0, cov_yy=-1.0),
           dict(base, time=1.0, tag="ODD_P", x=7.0, y=2.0, status="ok", hpl=1.0,
                cov_xx=1.0, cov_yy=1.0, cov_xy=3.0)]
    log: list = []
    with _Chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 720})
        page.on("console", lambda m: log.append(("console", m.type, m.text))
                if m.type == "error" else None)
        page.on("pageerror", lambda e: log.append(("pageerror", str(e))))
        page.route_web_socket("**/ws/positions*", handler)
        page.goto(live.url + "/")
        _ready(page)
        socks[-1].send(json.dumps(odd))
        time.sleep(1.5)  # a table refresh (every second) after the odd rows
        _post(live, [r for t in range(3) for r in _rows("AODD", (9, 2), t)])
        page.wait_for_selector('#tagtable tr[data-tag="AODD"]', timeout=10_000)
        assert _state(page, "window.robustloc.ignored") == 5
        for tag in ("ODD_C", "ODD_N", "ODD_P"):  # overflowing, negative, not PSD
            assert page.locator(f'circle.tag-marker[data-tag="{tag}"]').count() == 1
            assert page.locator(f'ellipse.tag-ellipse[data-tag="{tag}"]').count() == 0
        attrs = page.evaluate("() => [...document.querySelectorAll('#map [data-tag]')].flatMap("
                              "e => [...e.attributes].map(a => a.value))")
        assert not [a for a in attrs if "NaN" in a or "Infinity" in a]
        page.locator('g.offmap-marker[data-tag="ODD_H"]').wait_for(state="visible",
                                                                   timeout=5_000)
    assert not _errors(log), log


def test_map_page_says_when_the_mqtt_broker_is_not_connected(tmp_path):
    """``--mqtt`` where no broker listens: the page says the gateways' rows are not
    arriving (from ``/api/status``'s ``mqtt``), and says nothing once it is connected."""
    from robustloc.service.launch import MosquittoProcess, free_port

    if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
        pytest.skip("the mosquitto binary is missing (apt-get install mosquitto)")
    port = free_port()
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--mqtt", f"127.0.0.1:{port}"])
    broker = MosquittoProcess(port=port)
    try:
        srv.start()
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function(
                "/MQTT broker 127.0.0.1:\\d+ not connected \\(cannot reach the broker\\)/"
                ".test(document.getElementById('mqttmsg').textContent)", timeout=30_000)
            broker.start()  # the service connects (retries every 1-10 s); the panels poll
            page.wait_for_function("document.getElementById('mqttmsg').textContent === ''",
                                   timeout=40_000)
    finally:
        broker.stop()
        srv.stop()


def test_map_page_shows_invisible_and_bidirectional_characters_of_ids(tmp_path):
    """An id holding U+202E (right-to-left override) was drawn as the override made it
    look: "A-7\\u202Egnp.exe" read "A-7exe.png" in the table and on the map, and the
    override ran over the rest of its label; a zero-width space made two ids look alike
    (the map review's leftover).  The page shows each such character as <U+XXXX> in the
    table, the labels and the anchor table; ``data-tag`` keeps the id as sent."""
    spoof, twin = "A-7\u202egnp.exe", "A-\u200b8"
    anchors = [("Z\u202eA", x, y) if i == 0 else (a, x, y)
               for i, (a, x, y) in enumerate(ANCHORS)]
    srv = ServerProcess(["--anchors", str(_write(tmp_path / "bidi.csv", anchors)),
                         "--idle-flush", "0.3"])
    try:
        srv.start()
        rows = [dict(r, anchor=anchors[i % len(anchors)][0]) for i, r in
                enumerate(_rows(spoof, (4, 3), 0))] + [
            dict(r, anchor=anchors[i % len(anchors)][0]) for i, r in
            enumerate(_rows(twin, (6, 3), 0))]
        _post(srv, rows)
        wait_for(lambda: {spoof, twin} <= set(_latest(srv)), what="both tags")
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.querySelectorAll('#tagtable tr').length == 2")
            table = _table(page)
            assert table[spoof]["cells"][0] == "A-7<U+202E>gnp.exe"
            assert table[twin]["cells"][0] == "A-<U+200B>8"
            labels = page.evaluate("() => [...document.querySelectorAll('text.tag-label')]"
                                   ".map(e => e.textContent)")
            assert sorted(labels) == ["A-7<U+202E>gnp.exe", "A-<U+200B>8"]
            anchor_labels = page.evaluate(
                "() => [...document.querySelectorAll('text.anchor-label')].map(e => "
                "e.textContent)")
            assert "Z<U+202E>A" in anchor_labels
            page.wait_for_function("document.querySelectorAll('#anchortable tr').length == "
                                   f"{len(anchors)}")
            cell = page.evaluate("() => document.querySelector('#anchortable td').textContent")
            assert cell == "Z<U+202E>A"
    finally:
        srv.stop()
