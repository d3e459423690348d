"""Only the operator sees the view: token, Host, Origin, read-only; metadata as text.

Each request is made over a real socket to a served view (no mocks of aiohttp): the page,
its script, the websocket and the frame must each be refused without the run's token,
with a Host other than the served one (DNS rebinding) and, for the websocket and
cross-site requests, with another Origin; anything but GET is refused.
"""

from __future__ import annotations

import base64
import json
import os
import socket

import pytest

from stipi_daemon.app.liveview.server import ViewServer
from stipi_daemon.app.liveview.state import LiveState
from tests.app.liveview._view import get, publish, served, view_info

PATHS = ["/", "/static/view.js", "/static/view.css", "/frame.jpg"]


def _state() -> LiveState:
    state = LiveState(view_info())
    for k in range(5):
        publish(state, k)
    return state


def _host(server: ViewServer) -> str:
    return f"127.0.0.1:{server.port}"


def test_every_path_is_served_with_the_token_and_the_served_host() -> None:
    with served(_state()) as server:
        for path in PATHS:
            status, headers, body = get(server, f"{path}?token={server.token}")
            assert status == 200, path
            assert body
            assert "default-src 'none'" in headers["content-security-policy"]
        status, headers, body = get(server, f"/frame.jpg?token={server.token}")
        assert headers["content-type"] == "image/jpeg" and body[:2] == b"\xff\xd8"
        assert int(headers["x-frame-seq"]) == 4


@pytest.mark.parametrize("path", PATHS)
def test_without_the_token_or_with_another_one_is_refused(path: str) -> None:
    with served(_state()) as server:
        assert get(server, path)[0] == 403
        assert get(server, f"{path}?token=x{server.token}")[0] == 403
        assert get(server, f"{path}?token=")[0] == 403


@pytest.mark.parametrize(
    "host", ["evil.example:{port}", "localhost.evil.example:{port}", "127.0.0.1:1", ""]
)
def test_another_host_is_refused(host: str) -> None:
    with served(_state()) as server:
        h = host.format(port=server.port)
        status, _, body = get(server, f"/?token={server.token}", {"Host": h})
        assert status == 421, h
        assert b"token" not in body


def test_loopback_names_of_the_served_port_are_accepted() -> None:
    with served(_state()) as server:
        for h in (f"localhost:{server.port}", f"127.0.0.1:{server.port}"):
            assert get(server, f"/?token={server.token}", {"Host": h})[0] == 200


def test_a_cross_site_request_is_refused() -> None:
    with served(_state()) as server:
        url = f"/frame.jpg?token={server.token}"
        assert get(server, url, {"Origin": "http://evil.example"})[0] == 403
        assert get(server, url, {"Origin": f"http://{_host(server)}"})[0] == 200


@pytest.mark.parametrize("method", ["POST", "PUT", "DELETE", "PATCH"])
def test_it_is_read_only(method: str) -> None:
    with served(_state()) as server:
        assert get(server, f"/?token={server.token}", method=method)[0] == 405


def _ws_handshake(server: ViewServer, token: str, origin: str | None, host: str) -> bytes:
    """The server's answer to a websocket upgrade (raw, first bytes)."""
    key = base64.b64encode(os.urandom(16)).decode()
    lines = [
        f"GET /ws?token={token} HTTP/1.1",
        f"Host: {host}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {key}",
        "Sec-WebSocket-Version: 13",
    ]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    with socket.create_connection((server.host, server.port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        return s.recv(200)


def test_websocket_origin_and_token_are_checked() -> None:
    with served(_state()) as server:
        good_origin, host = f"http://{_host(server)}", _host(server)
        assert b" 101 " in _ws_handshake(server, server.token, good_origin, host)
        assert b" 403 " in _ws_handshake(server, server.token, "http://evil.example", host)
        assert b" 403 " in _ws_handshake(server, server.token, None, host)
        assert b" 403 " in _ws_handshake(server, "nope", good_origin, host)
        assert b" 421 " in _ws_handshake(server, server.token, good_origin, "evil.example:1")


async def test_the_websocket_sends_the_info_then_the_state() -> None:
    import aiohttp

    with served(_state()) as server:
        url = f"http://127.0.0.1:{server.port}/ws?token={server.token}"
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(url, origin=f"http://{_host(server)}") as ws,
        ):
            info = json.loads((await ws.receive()).data)["info"]
            state = json.loads((await ws.receive()).data)
    assert info["metadata"]["subject"] == "P-017" and info["mode"] == "live"
    assert state["frame_seq"] == 4 and len(state["s_k"]) == 5 and len(state["force"]) == 5


def test_the_page_carries_no_metadata_only_the_token() -> None:
    state = LiveState(view_info(subject="<script>alert(1)</script>"))
    with served(state) as server:
        _, _, body = get(server, f"/?token={server.token}")
    assert b"<script>alert" not in body
    assert server.token.encode() in body


def test_another_interface_is_an_explicit_choice_the_host_must_match() -> None:
    server = ViewServer(_state(), "0.0.0.0", 0)
    server.start()
    try:
        assert (
            get(server, f"/?token={server.token}", {"Host": f"127.0.0.1:{server.port}"})[0] == 200
        )
        assert (
            get(server, f"/?token={server.token}", {"Host": f"evil.example:{server.port}"})[0]
            == 421
        )
    finally:
        server.stop()


async def test_the_newest_frame_is_pushed_on_the_websocket_once() -> None:
    import aiohttp

    state = _state()
    with served(state) as server:
        url = f"http://127.0.0.1:{server.port}/ws?token={server.token}"
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(url, origin=f"http://{_host(server)}") as ws,
        ):
            while (msg := await ws.receive(timeout=5)).type != aiohttp.WSMsgType.BINARY:
                pass  # unasked: the server pushes the newest frame
            n = int.from_bytes(msg.data[:4], "big")
            head = json.loads(msg.data[4 : 4 + n])
            assert head["seq"] == 4 and msg.data[4 + n : 6 + n] == b"\xff\xd8"
            # no newer frame: only states follow, never the same frame again
            for _ in range(3):
                assert (await ws.receive(timeout=5)).type == aiohttp.WSMsgType.TEXT
            publish(state, 5)
            while (msg := await ws.receive(timeout=5)).type != aiohttp.WSMsgType.BINARY:
                pass
            n = int.from_bytes(msg.data[:4], "big")
            assert json.loads(msg.data[4 : 4 + n])["seq"] == 5
