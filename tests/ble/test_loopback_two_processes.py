"""The BLE bench without a radio: mock probe and daemon in two processes over loopback.

``stipi-daemon mock-peripheral --transport loopback:0`` serves a virtual radio on
127.0.0.1 (Bumble software controllers on one link; each client gets its own controller
over HCI/TCP); a second process opens the daemon's real BLE transport with ``hci:
loopback:PORT`` (bleak's API on Bumble's host stack) and streams through ProbeLink. The
samples must equal, index for index, what the same scene and seed give through the
serial path (an emulated Feather on a pty read by pyserial; docs/protocol.md framing, CRC
and seq checked by the decoder on both). Both processes are torn down and waited for.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ForceRows, ProbeLink
from stipi_daemon.probe.transports import open_transport
from stipi_daemon.probe.transports.configs import EmulatedTransportConfig

from .conftest import REPO, SCENES

N_SAMPLES = 300
SPEED = 4.0
SEED = 5
_SERVING = re.compile(r"serving a virtual radio on (127\.0\.0\.1):(\d+)")


@contextmanager
def mock_peripheral(
    *extra: str, scene: Path = SCENES / "grade1.yaml", speed: float = SPEED, seed: int = SEED
) -> Iterator[tuple[subprocess.Popen[str], int, list[str]]]:
    """Start ``stipi-daemon mock-peripheral --transport loopback:0``; yield it, its port and
    the lines it printed before serving. Stopped with SIGINT (then killed) and reaped."""
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "stipi_daemon",
            "mock-peripheral",
            "--scene",
            str(scene),
            "--transport",
            "loopback:0",
            "--seed",
            str(seed),
            "--speed",
            str(speed),
            "--duration",
            "600",
            "--report-every",
            "1000",
            *extra,
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    lines: list[str] = []
    try:
        assert proc.stdout is not None
        deadline = time.monotonic() + 120
        port = None
        while port is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            m = _SERVING.search(line)
            if m:
                port = int(m.group(2))
        assert port is not None, (
            f"mock-peripheral did not serve: {lines} {proc.stderr.read() if proc.stderr else ''}"
        )
        yield proc, port, lines
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=30)
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def _daemon_side(hci: str, n: int = N_SAMPLES) -> dict[str, object]:
    done = subprocess.run(
        [sys.executable, "-m", "tests.ble._loopback_client", hci, str(n), str(SPEED)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result: dict[str, object] = json.loads(done.stdout.strip().splitlines()[-1])
    return result


async def _serial_reference(n: int) -> list[tuple[int, int, float | None, int]]:
    clock = ScaledClock(10.0)
    config = EmulatedTransportConfig(scene=SCENES / "grade1.yaml", seed=SEED)
    probe = ProbeLink(open_transport(config, clock), clock=clock, rate_hz=100)
    await probe.connect()
    rows: list[tuple[int, int, float | None, int]] = []
    try:
        await probe.start_stream()
        async for ev in probe.events():
            if isinstance(ev, ForceRows):
                rows.extend((r.sample_index, r.adc_counts, r.force_n, r.t_mcu_us) for r in ev.rows)
                if len(rows) >= n:
                    break
    finally:
        await probe.close()
    return rows[:n]


def _relative(
    rows: list[tuple[int, int, float | None, int]],
) -> list[tuple[int, int, float | None, int]]:
    t0 = rows[0][3]
    return [(i, adc, force, t - t0) for i, adc, force, t in rows]


async def test_mock_peripheral_and_daemon_in_two_processes() -> None:
    with mock_peripheral() as (proc, port, lines):
        assert "advertising STIPI-01" in "".join(lines)
        with socket.create_connection(("127.0.0.1", port), timeout=10):
            pass  # listening on the loopback address it printed
        first = _daemon_side(f"loopback:{port}")
        # The probe advertises again after the first daemon left: a second one connects.
        second = _daemon_side(f"loopback:{port}", 50)
        assert proc.poll() is None  # still serving
    assert proc.returncode == 0
    reference = await _serial_reference(N_SAMPLES)
    rows = [tuple(r) for r in first["rows"]]  # type: ignore[attr-defined]
    assert [r[0] for r in rows] == list(range(N_SAMPLES))
    assert _relative(rows) == _relative(reference)
    stats = first["decoder"]
    assert isinstance(stats, dict)
    assert stats["crc_errors"] == stats["frames_lost"] == stats["restarts"] == 0
    assert stats["wrong_direction"] == 0 and stats["frames_ok"] > 0
    assert (first["gaps"], first["lost"], first["link_downs"]) == (0, 0, 0)
    assert (first["connections"], first["subscriptions"], first["mtu"]) == (1, 1, 23)
    assert first["calibration"] is not None
    assert len(second["rows"]) == 50 and second["connections"] == 1  # type: ignore[arg-type]


def test_a_killed_daemon_frees_the_probe_for_the_next_one() -> None:
    """A daemon killed with SIGKILL is a dongle pulled out: the probe sees a supervision
    timeout, advertises again, and the next daemon connects."""
    with mock_peripheral() as (_proc, port, _lines):
        victim = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "tests.ble._loopback_client",
                f"loopback:{port}",
                "100000",
                str(SPEED),
            ],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        try:
            time.sleep(8)  # connected and streaming by now on any machine we run on
        finally:
            os.kill(victim.pid, signal.SIGKILL)
            victim.wait(timeout=30)
        after = _daemon_side(f"loopback:{port}", 50)
    assert len(after["rows"]) == 50  # type: ignore[arg-type]
    assert after["connections"] == 1


def test_refused_connections_are_retried_within_one_open() -> None:
    """Two connections dropped as they are made (HCI 0x3E, what BlueZ reports as
    le-connection-abort-by-local): bleak-retry-connector's establish_connection retries
    inside the transport's one open(); the link comes up once, with no LinkDown."""
    with mock_peripheral("--refuse-connections", "2") as (proc, port, _lines):
        result = _daemon_side(f"loopback:{port}", 50)
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    assert result["connections"] == 1 and result["link_downs"] == 0
    assert "refused=2" in out and "conns=1" in out


@pytest.mark.parametrize(
    ("spec", "needle"),
    [
        ("usb:0", "no Bluetooth USB dongle at usb:0"),
        ("loopback:10.1.2.3:9321", "not a loopback address"),
    ],
)
def test_unusable_controllers_are_one_line(spec: str, needle: str) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "stipi_daemon",
            "mock-peripheral",
            "--scene",
            str(SCENES / "grade1.yaml"),
            "--transport",
            spec,
            "--duration",
            "1",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode != 0
    err = done.stderr.strip()
    assert err.count("\n") == 0 and needle in err and "Traceback" not in err
    if spec.startswith("usb"):
        assert "loopback:9321" in err  # the way to run without a dongle


def test_port_in_use_is_one_line() -> None:
    with mock_peripheral() as (_proc, port, _lines):
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "stipi_daemon",
                "mock-peripheral",
                "--scene",
                str(SCENES / "grade1.yaml"),
                "--transport",
                f"loopback:{port}",
                "--duration",
                "1",
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
    assert done.returncode != 0
    assert done.stderr.strip().count("\n") == 0 and "in use" in done.stderr
