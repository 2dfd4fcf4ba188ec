"""The web server over real sockets on 127.0.0.1: the page and its files, the state, live updates, the token,
read-only, and the relay out of a network namespace (through a Unix socket)."""

from __future__ import annotations

import contextlib
import gzip
import http.client
import json
import socket
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bac_cockpit.relay import Relay
from bac_cockpit.server import CockpitError, CockpitServer, check_exposure, is_loopback
from bac_cockpit.state import CockpitState

TOKEN = "s3cret-token-0123456789"


@pytest.fixture
def server() -> Iterator[CockpitServer]:
    srv = CockpitServer(CockpitState(), port=0)
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def get(url: str, headers: dict[str, str] | None = None, method: str = "GET") -> tuple[int, dict[str, str], bytes]:
    req = urllib.request.Request(url, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def base(srv: CockpitServer) -> str:
    return f"http://127.0.0.1:{srv.bound.port}"


def test_the_page_and_every_file_it_needs_are_served_from_here(server: CockpitServer) -> None:
    code, headers, body = get(base(server) + "/")
    assert code == 200 and b"<title>bac cockpit</title>" in body
    assert "script-src 'self'" in headers["Content-Security-Policy"] and headers["Cache-Control"] == "no-store"
    html = body.decode()
    for src in ("static/cockpit.js", "static/cockpit.css", "static/vendor/plotly-cartesian.min.js"):
        assert src in html
        code, h, data = get(base(server) + "/" + src, {"Accept-Encoding": "gzip"})
        assert code == 200 and len(data) > 100, src
        if src.endswith("plotly-cartesian.min.js"):  # 1.5 MB sent gzipped
            assert h["Content-Encoding"] == "gzip" and b"plotly.js" in gzip.decompress(data)[:200]
    assert "https://" not in html and "http://" not in html.replace("http://www.w3.org", "")  # nothing from outside
    assert get(base(server) + "/static/../server.py")[0] == 404


def test_read_only(server: CockpitServer) -> None:
    for method in ("POST", "PUT", "DELETE", "PATCH"):
        assert get(base(server) + "/api/state", method=method)[0] == 405, method


def test_a_dns_rebinding_host_is_refused_without_a_token(server: CockpitServer) -> None:
    conn = http.client.HTTPConnection("127.0.0.1", server.bound.port, timeout=10)
    conn.request("GET", "/api/state", headers={"Host": "attacker.example:8765"})
    assert conn.getresponse().status == 403
    assert get(f"http://localhost:{server.bound.port}/api/health")[0] == 200


def read_events(url: str, want: int, timeout: float = 20.0) -> list[tuple[str, dict[str, Any], float]]:
    """The first ``want`` server-sent events (or those that came before nothing came for ``timeout`` s), with the
    time each arrived."""
    out: list[tuple[str, dict[str, Any], float]] = []
    with contextlib.suppress(TimeoutError), urllib.request.urlopen(url, timeout=timeout) as r:
        event, data = "", []
        for raw in r:
            line = raw.decode().rstrip("\n")
            if line.startswith("event:"):
                event = line[6:].strip()
            elif line.startswith("data:"):
                data.append(line[5:].strip())
            elif not line and data:
                out.append((event, json.loads("".join(data)), time.monotonic()))
                event, data = "", []
                if len(out) >= want:
                    return out
    return out


def test_live_updates_arrive_as_patches_in_order(server: CockpitServer) -> None:
    got: list[Any] = []
    t = threading.Thread(target=lambda: got.extend(read_events(base(server) + "/events", 4)))
    t.start()
    deadline = time.monotonic() + 10
    while not server.hub.clients and time.monotonic() < deadline:
        time.sleep(0.01)
    sent = []
    for i in range(3):
        sent.append(time.monotonic())
        server.apply(lambda st, i=i: st.set_campaign_info({"campaign_id": f"c{i}"}))
    t.join(20)
    assert [e for e, _, _ in got] == ["snapshot", "patch", "patch", "patch"]
    assert [d["campaign"]["campaign_id"] for _, d, _ in got[1:]] == ["c0", "c1", "c2"]
    assert set(got[1][1]) == {"campaign", "version", "mode", "server_wall"}  # only what changed
    assert max(arr - s for (_, _, arr), s in zip(got[1:], sent, strict=True)) < 1.0


def test_exposure_needs_a_token() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.20")
    assert check_exposure("127.0.0.1", "") == ""
    with pytest.raises(CockpitError, match="token"):
        check_exposure("0.0.0.0", "")
    with pytest.raises(CockpitError, match="too short"):
        check_exposure("0.0.0.0", "short")
    auto = check_exposure("0.0.0.0", "auto")
    assert len(auto) >= 16 and auto != check_exposure("0.0.0.0", "auto")
    with pytest.raises(CockpitError):
        CockpitServer(CockpitState(), host="0.0.0.0", port=0)


def test_with_a_token_every_request_needs_it() -> None:
    srv = CockpitServer(CockpitState(), port=0, token=TOKEN)
    srv.start()
    try:
        b = base(srv)
        for path in ("/", "/api/state", "/events", "/static/cockpit.js"):
            assert get(b + path)[0] == 401, path
            assert get(b + path + "?token=wrong-token-wrong-token")[0] == 403, path
        code, headers, _ = get(b + f"/?token={TOKEN}")
        assert code == 200 and "bac_cockpit_token=" in headers["Set-Cookie"] and "HttpOnly" in headers["Set-Cookie"]
        cookie = headers["Set-Cookie"].split(";")[0]
        assert get(b + "/api/state", {"Cookie": cookie})[0] == 200  # the page's own requests carry the cookie
        assert get(b + "/api/state", {"Authorization": f"Bearer {TOKEN}"})[0] == 200
        assert srv.url.endswith(f"/?token={TOKEN}")
    finally:
        srv.stop()


def test_a_taken_port_falls_back_to_a_free_one() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        taken = s.getsockname()[1]
        srv = CockpitServer(CockpitState(), port=taken)
        bound = srv.start()
        try:
            assert bound.fallback_from == taken and bound.port not in (0, taken)
            assert get(f"http://127.0.0.1:{bound.port}/api/health")[0] == 200
        finally:
            srv.stop()


def test_the_relay_publishes_a_cockpit_served_on_a_unix_socket(tmp_path: Path) -> None:
    sock = tmp_path / "c.sock"
    relay = Relay("127.0.0.1", 0, str(sock))
    port = relay.start()
    try:
        code, _, body = get(f"http://127.0.0.1:{port}/")
        assert code == 503 and b"starting" in body  # the cockpit is not there yet
        srv = CockpitServer(CockpitState(), unix_socket=str(sock), serve_tcp=False, token=TOKEN)
        srv.start()
        try:
            assert srv.bound.port == 0 and sock.exists() and (sock.stat().st_mode & 0o077) == 0
            assert get(f"http://127.0.0.1:{port}/api/state")[0] == 401  # the cockpit still checks the token
            code, _, body = get(f"http://127.0.0.1:{port}/api/state?token={TOKEN}")
            assert code == 200 and json.loads(body)["mode"] == "live"
            got = read_events(f"http://127.0.0.1:{port}/events?token={TOKEN}", 1)
            assert got[0][0] == "snapshot"
        finally:
            srv.stop()
    finally:
        relay.stop()


@pytest.mark.slow
def test_a_flood_of_diagnostics_is_sent_at_most_twice_a_second(server: CockpitServer) -> None:
    from bac_cockpit.state import DiagView

    got: list[Any] = []
    t = threading.Thread(target=lambda: got.extend(read_events(base(server) + "/events", 99, timeout=3)))
    t.start()
    deadline = time.monotonic() + 10
    while not server.hub.clients and time.monotonic() < deadline:
        time.sleep(0.01)
    t0 = time.monotonic()
    for i in range(40):  # 40 diagnostics messages in 0.4 s (10x real time)
        v = [DiagView("imu_ingest: imu/data_raw", 0, f"OK {i}", "", {"rate_hz": "400"})]
        server.apply(lambda st, v=v: st.on_diagnostics(v), throttle_s=0.5)
        time.sleep(0.01)
    server.apply(lambda st: st.set_campaign_info({"campaign_id": "after"}))  # not held back by the flood
    t.join(20)
    kinds = [("campaign" if "campaign" in d else "diag") for _, d, _ in got[1:]]
    assert kinds.count("diag") <= 3 and "campaign" in kinds, kinds
    last_diag = [d for _, d, _ in got[1:] if "diagnostics" in d][-1]
    assert last_diag["imu"]["stream"]["message"] == "OK 39"  # the held update sends the latest state
    assert got[kinds.index("campaign") + 1][2] - t0 < 1.5
