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
                    vx, vy, vw, vh = map(float, page.locator("svg#map").get_attribute(
                        "viewBox").split())
                    box = page.locator("svg#map").bounding_box()
                    s = min(box["width"] / vw, box["height"] / vh)
                    ox = box["x"] + (box["width"] - vw * s) / 2
                    oy = box["y"] + (box["height"] - vh * s) / 2
                    want = (ox + (row["x"] - vx) * s, oy + (-row["y"] - vy) * s)
                    mb = marker.bounding_box()
                    got = (mb["x"] + mb["width"] / 2, mb["y"] + mb["height"] / 2)
                    assert abs(got[0] - want[0]) < 1.5 and abs(got[1] - want[1]) < 1.5, (
                        tag, got, want)
                    assert page.locator(f'ellipse.tag-ellipse[data-tag="{tag}"]').count() == 1
                # per-anchor health: last heard and rejection rate in the side table
                page.wait_for_function(
                    "document.querySelectorAll('#anchortable tr').length == 10", timeout=10_000)
                time.sleep(2.5)  # one panel refresh after the replay
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
            assert all(float(p.split(",")[0]) > 15 for p in trail.split()), trail
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
            assert [float(img.get_attribute(k)) for k in ("x", "y", "width", "height")] == [
                extent[0], -extent[3], extent[2] - extent[0], extent[3] - extent[1]]
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
            vx, _, vw, _ = map(float, page.get_attribute("svg#map", "viewBox").split())
            assert vx < 40 and vx + vw > 65
            trail = page.get_attribute('polyline.tag-trail[data-tag="T"]', "points")
            assert all(float(p.split(",")[0]) > 35 for p in trail.split()), trail
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


def test_map_page_ages_tags_by_their_own_time(tmp_path):
    """On a page opened now, a tag whose last fix is 17 s (device clock) or 40 s (Unix
    clock) behind is shown that old and faded; the fresh ones are not."""
    srv = ServerProcess(["--anchors", str(_write_anchors(tmp_path / "a.csv")),
                         "--idle-flush", "0.3"])
    try:
        srv.start()
        now = time.time()
        rows = []
        for k in range(4):
            rows += _rows("OLD", (3, 2), k) + _rows("EOLD", (8, 2), now - 43 + k)
            rows += _rows("NEW", (13, 2), 17 + k) + _rows("ENEW", (18, 2), now - 3 + k)
        _post(srv, rows)
        wait_for(lambda: len(_latest(srv)) == 4, what="four tags")
        with _Chromium() as browser:
            page = _open(browser, srv.url + "/")
            page.wait_for_function("document.querySelectorAll('#tagtable tr').length == 4")
            ages = page.evaluate("() => Object.fromEntries([...window.robustloc.tags.values()]"
                                 ".map(t => [t.tag, (Date.now() - t.seen) / 1000]))")
            assert ages["OLD"] == pytest.approx(17, abs=1.5)
            assert ages["NEW"] < 1.5
            assert ages["EOLD"] == pytest.approx(time.time() - (now - 40), abs=3)
            assert ages["ENEW"] < 8
            rows = _table(page)
            assert rows["OLD"]["cells"][-1] in ("16 s", "17 s", "18 s")
            assert "stale" in rows["OLD"]["cls"]
            assert "stale" not in rows["NEW"]["cls"]
            page.wait_for_function("document.querySelector('circle.tag-marker[data-tag=OLD]')"
                                   ".getAttribute('data-stale') == '1'", timeout=5_000)
            for tag, stale in (("EOLD", "1"), ("NEW", "0"), ("ENEW", "0")):
                assert page.get_attribute(f'circle.tag-marker[data-tag="{tag}"]',
                                          "data-stale") == stale
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
