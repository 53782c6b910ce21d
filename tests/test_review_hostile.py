"""``livecap review`` under attack (issue 36 item 2) and shared by several tabs (item 12), against a
real server process: what a foreign web page, a DNS-rebinding page or a careless client can send
must neither change nor read the session; malformed bodies get a 400 naming the field."""

from __future__ import annotations

import asyncio
import json

import pytest

from tests.review_server import ROOT

EVIL = "http://evil.example"


@pytest.fixture
def server(review_server):
    return review_server


def snapshot(server):
    status, csv = server.request("/export/weights.csv")
    assert status == 200
    return csv, server.request("/api/curves")[1]["version"], server.request("/export/markers.json")[1]


def raw(server, path, data: bytes | None, headers: dict):
    """(status, body) of a request with exactly these headers (no token unless given)."""
    return server.raw(path, data, headers)[:2]


EDIT = json.dumps({"frame": 500, "weights": {"jawOpen": 0.9}, "range": [450, 549]}).encode()


def test_foreign_pages_can_neither_change_nor_read_the_session(server):
    before = snapshot(server)
    host = server.base.split("//", 1)[1]
    ok = {"X-Livecap-Token": server.token}
    attacks = [  # what a page the user visits can make the browser send, and worse
        ("/api/edit", EDIT, {"Content-Type": "text/plain", "Origin": EVIL}),  # a simple CORS request
        ("/api/edit", EDIT, {"Content-Type": "text/plain", "Origin": EVIL, **ok}),  # even knowing the token
        ("/api/edit", EDIT, {"Content-Type": "application/json", "Origin": EVIL, **ok}),
        ("/api/edit", EDIT, {"Content-Type": "text/plain", **ok}),  # JSON bodies only
        ("/api/edit", EDIT, {"Content-Type": "application/json"}),  # no token
        ("/api/edit", EDIT, {"Content-Type": "application/json", "X-Livecap-Token": "guess"}),
        ("/api/undo", b"{}", {"Content-Type": "text/plain", "Origin": EVIL}),
        ("/api/undo", b"{}", {"Content-Type": "application/json", "Origin": "null", **ok}),
        ("/api/pose", b'{"frame": 1, "pins": [{"vertex": 1, "goal": [0, 0, 0]}], "commit": true, "range": [0, 9]}',
         {"Content-Type": "text/plain", "Origin": EVIL}),
        ("/api/markers", b'{"frame": 1, "label": "x", "triangle": [0, 1, 2], "point": [0, 0, 0]}',
         {"Content-Type": "text/plain", "Origin": EVIL}),
    ]
    for path, data, headers in attacks:
        status, body = raw(server, path, data, headers)
        assert status in (403, 415), (path, headers, status, body[:200])
    reads = [  # DNS rebinding: the page's own origin, but Host names the attacker's domain
        ("/export/weights.csv", {"Host": "attacker.example", **ok}),
        ("/export/weights.csv", {"Host": f"attacker.example:{host.rsplit(':', 1)[1]}", **ok}),
        ("/api/curves", {"Host": "attacker.example"}),
        ("/?token=" + server.token, {"Host": "attacker.example"}),
        ("/export/weights.csv", {}),  # no token
        ("/export/markers.json", {"Host": "attacker.example", **ok}),
        ("/api/curves", {"Origin": EVIL, **ok}),
        ("/", {}),  # the page without the token gives nothing away
    ]
    for path, headers in reads:
        status, body = raw(server, path, None, headers)
        assert status == 403 and b"browDownLeft" not in body and server.token.encode() not in body, (path, headers)
    assert snapshot(server) == before
    # the page's own names are served (Host with the port, any loopback spelling)
    assert raw(server, "/api/meta", None, {"Host": host.replace("127.0.0.1", "localhost"), **ok})[0] == 200


def test_the_printed_url_gives_the_page_with_its_token_and_a_cookie(server):
    import http.cookiejar
    import urllib.request

    jar = http.cookiejar.CookieJar()
    opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
    with opener.open(server.url, timeout=60) as r:  # ?token=: the page, and the cookie for later calls
        page = r.read().decode()
    assert f'content="{server.token}"' in page
    with opener.open(server.base + "/export/weights.csv", timeout=60) as r:  # the cookie alone suffices
        assert r.read().startswith(b"frame,time,")


def test_websocket_checks_origin_and_token(server):
    import aiohttp

    async def attempt(url, origin):
        async with aiohttp.ClientSession() as s:
            try:
                async with s.ws_connect(url, origin=origin) as ws:
                    await ws.send_json({"frame": 1, "pins": [{"vertex": 1, "goal": [0, 0, 0]}]})
                    return (await ws.receive_json(timeout=30)).get("frame")
            except aiohttp.WSServerHandshakeError as exc:
                return exc.status

    with_token = f"{server.base}/ws?token={server.token}"
    assert asyncio.run(attempt(with_token, EVIL)) == 403
    assert asyncio.run(attempt(f"{server.base}/ws", server.base)) == 403
    assert asyncio.run(attempt(with_token, server.base)) == 1


BAD = [  # body, the field the one-line error must name
    ('{"frame": 10, "weights": {"jawOpen": NaN}}', "NaN"),
    ('{"frame": 10, "weights": {"jawOpen": 1e308}}', "weights.jawOpen"),
    ('{"frame": 10, "weights": {"jawOpen": -0.5}}', "weights.jawOpen"),
    ('{"frame": 10, "weights": {"jawOpen": "1"}}', "weights.jawOpen"),
    ('{"frame": 10, "weights": [0.5]}', "weights"),
    ('{"frame": 10, "weights": null}', "weights"),
    ('{"frame": Infinity, "weights": {"jawOpen": 0.5}}', "Infinity"),
    ('{"frame": 1e300, "weights": {"jawOpen": 0.5}}', "frame"),
    ('{"frame": "10", "weights": {"jawOpen": 0.5}}', "frame"),
    ('{"frame": 10, "weights": {"jawOpen": 0.5}, "range": [5]}', "range"),
    ('{"frame": 10, "weights": {"jawOpen": 0.5}, "range": [20, 30]}', "range"),
    ("[" * 100000 + "]" * 100000, "body"),
    ('{"a": ' * 50000 + "1" + "}" * 50000, "body"),
    ("[1, 2]", "body"),
    ("{not json", "body"),
]
BAD_POSE = [
    ('{"frame": 10, "pins": [1, 2]}', "pins[0]"),
    ('{"frame": 10, "pins": "chin"}', "pins"),
    ('{"frame": 10, "pins": []}', "pins"),
    ('{"frame": 10, "pins": [{"vertex": 1, "goal": [0, NaN, 0]}]}', "NaN"),
    ('{"frame": 10, "pins": [{"vertex": 1, "goal": [0, 1e308, 0]}]}', "pins[0].goal"),
    ('{"frame": 10, "pins": [{"vertex": 1.5, "goal": [0, 0, 0]}]}', "pins[0].vertex"),
    ('{"frame": 10, "pins": [{"marker": 7, "goal": [0, 0, 0]}]}', "pins[0].marker"),
    ('{"frame": 10, "pins": [{"vertex": 1, "goal": [0, 0, 0]}], "commit": "yes"}', "commit"),
]


BAD_MARKER = [
    ('{"frame": 10, "label": "nope", "triangle": [0, 1, 2], "point": [0, 0, 0]}', "label"),
    ('{"frame": 10, "label": 3, "triangle": [0, 1, 2], "point": [0, 0, 0]}', "label"),
    ('{"frame": 10, "label": "LABEL", "triangle": [0, 1], "point": [0, 0, 0]}', "triangle"),
    ('{"frame": 10, "label": "LABEL", "triangle": [0, 1, 2.5], "point": [0, 0, 0]}', "triangle[2]"),
    ('{"frame": 10, "label": "LABEL", "triangle": [0, 0, 0], "point": [0, 0, 0]}', "triangle"),
    ('{"frame": 10, "label": "LABEL", "triangle": [-1, 99999999, 2], "point": [0, 0, 0]}', "triangle"),
    ('{"frame": 10, "label": "LABEL", "triangle": TRI, "point": [0, NaN, 0]}', "NaN"),
    ('{"frame": 10, "label": "LABEL", "triangle": TRI, "point": [0, 1e308, 0]}', "point"),
    ('{"frame": 10, "label": "LABEL", "triangle": TRI, "point": "chin"}', "point"),
    ('{"frame": -1, "label": "LABEL", "triangle": TRI, "point": [0, 0, 0]}', "frame"),
]


def _marker_cases(server) -> list[tuple[str, str]]:
    from livecap.core.rig import Rig

    label = server.get("/api/meta")["labels"][0]
    tri = str(Rig.load(ROOT / "recordings/demo_rig.npz").triangles[0].tolist())
    return [(t.replace("LABEL", label).replace("TRI", tri), f) for t, f in BAD_MARKER]


@pytest.mark.parametrize("path,cases", [("/api/edit", BAD), ("/api/pose", BAD_POSE), ("/api/markers", None)])
def test_malformed_bodies_get_400_naming_the_field(server, path, cases):
    before = snapshot(server)
    head = {"X-Livecap-Token": server.token, "Content-Type": "application/json"}
    for text, field in cases or _marker_cases(server):
        status, body = raw(server, path, text.encode(), head)
        assert status == 400, (text[:60], status, body[:300])
        error = json.loads(body)["error"]
        assert field in error and "\n" not in error, (text[:60], error)
    for q in ("nan", "inf", "-1", "x"):
        status, body = raw(server, f"/api/keys?max_error={q}", None, head)
        assert status == 400 and "max_error" in json.loads(body)["error"]
    assert snapshot(server) == before


def test_curves_are_strict_json(server):
    head = {"X-Livecap-Token": server.token, "Content-Type": "application/json"}
    nan = b'{"frame": 10, "weights": {"jawOpen": NaN}, "range": [0, 20]}'  # 775 NaN cells on the old server
    assert raw(server, "/api/edit", nan, head)[0] == 400
    status, body = raw(server, "/api/curves", None, head)

    def refuse(name):
        raise ValueError(name)

    assert status == 200 and json.loads(body, parse_constant=refuse)["weights"]


def test_a_tab_cannot_undo_another_tabs_edit(server):
    def edit(client, frame, value, a, b):
        return server.request("/api/edit", {"frame": frame, "weights": {"jawOpen": value}, "range": [a, b]},
                              client=client)

    original = snapshot(server)[0]
    assert edit("tabA", 1000, 0.8, 990, 1010)[0] == 200
    assert edit("tabB", 1005, 0.2, 1000, 1020)[0] == 200  # over A's rows
    after_b = snapshot(server)[0]
    status, r = server.request("/api/undo", {}, client="tabA")
    assert status == 409 and "990..1010" in r["error"]
    assert snapshot(server)[0] == after_b  # refused: B's edit stands
    assert server.request("/api/undo", {}, client="tabC") == (200, None)  # nothing of C's to undo
    assert server.request("/api/undo", {}, client="tabB")[0] == 200
    assert server.request("/api/undo", {}, client="tabA")[0] == 200
    assert snapshot(server)[0] == original
    # edits over other rows undo independently
    assert edit("tabA", 1500, 0.8, 1490, 1510)[0] == 200
    assert edit("tabB", 1700, 0.8, 1690, 1710)[0] == 200
    only_b = server.request("/api/undo", {}, client="tabA")
    assert only_b[0] == 200 and only_b[1]["undo"] == 0 and (only_b[1]["a"], only_b[1]["b"]) == (1490, 1510)
    assert server.request("/api/curves", client="tabB")[1]["undo"] == 1
    assert server.request("/api/undo", {}, client="tabB")[0] == 200
    assert snapshot(server)[0] == original


def test_allowed_hosts_name_this_server_with_its_port():
    from livecap.review.guard import allowed_hosts

    assert allowed_hosts("127.0.0.1", 8765) == {"localhost:8765", "127.0.0.1:8765", "[::1]:8765"}
    assert "[fd00::5]:80" in allowed_hosts("fd00::5", 80) and "box:80" in allowed_hosts("::", 80, ("Box",))
    assert not any(h.startswith("0.0.0.0") for h in allowed_hosts("0.0.0.0", 80))
