"""Build the probe firmware with avr-gcc and check its flash and RAM use.

Limits (docs/firmware.md): flash <= 90 % of the 28,672 B left by the Caterina bootloader,
RAM (.data + .bss + .noinit) <= 75 % of 2,560 B, leaving the rest for the stack.
The ELF lands in ``firmware/feather32u4/build/`` (the simavr harness runs it); the Makefile
takes a flock, so this test may run next to the simavr test under pytest-xdist.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.conftest import COLD_BUILD_TIMEOUT_S, REPO_ROOT, require_path, require_tool

#: A cold build on busy cores may take minutes: the limit only has to catch a hang.
pytestmark = pytest.mark.timeout(COLD_BUILD_TIMEOUT_S + 60)

FIRMWARE_DIR = REPO_ROOT / "firmware" / "feather32u4"
ELF = FIRMWARE_DIR / "build" / "stipi_feather32u4.elf"
ARDUINO_CORE = Path("/usr/share/arduino/hardware/arduino/avr/cores/arduino")
FLASH_MAX_B = 28672
RAM_MAX_B = 2560


def _sections(elf: Path) -> dict[str, int]:
    out = subprocess.run(
        ["avr-size", "-A", str(elf)], capture_output=True, text=True, check=True
    ).stdout
    sizes: dict[str, int] = {}
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0].startswith(".") and parts[1].isdigit():
            sizes[parts[0]] = int(parts[1])
    return sizes


def _make(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the firmware Makefile with ``args`` (skipped without the AVR toolchain); must pass."""
    require_tool("avr-gcc", "avr-size", "make", "flock")
    require_path(ARDUINO_CORE, "arduino-core-avr")
    proc = subprocess.run(
        ["make", "-C", str(FIRMWARE_DIR), *args],
        capture_output=True,
        text=True,
        timeout=COLD_BUILD_TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    return proc


def test_firmware_builds_within_flash_and_ram_budget() -> None:
    _make("all", "-j2")
    assert ELF.is_file()
    s = _sections(ELF)
    flash_b = s.get(".text", 0) + s.get(".data", 0)
    ram_b = s.get(".data", 0) + s.get(".bss", 0) + s.get(".noinit", 0)
    assert s.get(".text", 0) > 4000, f"implausibly small firmware: {s}"
    assert flash_b <= 0.90 * FLASH_MAX_B, f"flash {flash_b} B > 90 % of {FLASH_MAX_B} B"
    assert ram_b <= 0.75 * RAM_MAX_B, f"RAM {ram_b} B > 75 % of {RAM_MAX_B} B"


def test_check_size_target_agrees() -> None:
    assert "size OK" in _make("check-size").stdout
