"""The operator's side of the CLI: the rich live view on a terminal, and Ctrl-C.

Both run the real CLI in a subprocess on the emulated Feather and the simulator camera
(the short grade-I scene, accelerated). On a pseudo-terminal the daemon must draw its live
panel and finish the measurement without an error; interrupted with SIGINT (Ctrl-C) it
must close its devices, leave the session finished as ``aborted`` (not ``interrupted``,
which means a recorder that died), say so in one line and exit with status 130.
"""

from __future__ import annotations

import fcntl
import os
import pty
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

from stipi_daemon.storage.reader import SessionReader
from tests.daemon._support import SHORT_MEASUREMENT, short_scene, write_config


def _config(tmp_path: Path, speed: float) -> Path:
    scene = str(short_scene(tmp_path, width=160, height=120))
    return write_config(
        tmp_path,
        {
            "probe": {"transport": {"kind": "emulated", "scene": scene}},
            "camera": {"kind": "simulator", "scene": scene},
            "measurement": SHORT_MEASUREMENT,
            "run": {"speed": speed},
        },
    )


def test_live_view_on_a_terminal(tmp_path: Path) -> None:
    config = _config(tmp_path, speed=8.0)
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 110, 0, 0))
    env = {**os.environ, "TERM": "xterm-256color", "COLUMNS": "110", "LINES": "40"}
    env.pop("NO_COLOR", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
        stdin=slave,
        stdout=slave,
        stderr=slave,
        env=env,
        close_fds=True,
    )
    os.close(slave)
    chunks: list[bytes] = []
    deadline = time.monotonic() + 90.0
    try:
        while time.monotonic() < deadline:
            ready, _, _ = select.select([master], [], [], 0.2)
            if ready:
                try:
                    data = os.read(master, 65536)
                except OSError:  # EIO: the child closed the terminal
                    break
                if not data:
                    break
                chunks.append(data)
            elif proc.poll() is not None:
                break
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
        os.close(master)
    text = b"".join(chunks).decode("utf-8", "replace")
    assert code == 0, text[-3000:]
    assert "Traceback" not in text and "error" not in text.lower(), text[-3000:]
    # The live panel was drawn (title, phase line, readings) with cursor control codes,
    # and the results were printed below it.
    assert "STIP-I measurement" in text
    for needle in ("phase", "RECOVERY", "S_k", "force"):
        assert needle in text, (needle, text[-3000:])
    assert "\x1b[" in text
    assert "D_p =" in text and "session written to" in text


def test_ctrl_c_leaves_an_aborted_session(tmp_path: Path) -> None:
    config = _config(tmp_path, speed=2.0)
    proc = subprocess.Popen(
        [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    sessions = tmp_path / "sessions"
    deadline = time.monotonic() + 60.0
    try:
        # Interrupt once the session exists and is recording.
        while not list(sessions.glob("*/session.sqlite")):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no session started"
            time.sleep(0.05)
        time.sleep(2.0)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, (out, err)
    assert err == "stipi-daemon: interrupted\n", err
    assert "measurement aborted" in out and "Traceback" not in out + err
    assert f"`stipi-daemon analyze {sessions}" in out  # what the recording allows: said how
    (session,) = sessions.iterdir()
    with SessionReader(session) as reader:
        assert str(reader.status) == "aborted"
        assert reader.integrity_check().ok
        assert reader.counts()["frames"] > 0
        summary = reader.summary
    assert summary is not None and summary["verdict"]["status"] == "incomplete"
