"""A viewer that stops reading changes nothing in the stored session.

The short grade-I scene (as in ``test_speed_identity``: 160x120 at 60 fps, every device
simulated, so the run is on a :class:`~stipi_daemon.clock.VirtualClock`) is measured once
without the live view, and once with it served and a viewer connected that stops reading
after the websocket handshake and after asking for a frame, for more than 30 s of wall
time (the run is paced slowly to last that long). Every stored row, ``summary.json`` and
every decoded video frame must be identical, bit for bit.
"""

from __future__ import annotations

import base64
import hashlib
import io
import os
import re
import socket
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_daemon
from stipi_daemon.storage.video_readback import iter_video_images
from tests.daemon._support import session_record, tiny_config, tiny_scene

#: Wall time the viewer must stay stalled while the run goes on [s].
STALL_WALL_S = 30.0
URL_LINE = re.compile(r"live view: (http://\S+)")


def _scene(directory: Path) -> Path:
    return tiny_scene(directory, "grade1_stalled_viewer")


def _config(tmp_path: Path, scene: Path, name: str, speed: float, view: bool) -> Path:
    return tiny_config(tmp_path / name, scene, run={"speed": speed}, view={"enabled": view})


def _stalled_socket(url: str, request: str) -> socket.socket:
    """A connection that sends ``request`` (to the served host, with its origin) and then
    reads only the first bytes of the answer, never more; a small receive buffer."""
    parts = urlsplit(url)
    host, port = parts.hostname or "", parts.port or 80
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, port))
    s.sendall(request.format(host=f"{host}:{port}", query=parts.query).encode())
    s.settimeout(10)
    assert s.recv(12).startswith(b"HTTP/1.1 ")
    return s


def _stall(url: str) -> list[socket.socket]:
    key = base64.b64encode(os.urandom(16)).decode()
    ws = _stalled_socket(
        url,
        "GET /ws?{query} HTTP/1.1\r\nHost: {host}\r\nOrigin: http://{host}\r\n"
        "Upgrade: websocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n",
    )
    frame = _stalled_socket(url, "GET /frame.jpg?{query} HTTP/1.1\r\nHost: {host}\r\n\r\n")
    return [ws, frame]


def _video_digest(session_dir: Path) -> str:
    h = hashlib.sha256()
    for image in iter_video_images(session_dir / "video.mkv"):
        h.update(image.tobytes())
    return h.hexdigest()


@pytest.mark.timeout(600)
async def test_a_stalled_viewer_changes_nothing_stored(tmp_path: Path) -> None:
    scene = _scene(tmp_path)
    plain = await run_daemon(
        load_config(_config(tmp_path, scene, "plain", 50.0, False)), quiet=True
    )
    assert plain.exit_code == 0

    out = io.StringIO()
    stalled: list[socket.socket] = []
    t_stalled: list[float] = []

    def viewer() -> None:
        deadline = time.monotonic() + 120
        while (m := URL_LINE.search(out.getvalue())) is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert m is not None
        stalled.extend(_stall(m.group(1)))
        t_stalled.append(time.monotonic())

    thread = threading.Thread(target=viewer, daemon=True)
    thread.start()
    # paced so that the run lasts longer than STALL_WALL_S (about 11 s of session time)
    cfg = load_config(_config(tmp_path, scene, "viewed", 0.3, True))
    viewed = await run_daemon(cfg, out=out, live=False)
    t_end = time.monotonic()
    thread.join(timeout=10)
    try:
        assert viewed.exit_code == 0
        assert len(stalled) == 2 and t_end - t_stalled[0] >= STALL_WALL_S
        assert "live view: http://127.0.0.1:" in out.getvalue()
        a: dict[str, Any] = session_record(plain.session_dir)
        b: dict[str, Any] = session_record(viewed.session_dir)
        assert a["tables"]["frames"] and a["tables"]["force_samples"]
        for table, rows in a["tables"].items():
            assert b["tables"][table] == rows, table
        assert b["summary"] == a["summary"]
        assert _video_digest(viewed.session_dir) == _video_digest(plain.session_dir)
    finally:
        for s in stalled:
            s.close()
