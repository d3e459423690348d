"""The CLI as a process whose standard output is closed or full, or whose terminal closes.

A measurement whose console cannot be written - stdout closed when it starts (``>&-``),
on a full disk (``>/dev/full``) - or that receives SIGHUP (its terminal closed) ends as
Ctrl-C ends it: the session finished ``aborted`` and whole (integrity check ok, writer
lock released), one line on stderr, no traceback. Another command whose output is full
says so in one line. (A pipe whose reader left is tests/daemon/test_cli_process_end.py.)
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

from stipi_daemon.storage import SessionReader
from tests.daemon._support import short_config

CLI = (sys.executable, "-m", "stipi_daemon")
#: Generous: the machine is shared and often loaded; these are not timing tests.
TIMEOUT_S = 600


def _aborted_and_whole(root: Path) -> Path:
    (session,) = root.iterdir()
    assert json.loads((session / "summary.json").read_text())["status"] == "aborted"
    assert not (session / "writer.lock").exists()
    assert not list(session.glob("*.tmp"))
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
    return session


def test_a_measurement_with_stdout_closed_ends_as_ctrl_c_does(tmp_path: Path) -> None:
    config = short_config(tmp_path, {}, speed=4.0)
    proc = subprocess.run(
        ["sh", "-c", 'exec "$@" >&-', "sh", *CLI, "--config", str(config)],
        stderr=subprocess.PIPE,
        text=True,
        timeout=TIMEOUT_S,
        cwd=tmp_path,
    )
    assert proc.returncode == 130, proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith("stipi-daemon: stopped: standard output is closed;"), line
    session = _aborted_and_whole(tmp_path / "sessions")
    assert str(session) in line


def test_a_measurement_with_stdout_full_ends_as_ctrl_c_does(tmp_path: Path) -> None:
    config = short_config(tmp_path, {}, speed=4.0)
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=TIMEOUT_S,
            cwd=tmp_path,
        )
    assert proc.returncode == 130, proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith("stipi-daemon: stopped: standard output failed: No space left"), line
    _aborted_and_whole(tmp_path / "sessions")


def test_another_command_with_stdout_full_is_one_line(tmp_path: Path) -> None:
    (tmp_path / "sessions").mkdir()
    with open("/dev/full", "w") as full:
        proc = subprocess.run(
            [*CLI, "sessions", "list", "--root", str(tmp_path / "sessions")],
            stdout=full,
            stderr=subprocess.PIPE,
            text=True,
            timeout=TIMEOUT_S,
            cwd=tmp_path,
        )
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr == (
        "stipi-daemon: error: cannot write the output: [Errno 28] No space left on device\n"
    )


def test_sighup_ends_a_measurement_as_ctrl_c_does(tmp_path: Path) -> None:
    config = short_config(tmp_path, {}, speed=1.0)
    proc = subprocess.Popen(
        [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert proc.stdout is not None
        seen: list[str] = []
        for line in proc.stdout:  # recording: the stream is up and the operator was asked
            seen.append(line)
            if "idle -> armed" in line:
                break
        else:  # the output ended without it: the signal would reach no measurement
            raise AssertionError(f"no 'idle -> armed' line (exit {proc.wait()}): {seen[-20:]}")
        proc.send_signal(signal.SIGHUP)
        out, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGHUP, err
    assert err == "stipi-daemon: terminated (SIGHUP) (the terminal closed)\n"
    assert "measurement aborted; what was recorded is in" in out
    _aborted_and_whole(tmp_path / "sessions")
