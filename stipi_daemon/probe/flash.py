"""Flash the probe firmware onto a Feather 32u4 (Caterina bootloader, AVR109 protocol).

``flash(port)`` builds the hex if needed (``make -C firmware/feather32u4``), reads and checks
the whole image (Intel HEX syntax, checksums, end-of-file record, and that it fits the
28,672 B application section below Caterina's 4 KB boot section) before anything touches the
board, opens ``port`` at 1200 baud and closes it (the Caterina reset request), waits for the
bootloader's serial port (it may come back under a new name: any port matching
``ports_glob`` that was not there before, or the same name after it vanished), then runs
``avrdude -p atmega32u4 -c avr109 -D -U flash:w:HEX:i`` (avrdude verifies after writing).
Every failure raises ``FlashError`` with one line that says what to do; an avrdude failure
is reported by the line that says what failed (avrdude 7.1 always ends with "avrdude done.
Thank you."), with advice for a silent port, a wrong board and a part whose lock bits refuse
the write. ``python -m stipi_daemon.probe.flash PORT`` is what ``make flash`` runs.
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
from dataclasses import dataclass
from pathlib import Path

from stipi_daemon.errors import DeviceNotFoundError, StipiError

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware" / "feather32u4"
HEX_NAME = "build/stipi_feather32u4.hex"

#: ATmega32u4: 32 KB of flash, the top 4 KB (0x7000-0x7FFF) hold the Caterina bootloader
#: (BOOTSZ = 4096 B), so an application may use bytes 0x0000-0x6FFF.
APP_SECTION_B = 28672
#: What the bootloader reports for an ATmega32u4 (avrdude prints it as "1E 95 87").
ATMEGA32U4_SIGNATURE = "1E 95 87"


class FlashError(StipiError, RuntimeError):
    """A flashing step failed; str() is one line for the operator."""


class ImageError(FlashError):
    """The firmware image is bad input (unreadable, damaged, too large): nothing was touched."""


class PortNotFoundError(FlashError, DeviceNotFoundError):
    """The probe's serial port is not there (bad input, as for the daemon): nothing was
    touched."""


@dataclass(frozen=True)
class FirmwareImage:
    """A checked Intel HEX image: ``data`` maps byte address -> value."""

    path: Path
    data: dict[int, int]

    @property
    def end_b(self) -> int:
        """One past the highest address written (what must fit the application section)."""
        return max(self.data) + 1


def _parse_record(line: str, where: str) -> tuple[int, int, bytes]:
    """(record type, 16-bit address, data) of one Intel HEX record, checked completely."""
    if not line.startswith(":"):
        raise ImageError(f"{where}: not an Intel HEX record (does not start with ':')")
    try:
        raw = bytes.fromhex(line[1:])
    except ValueError:
        raise ImageError(f"{where}: not an Intel HEX record (non-hex characters)") from None
    if len(raw) < 5 or len(raw) != 5 + raw[0]:
        raise ImageError(f"{where}: record length does not match its byte count")
    if sum(raw) & 0xFF:
        raise ImageError(f"{where}: checksum error (the file is damaged)")
    return raw[3], int.from_bytes(raw[1:3], "big"), raw[4:-1]


def read_image(hex_path: Path, limit_b: int = APP_SECTION_B) -> FirmwareImage:
    """Read and check all of ``hex_path``; FlashError (one line, file and line) when it is not
    a complete Intel HEX image that fits in ``limit_b`` bytes from address 0."""
    try:
        text = Path(hex_path).read_bytes().decode("ascii")
    except OSError as exc:
        raise ImageError(f"cannot read firmware image {hex_path}: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ImageError(
            f"{hex_path}: not an Intel HEX file (non-ASCII byte at offset {exc.start})"
        ) from None
    data: dict[int, int] = {}
    base = 0
    ended = False
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line:
            continue
        where = f"{hex_path}:{number}"
        if ended:
            raise ImageError(f"{where}: data after the end-of-file record")
        rtype, address, payload = _parse_record(line, where)
        if rtype == 0:
            for i, value in enumerate(payload):
                if base + address + i in data:
                    raise ImageError(f"{where}: address 0x{base + address + i:04X} given twice")
                data[base + address + i] = value
        elif rtype == 1:
            ended = True
        elif rtype in (2, 4) and len(payload) == 2:
            base = int.from_bytes(payload, "big") << (4 if rtype == 2 else 16)
        elif rtype not in (3, 5):
            raise ImageError(f"{where}: unknown Intel HEX record type {rtype:02X}")
    if not ended:
        raise ImageError(f"{hex_path}: no end-of-file record (the file is cut short)")
    if not data:
        raise ImageError(f"{hex_path}: the image holds no data")
    image = FirmwareImage(Path(hex_path), data)
    if image.end_b > limit_b:
        raise ImageError(
            f"{hex_path}: image ends at byte {image.end_b:,}, beyond the {limit_b:,} B "
            f"application section (0x0000-0x{limit_b - 1:04X}); writing it would overwrite "
            "the bootloader: make the firmware smaller"
        )
    return image


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


#: Words of an avrdude line that says what failed (avrdude 7.1: "avrdude error: ...";
#: 6.x: "avrdude: ...: programmer is not responding", "verification error").
_FAILURE_WORDS = (
    "error",
    "not responding",
    "did not respond",
    "out of range",
    "mismatch",
    "failed",
    "can't",
    "cannot",
    "unable",
    "not found",
    "invalid",
    "expected signature",
)
_CLOSING_LINE = "avrdude done"


def avrdude_reason(output: str) -> str:
    """The line of avrdude's ``output`` that says what failed: the first line naming a failure
    (later ones are consequences, e.g. "leave prog mode" after a silent port), not the last
    line, which is always "avrdude done.  Thank you."; without one, the last other line."""
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.lower().startswith(_CLOSING_LINE)]
    chosen = next(
        (ln for ln in lines if any(w in ln.lower() for w in _FAILURE_WORDS)),
        lines[-1] if lines else "no output",
    )
    for prefix in ("avrdude error:", "avrdude warning:", "avrdude:"):
        if chosen.lower().startswith(prefix):
            chosen = chosen[len(prefix) :].strip()
    return chosen


def _mismatch_address(output: str) -> int | None:
    """The byte address of avrdude's first verify mismatch, if it printed one (7.1: "device
    0xff != input 0x0c at addr 0x0000 (error)"; 6.x: "first mismatch at byte 0x0000")."""
    for marker in (" at addr ", "first mismatch at byte "):
        for line in output.splitlines():
            at = line.find(marker)
            if at >= 0:
                try:
                    return int(line[at + len(marker) :].split()[0].rstrip(","), 16)
                except (ValueError, IndexError):
                    return None
    return None


def _line_with(output: str, text: str) -> str | None:
    return next((ln.strip() for ln in output.splitlines() if text in ln.lower()), None)


def avrdude_failure(output: str, port: str, hex_name: str) -> str:
    """One line for a failed avrdude run: its reason, and what helps."""
    reason = avrdude_reason(output)
    low = output.lower()
    if "verification error" in low or "verification mismatch" in low:
        at = _mismatch_address(output)
        where = f" at byte 0x{at:04X}" if at is not None else ""
        return (
            f"verify error{where}: the flash still differs from {hex_name} after writing; "
            "a part whose lock bits refuse writes stays so, flashing again will not help: "
            "read them (avrdude -c avr109 -P PORT -U lock:r:-:h), clear them with an ISP "
            "programmer (chip erase) and burn the Caterina bootloader again"
        )
    if "expected signature" in low:
        found = _line_with(output, "device signature")
        got = found.split(":", 1)[-1].strip() if found else reason
        return (
            f"wrong board on {port}: {got}, but this firmware is for a Feather 32u4 "
            f"(ATmega32u4, signature {ATMEGA32U4_SIGNATURE}): check --port"
        )
    if "not responding" in low or "did not respond" in low:
        return (
            f"avrdude failed on {port}: {reason}: no AVR109 bootloader answered; is it a "
            "Feather 32u4 on this port? double-tap its reset button and run again within 8 s"
        )
    return f"avrdude failed on {port}: {reason}"


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
    low = out.lower()
    if proc.returncode != 0 or "verification error" in low or "verification mismatch" in low:
        raise FlashError(avrdude_failure(out, port, hex_path.name))


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
        raise ImageError(f"no firmware hex at {hex_path}: build it (make -C firmware/feather32u4)")
    image = read_image(Path(hex_path))  # all of it, before anything touches the board
    log(f"{image.path.name}: {image.end_b:,} of {APP_SECTION_B:,} B of the application section")
    if not os.path.exists(port):
        raise PortNotFoundError(f"no serial port {port}: is the probe plugged in? (pass --port)")
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
        return 2 if isinstance(exc, ImageError) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
