"""A simulated Caterina bootloader (Feather 32u4) on a pty, for flashing tests.

Written from Atmel's AVR109 application note ("Self-programming", the command set avrdude's
``-c avr109`` speaks) and Caterina's behaviour: the application's CDC port answers a 1200-baud
touch by resetting; the bootloader then enumerates (here: a NEW pty, reachable under a new
name) and serves AVR109 commands. Flash writes land in ``self.flash`` (32 KB, erased = 0xFF).

Faults a bench meets: ``silent`` (the port appears but nothing answers, e.g. the application
still running on it or another device), ``signature`` (another part answers, a wrong board),
``locked`` (the part's lock bits make SPM ignore page writes, ATmega32u4 datasheet 28.5: the
bootloader acknowledges every block, the flash keeps its old content).
"""

from __future__ import annotations

import os
import pty
import select
import termios
import threading
import time
import tty
from pathlib import Path

SIGNATURE = bytes([0x87, 0x95, 0x1E])  # ATmega32u4 1E 95 87, sent low byte first
FLASH_BYTES = 32768
BLOCK = 128


class CaterinaSim:
    """App port ``dir/ttyACM0``; after a 1200-baud touch the bootloader appears on ttyACM1."""

    def __init__(
        self,
        directory: Path,
        reappear_s: float = 0.3,
        *,
        silent: bool = False,
        signature: bytes = SIGNATURE,
        locked: bool = False,
    ) -> None:
        self.dir = directory
        self.reappear_s = reappear_s
        self.silent = silent
        self.signature = signature
        self.locked = locked
        self.touched = False
        self.flash = bytearray(b"\xff" * FLASH_BYTES)
        self.written: set[int] = set()
        self.commands: list[str] = []
        self.app_link = directory / "ttyACM0"
        self.boot_link = directory / "ttyACM1"
        self._stop = threading.Event()
        self._app_master, self._app_slave = pty.openpty()
        tty.setraw(self._app_slave)
        os.symlink(os.ttyname(self._app_slave), self.app_link)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)

    def _run(self) -> None:
        while not self._stop.is_set():  # the application: waits for the 1200-baud touch
            if termios.tcgetattr(self._app_slave)[5] == termios.B1200:
                break
            time.sleep(0.01)
        else:
            return
        self.touched = True
        self.app_link.unlink()  # the CDC device goes away, the bootloader enumerates
        time.sleep(self.reappear_s)
        master, slave = pty.openpty()
        tty.setraw(slave)
        tty.setraw(master)
        os.symlink(os.ttyname(slave), self.boot_link)
        try:
            self._serve(master)
        finally:
            os.close(master)
            os.close(slave)

    def _read(self, fd: int, n: int) -> bytes:
        out = b""
        while len(out) < n and not self._stop.is_set():
            r, _, _ = select.select([fd], [], [], 0.05)
            if r:
                try:
                    got = os.read(fd, n - len(out))
                    out += b"" if self.silent else got
                except OSError:
                    time.sleep(0.01)
        return out

    def _serve(self, fd: int) -> None:
        addr = 0  # word address (AVR109 'A')
        while not self._stop.is_set():
            c = self._read(fd, 1)
            if not c:
                continue
            cmd = chr(c[0])
            self.commands.append(cmd)
            reply, addr = self._command(fd, cmd, addr)
            if reply:
                os.write(fd, reply)

    def _command(self, fd: int, cmd: str, addr: int) -> tuple[bytes, int]:
        simple = {
            "S": b"CATERIN",
            "V": b"10",
            "v": b"?",
            "p": b"S",
            "a": b"Y",
            "t": b"\x44\x00",
            "s": self.signature,
            "b": b"Y" + BLOCK.to_bytes(2, "big"),
        }
        if cmd in simple:
            return simple[cmd], addr
        if cmd in "TxyPLEe":  # select device, LEDs, enter/leave programming, exit, erase
            if cmd in "Txy":
                self._read(fd, 1)
            if cmd == "e" and not self.locked:
                self.flash[:] = b"\xff" * FLASH_BYTES
            return b"\r", addr
        if cmd == "r":  # lock bits: 0x2C = LB1 and LB2 programmed (no further programming)
            return b"\x2c" if self.locked else b"\xff", addr
        if cmd in "FNQ":  # fuse bytes
            return b"\xff", addr
        if cmd == "A":
            a = self._read(fd, 2)
            return b"\r", int.from_bytes(a, "big")
        if cmd == "B":
            hdr = self._read(fd, 3)
            n, mem = int.from_bytes(hdr[:2], "big"), chr(hdr[2])
            data = self._read(fd, n)
            if mem == "F" and not self.locked:
                start = addr * 2
                self.flash[start : start + n] = data
                self.written.update(range(start, start + n))
                addr += n // 2
            return b"\r", addr
        if cmd == "g":
            hdr = self._read(fd, 3)
            n, mem = int.from_bytes(hdr[:2], "big"), chr(hdr[2])
            if mem == "F":
                start = addr * 2
                return bytes(self.flash[start : start + n]), addr + n // 2
            return b"\xff" * n, addr
        if cmd == "\x1b":
            return b"", addr
        return b"?", addr


def parse_ihex(path: Path) -> dict[int, int]:
    """Address -> byte of an Intel hex file (data records; extended segment/linear ignored
    beyond 64 KB, which an ATmega32u4 image never reaches)."""
    mem: dict[int, int] = {}
    for line in path.read_text().splitlines():
        if not line.startswith(":"):
            continue
        raw = bytes.fromhex(line[1:])
        n, address, rtype = raw[0], int.from_bytes(raw[1:3], "big"), raw[3]
        if rtype == 0:
            for i in range(n):
                mem[address + i] = raw[4 + i]
    return mem
