"""Live service: the query strings of the GET endpoints (the API review).

A real ``robustloc serve`` on a free loopback port, with a token (so that ``?token=`` is
exercised as a query parameter too), holding the positions of two tags.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("uvicorn")
httpx = pytest.importorskip("httpx")

from _waiting import wait_until  # noqa: E402

from robustloc.service.launch import ServerProcess, read_metric  # noqa: E402

TOKEN = "q-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
XY = {"A1": (0, 0), "A2": (10, 0), "A3": (10, 10), "A4": (0, 10), "A5": (5, 12)}
#: epochs of tag "A" (times 0 .. 59) and of tag "B" (times 0, 10, 20)
N_A = 60
B_TIMES = (0.0, 10.0, 20.0)


def _rows(tag: str, times: tuple[float, ...] | range) -> list[dict]:
    return [{"time": float(t), "tag": tag, "anchor": a,
             "range": float(np.hypot(3 - p[0], 4 - p[1]))}
            for t in times for a, p in XY.items()]


def _metric(url: str, name: str) -> float:
    for line in httpx.get(url + "/metrics", headers=AUTH).text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[-1])
    return 0.0


def _bad_queries(url: str) -> float:
    return _metric(url, 'robustloc_requests_rejected_total{reason="bad_query"}')


@pytest.fixture(scope="module")
def srv(tmp_path_factory) -> Iterator[ServerProcess]:
    d: Path = tmp_path_factory.mktemp("query")
    anchors = d / "anchors.csv"
    anchors.write_text("anchor,x,y\n" + "".join(f"{a},{x},{y}\n" for a, (x, y) in XY.items()))
    s = ServerProcess(["--anchors", str(anchors), "--latency-window", "0",
                       "--idle-flush", "0.3"], env={"ROBUSTLOC_TOKEN": TOKEN})
    s.start()
    try:
        rows = _rows("A", range(N_A)) + _rows("B", B_TIMES)
        r = httpx.post(s.url + "/api/measurements", json=rows, headers=AUTH)
        assert r.status_code == 202 and r.json()["accepted"] == len(rows), r.text
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            got = httpx.get(s.url + "/api/positions?limit=1000", headers=AUTH).json()
            if len(got) == N_A + len(B_TIMES):
                break
            time.sleep(0.2)
        else:
            pytest.fail("the positions were not all solved")
        yield s
    finally:
        s.stop()


def test_limit_keeps_the_latest_rows_and_says_so(srv):
    """``limit`` keeps the latest rows (as before) but said nothing: a query matching more
    rows than ``limit`` lost its earliest silently.  Now ``X-Total-Count`` gives the rows
    matched and ``X-Truncated: true`` marks a body that left some out."""
    u = srv.url
    r = httpx.get(u + "/api/positions?tag=A&limit=10", headers=AUTH)
    assert r.status_code == 200
    assert [p["time"] for p in r.json()] == [float(t) for t in range(N_A - 10, N_A)]
    assert r.headers["x-total-count"] == str(N_A) and r.headers["x-truncated"] == "true"
    # the rest, with a narrower until (as the docs say)
    r = httpx.get(u + f"/api/positions?tag=A&until={N_A - 11}&limit=10", headers=AUTH)
    assert [p["time"] for p in r.json()] == [float(t) for t in range(N_A - 20, N_A - 10)]
    assert r.headers["x-total-count"] == str(N_A - 10)
    # nothing left out: the count, no X-Truncated
    r = httpx.get(u + "/api/positions?since=0&until=1000", headers=AUTH)
    assert len(r.json()) == N_A + len(B_TIMES)
    assert r.headers["x-total-count"] == str(N_A + len(B_TIMES))
    assert "x-truncated" not in r.headers
    r = httpx.get(u + "/api/positions?tag=A&limit=60", headers=AUTH)
    assert len(r.json()) == N_A and "x-truncated" not in r.headers
    r = httpx.get(u + "/api/positions?tag=nobody", headers=AUTH)
    assert r.json() == [] and r.headers["x-total-count"] == "0"


@pytest.mark.parametrize(("path", "name"), [
    ("/api/positions?tags=A", "tags"), ("/api/positions?from=5", "from"),
    ("/api/positions?format=csv", "format"), ("/api/positions?offset=1", "offset"),
    ("/api/positions?tag=A&tag=B", "tag"), ("/api/positions?limit=5&limit=6", "limit"),
    ("/api/latest?tag=A", "tag"), ("/api/anchors?x=1", "x"), ("/api/status?verbose=1", "verbose"),
    ("/metrics?name=robustloc_rows_accepted_total", "name"), ("/floorplan?size=2", "size"),
])
def test_unknown_or_repeated_query_parameters_are_refused(srv, path, name):
    """A misspelled, unknown or repeated parameter was ignored: ``tags=A``, ``from=5``,
    ``format=csv``, ``offset=1`` answered every row, ``tag=A&tag=B`` only B's, and
    ``/api/latest?tag=A`` every tag.  Now ``400`` naming it, counted as ``bad_query``."""
    u = srv.url
    before = _bad_queries(u)
    r = httpx.get(u + path, headers=AUTH)
    assert r.status_code == 400, (path, r.status_code, r.text[:200])
    assert repr(name) in r.json()["error"]
    assert _bad_queries(u) == before + 1
    assert httpx.get(u + "/healthz").status_code == 200


def test_known_query_parameters_still_answer(srv):
    """The parameters each endpoint takes (``token`` among them) answer as before."""
    u = srv.url
    r = httpx.get(u + f"/api/positions?tag=B&since=0&until=100&limit=5&token={TOKEN}")
    assert r.status_code == 200 and [p["time"] for p in r.json()] == list(B_TIMES)
    for path in ("/api/latest", "/api/anchors", "/api/status", "/metrics"):
        assert httpx.get(u + f"{path}?token={TOKEN}").status_code == 200, path
        assert httpx.get(u + path, headers=AUTH).status_code == 200, path
    assert len(httpx.get(u + "/api/latest", headers=AUTH).json()) == 2
    # the token twice: refused as any repeated parameter
    assert httpx.get(u + f"/api/latest?token={TOKEN}&token={TOKEN}").status_code == 400


def test_websocket_positions_refuses_unknown_parameters_at_the_handshake(srv):
    """``/ws/positions?tags=A`` subscribed to every tag; now refused at the handshake with
    HTTP 400 and the reason, counted as ``bad_query``; ``tag``, ``batch``, ``token`` work."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    w = srv.url.replace("http://", "ws://")
    before = _bad_queries(srv.url)
    for q in ("tags=A", "tag=A&tag=B", "bach=1"):
        with pytest.raises(InvalidStatus) as refused:
            connect(w + f"/ws/positions?{q}&token={TOKEN}", open_timeout=10)
        assert refused.value.response.status_code == 400, q
        assert b"bad query" in refused.value.response.body, q
    assert _bad_queries(srv.url) == before + 3
    with connect(w + f"/ws/positions?tag=A&batch=1&token={TOKEN}", open_timeout=10):
        pass


def test_queried_tag_is_trimmed_as_ingest_trims(srv):
    """Ingest stores ``" C "`` as ``C``; ``?tag=%20C`` was not trimmed and found nothing
    (the only test that adds rows: run last, it leaves the others' counts alone)."""
    u = srv.url
    r = httpx.post(u + "/api/measurements", json=_rows(" C ", (30.0,)), headers=AUTH)
    assert r.status_code == 202 and r.json()["accepted"] == len(XY)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        got = httpx.get(u + "/api/positions?tag=C", headers=AUTH).json()
        if got:
            break
        time.sleep(0.2)
    assert [p["time"] for p in got] == [30.0] and got[0]["tag"] == "C"
    for q in ("%20C", "C%20%20", "%09C%20"):
        r = httpx.get(u + f"/api/positions?tag={q}", headers=AUTH)
        assert r.status_code == 200 and r.json() == got, q
    # only spaces: no tag given, as ``?tag=`` is (every tag)
    assert len(httpx.get(u + "/api/positions?tag=%20&limit=1000", headers=AUTH).json()) == \
        N_A + len(B_TIMES) + 1


@pytest.mark.parametrize(("query", "name"), [
    ("bogus=1", "bogus"), ("tag=A", "tag"), ("token=x&token=y", "token"),
])
def test_post_measurements_refuses_unknown_or_repeated_query_parameters(srv, query, name):
    """``POST /api/measurements`` took any query (``?bogus=1`` stored the rows, a
    misspelled option said nothing) while every GET refused it: now ``400`` naming it,
    counted as ``bad_query``, before the body is read; nothing of the body is stored."""
    u = srv.url
    before = _bad_queries(u)
    accepted = read_metric(u, "robustloc_rows_accepted_total", AUTH)
    r = httpx.post(u + f"/api/measurements?{query}", json=_rows("E", (50.0,)), headers=AUTH)
    assert r.status_code == 400, r.text
    assert r.json()["error"].startswith("bad query: ") and repr(name) in r.json()["error"]
    assert _bad_queries(u) == before + 1
    assert read_metric(u, "robustloc_rows_accepted_total", AUTH) == accepted > 0


def test_websocket_measurements_refuses_unknown_parameters_at_the_handshake(srv):
    """``/ws/measurements?bogus=1`` was accepted as ingest; now refused at the handshake
    with HTTP 400 and the reason (as ``/ws/positions``), counted as ``bad_query``."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    w = srv.url.replace("http://", "ws://")
    before = _bad_queries(srv.url)
    for q in (f"bogus=1&token={TOKEN}", f"token={TOKEN}&token={TOKEN}"):
        with pytest.raises(InvalidStatus) as refused:
            connect(w + f"/ws/measurements?{q}", open_timeout=10)
        assert refused.value.response.status_code == 400, q
        assert b"bad query" in refused.value.response.body, q
    assert _bad_queries(srv.url) == before + 2


def test_post_measurements_with_the_token_in_the_query_still_ingests(srv):
    """The parameter the POST takes (``token``) and none at all: accepted as before
    (adds a tag's rows: after the tests that count them)."""
    u = srv.url
    r = httpx.post(u + f"/api/measurements?token={TOKEN}", json=_rows("D", (40.0,)))
    assert r.status_code == 202 and r.json()["accepted"] == len(XY), r.text
    r = httpx.post(u + "/api/measurements", json=_rows("D", (41.0,)), headers=AUTH)
    assert r.status_code == 202 and r.json()["accepted"] == len(XY), r.text
    got = wait_until(lambda: (p := httpx.get(u + "/api/positions?tag=D", headers=AUTH).json())
                     and len(p) == 2 and p, timeout=30, what="tag D's epochs solved")
    assert [p["time"] for p in got] == [40.0, 41.0]
