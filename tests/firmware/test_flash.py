"""stipi_daemon.probe.flash against a simulated Caterina bootloader, with the real avrdude.

The real firmware hex is written through ``flash()``: 1200-baud touch on the app port, the
bootloader appearing under a NEW port name, ``avrdude -c avr109`` writing and verifying. The
bytes the simulated bootloader received must equal the hex. Failures give one clear line.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from stipi_daemon.probe import flash as flashmod
from tests.conftest import REPO_ROOT, require_tool
from tests.firmware.caterina_sim import CaterinaSim, parse_ihex

FIRMWARE_DIR = REPO_ROOT / "firmware" / "feather32u4"


def test_flash_writes_the_real_hex_into_caterina(tmp_path: Path) -> None:
    require_tool("avrdude", "make", "avr-gcc")
    hex_path = flashmod.build_hex(FIRMWARE_DIR)
    sim = CaterinaSim(tmp_path)
    lines: list[str] = []
    try:
        port = flashmod.flash(
            str(sim.app_link),
            hex_path,
            ports_glob=str(tmp_path / "ttyACM*"),
            timeout_s=10,
            log=lines.append,
        )
    finally:
        sim.close()
    assert port == str(sim.boot_link)  # came back under a new name
    image = parse_ihex(hex_path)
    assert len(image) > 10000
    got = {a: sim.flash[a] for a in image}
    assert got == image
    assert sim.written >= set(image)
    assert "g" in sim.commands  # avrdude read the flash back to verify
    assert lines[-1] == "flashed and verified"


def test_flash_failures_are_one_line(tmp_path: Path) -> None:
    require_tool("avrdude")
    hex_path = tmp_path / "x.hex"
    hex_path.write_text(":00000001FF\n")
    with pytest.raises(flashmod.FlashError, match="no serial port"):
        flashmod.flash(str(tmp_path / "nope"), hex_path, log=lambda s: None)
    with pytest.raises(flashmod.FlashError, match="not found: install avrdude"):
        flashmod.flash(str(tmp_path / "nope"), hex_path, avrdude="no-such-avrdude")
    quiet = tmp_path / "quiet"
    quiet.write_text("")  # a port that never answers the touch with a bootloader
    with pytest.raises(flashmod.FlashError, match="no bootloader port appeared within"):
        flashmod.wait_bootloader(str(quiet), set(), str(tmp_path / "ttyACM*"), timeout_s=0.3)


def test_cli_flash_writes_the_hex_into_caterina(tmp_path: Path) -> None:
    """``stipi-daemon flash --port P --hex F``: the same path through the command line."""
    require_tool("avrdude", "make", "avr-gcc")
    from stipi_daemon.cli import main

    hex_path = flashmod.build_hex(FIRMWARE_DIR)
    sim = CaterinaSim(tmp_path)
    try:
        rc = main(
            [
                "flash",
                "--port",
                str(sim.app_link),
                "--hex",
                str(hex_path),
                "--ports-glob",
                str(tmp_path / "ttyACM*"),
                "--timeout",
                "10",
            ]
        )
    finally:
        sim.close()
    assert rc == 0
    image = parse_ihex(hex_path)
    assert {a: sim.flash[a] for a in image} == image


def test_cli_flash_without_avrdude_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from stipi_daemon.cli import main

    monkeypatch.setenv("PATH", str(tmp_path))  # nothing on PATH, avrdude included
    hex_path = tmp_path / "x.hex"
    hex_path.write_text(":00000001FF\n")
    rc = main(["flash", "--port", str(tmp_path / "ttyACM0"), "--hex", str(hex_path)])
    err = capsys.readouterr().err
    assert rc != 0
    assert err.strip().count("\n") == 0 and "avrdude not found" in err
