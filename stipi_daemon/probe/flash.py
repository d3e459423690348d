"""Flash the probe firmware onto a Feather 32u4 (Caterina bootloader, AVR109 protocol).

``flash(port)`` builds the hex if needed (``make -C firmware/feather32u4``), opens ``port`` at
1200 baud and closes it (the Caterina reset request), waits for the bootloader's serial port
(it may come back under a new name: any port matching ``ports_glob`` that was not there before,
or the same name after it vanished), then runs ``avrdude -p atmega32u4 -c avr109 -D -U
flash:w:HEX:i`` (avrdude verifies after writing). Every failure raises ``FlashError`` with one
line that says what to do. ``python -m stipi_daemon.probe.flash PORT`` is what ``make flash``
runs.
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware" / "feather32u4"
HEX_NAME = "build/stipi_feather32u4.hex"


class FlashError(RuntimeError):
    """A flashing step failed; str() is one line for the operator."""


def build_hex(firmware_dir: Path = FIRMWARE_DIR) -> Path:
    """Run make (it rebuilds only what changed) and return the hex path."""
    if shutil.which("make") is None:
        raise FlashError("cannot build the firmware: make not found (install make and gcc-avr)")
    proc = subprocess.run(
        ["make", "-C", str(firmware_dir)], capture_output=True, text=True, check=False
    )
    hex_path = firmware_dir / HEX_NAME
    if proc.returncode != 0 or not hex_path.is_file():
        last = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise FlashError(f"firmware build failed: {last[0]}")
    return hex_path


def touch_1200(port: str) -> None:
    """Open and close ``port`` at 1200 baud: Caterina's request to enter the bootloader."""
    try:
        import serial  # pyserial
    except ImportError:  # not installed: the same touch with termios (POSIX)
        _touch_1200_termios(port)
        return
    try:
        ser = serial.Serial()
        ser.port = port
        ser.baudrate = 1200
        ser.dsrdtr = False
        ser.open()
        ser.close()
    except (serial.SerialException, OSError):
        # e.g. a pty without modem-control lines: set the baud rate with termios alone
        _touch_1200_termios(port)


def _touch_1200_termios(port: str) -> None:
    import termios

    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        raise FlashError(f"cannot open {port} at 1200 baud: {exc}") from exc
    try:
        attrs = termios.tcgetattr(fd)
        attrs[4] = attrs[5] = termios.B1200
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except termios.error as exc:
        raise FlashError(f"cannot set 1200 baud on {port}: {exc}") from exc
    finally:
        os.close(fd)


def wait_bootloader(
    port: str, before: set[str], ports_glob: str, timeout_s: float, poll_s: float = 0.05
) -> str:
    """The bootloader's port: a new one matching ``ports_glob``, or ``port`` once it returns."""
    deadline = time.monotonic() + timeout_s
    vanished = False
    while time.monotonic() < deadline:
        now = set(glob.glob(ports_glob))
        new = sorted(now - before)
        if new:
            return new[0]
        if not os.path.exists(port):
            vanished = True
        elif vanished:
            return port
        time.sleep(poll_s)
    raise FlashError(
        f"no bootloader port appeared within {timeout_s:.0f} s after the 1200-baud touch on "
        f"{port}: double-tap the reset button and run again"
    )


def run_avrdude(avrdude: str, port: str, hex_path: Path, baud: int) -> None:
    cmd = [
        avrdude,
        "-p",
        "atmega32u4",
        "-c",
        "avr109",
        "-P",
        port,
        "-b",
        str(baud),
        "-D",
        "-U",
        f"flash:w:{hex_path}:i",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    out = proc.stdout + proc.stderr
    if "verification error" in out or "verification mismatch" in out:
        raise FlashError(f"verify error: flash content differs from {hex_path.name} (flash again)")
    if proc.returncode != 0:
        lines = [ln.strip() for ln in out.splitlines() if ln.strip()]
        raise FlashError(f"avrdude failed on {port}: {lines[-1] if lines else 'no output'}")


def flash(
    port: str,
    hex_path: Path | None = None,
    *,
    build: bool = True,
    avrdude: str = "avrdude",
    ports_glob: str = "/dev/ttyACM*",
    timeout_s: float = 10.0,
    baud: int = 57600,
    log: Callable[[str], None] = print,
) -> str:
    """Flash ``hex_path`` (default: build the firmware) through ``port``; returns the port
    the bootloader answered on. Raises FlashError (one line) on any failure."""
    avrdude_path = shutil.which(avrdude)
    if avrdude_path is None:
        raise FlashError(f"{avrdude} not found: install avrdude")
    if hex_path is None:
        hex_path = build_hex() if build else FIRMWARE_DIR / HEX_NAME
    if not Path(hex_path).is_file():
        raise FlashError(f"no firmware hex at {hex_path}: build it (make -C firmware/feather32u4)")
    if not os.path.exists(port):
        raise FlashError(f"no serial port {port}: is the probe plugged in? (pass --port)")
    before = set(glob.glob(ports_glob))
    log(f"resetting {port} into the bootloader (1200-baud touch)")
    touch_1200(port)
    boot_port = wait_bootloader(port, before, ports_glob, timeout_s)
    log(f"bootloader on {boot_port}; writing and verifying {Path(hex_path).name}")
    run_avrdude(avrdude_path, boot_port, Path(hex_path), baud)
    log("flashed and verified")
    return boot_port


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m stipi_daemon.probe.flash")
    ap.add_argument("port", nargs="?", default="/dev/ttyACM0")
    ap.add_argument("--hex", type=Path, default=None)
    ap.add_argument("--timeout", type=float, default=10.0)
    args = ap.parse_args(argv)
    try:
        flash(args.port, args.hex, timeout_s=args.timeout)
    except FlashError as exc:
        print(f"flash: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
