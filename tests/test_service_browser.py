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
