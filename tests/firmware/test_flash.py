"""stipi_daemon.probe.flash against a simulated Caterina bootloader, with the real avrdude.

The real firmware hex is written through ``flash()``: 1200-baud touch on the app port, the
bootloader appearing under a NEW port name, ``avrdude -c avr109`` writing and verifying. The
bytes the simulated bootloader received must equal the hex. Failures give one clear line.
"""

from __future__ import annotations

import os
import subprocess
import termios
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
    hex_path.write_text(":0100000055AA\n:00000001FF\n")  # one byte, 0x55 at 0
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
    hex_path.write_text(":0100000055AA\n:00000001FF\n")
    rc = main(["flash", "--port", str(tmp_path / "ttyACM0"), "--hex", str(hex_path)])
    err = capsys.readouterr().err
    assert rc != 0
    assert err.strip().count("\n") == 0 and "avrdude not found" in err


# ---------------------------------------------------------------------------------------
# The image is checked whole before the board is touched; avrdude's real reason is reported
# ---------------------------------------------------------------------------------------


def _image_hex(tmp_path: Path, size_b: int, name: str = "image.hex") -> Path:
    """An Intel HEX image of ``size_b`` bytes from address 0, written by avr-objcopy (not by
    the code under test)."""
    require_tool("avr-objcopy")
    binary = tmp_path / (name + ".bin")
    binary.write_bytes(bytes((i * 7 + 3) & 0xFF for i in range(size_b)))
    out = tmp_path / name
    subprocess.run(["avr-objcopy", "-I", "binary", "-O", "ihex", str(binary), str(out)], check=True)
    return out


def _app_port_baud(sim: CaterinaSim) -> int:
    fd = os.open(sim.app_link, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        return int(termios.tcgetattr(fd)[5])
    finally:
        os.close(fd)


def test_application_section_boundary(tmp_path: Path) -> None:
    image = flashmod.read_image(_image_hex(tmp_path, flashmod.APP_SECTION_B, "fits.hex"))
    assert image.end_b == 28672 and len(image.data) == 28672
    with pytest.raises(flashmod.FlashError, match="beyond the 28,672 B application section"):
        flashmod.read_image(_image_hex(tmp_path, flashmod.APP_SECTION_B + 1, "over.hex"))


def test_oversize_image_is_refused_before_the_touch(tmp_path: Path) -> None:
    require_tool("avrdude")
    hex_path = _image_hex(tmp_path, 30000)
    sim = CaterinaSim(tmp_path)
    try:
        with pytest.raises(flashmod.FlashError) as err:
            flashmod.flash(str(sim.app_link), hex_path, ports_glob=str(tmp_path / "ttyACM*"))
        assert _app_port_baud(sim) != termios.B1200  # never touched
    finally:
        sim.close()
    msg = str(err.value)
    assert "\n" not in msg and str(hex_path) in msg
    assert "image ends at byte 30,000, beyond the 28,672 B application section" in msg
    assert not sim.touched and sim.commands == [] and sim.app_link.exists()


DAMAGED = {
    "checksum": (":0100000055AB\n:00000001FF\n", ":1: checksum error"),
    "cut short": (":0100000055AA\n", "no end-of-file record"),
    "not hex": (":0100000055AA\n:0100010Z55AA\n:00000001FF\n", ":2: not an Intel HEX record"),
    "count": (":020000005555\n:00000001FF\n", ":1: record length does not match"),
    "no colon": ("0100000055AA\n:00000001FF\n", ":1: not an Intel HEX record"),
    "after end": (":00000001FF\n:0100000055AA\n", ":2: data after the end-of-file record"),
    "empty": (":00000001FF\n", "the image holds no data"),
    "twice": (":0100000055AA\n:0100000055AA\n:00000001FF\n", ":2: address 0x0000 given twice"),
    "latin-1": (":0100000055AA\n\u00e9\n", "non-ASCII byte at offset 14"),
}


@pytest.mark.parametrize("case", sorted(DAMAGED))
def test_damaged_image_is_refused_before_the_touch(tmp_path: Path, case: str) -> None:
    require_tool("avrdude")
    text, expected = DAMAGED[case]
    hex_path = tmp_path / "bad.hex"
    hex_path.write_bytes(text.encode("latin-1"))
    sim = CaterinaSim(tmp_path)
    try:
        with pytest.raises(flashmod.FlashError) as err:
            flashmod.flash(str(sim.app_link), hex_path, ports_glob=str(tmp_path / "ttyACM*"))
        assert _app_port_baud(sim) != termios.B1200
    finally:
        sim.close()
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(hex_path)) and expected in msg, msg
    assert isinstance(err.value, flashmod.ImageError) and not sim.touched


def test_cli_refuses_an_oversize_image_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    require_tool("avrdude")
    from stipi_daemon.cli import main

    hex_path = _image_hex(tmp_path, 33000)
    sim = CaterinaSim(tmp_path)
    try:
        rc = main(["flash", "--port", str(sim.app_link), "--hex", str(hex_path),
                   "--ports-glob", str(tmp_path / "ttyACM*")])  # fmt: skip
    finally:
        sim.close()
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0  # bad input, like every command's
    assert "beyond the 28,672 B application section" in err and not sim.touched


def _flash_into(sim: CaterinaSim, tmp_path: Path, hex_path: Path) -> str:
    """flash() into ``sim``; the one-line FlashError message it must end with."""
    try:
        with pytest.raises(flashmod.FlashError) as err:
            flashmod.flash(
                str(sim.app_link),
                hex_path,
                ports_glob=str(tmp_path / "ttyACM*"),
                timeout_s=10,
                log=lambda s: None,
            )
    finally:
        sim.close()
    msg = str(err.value)
    assert "\n" not in msg and "Thank you" not in msg, msg
    return msg


def test_silent_bootloader_names_avrdude_reason(tmp_path: Path) -> None:
    """avrdude 7.1 ends with "avrdude done.  Thank you."; the reason is a line before it.
    (avrdude gives up on a silent port after about 50 s of its own timeouts.)"""
    require_tool("avrdude")
    hex_path = _image_hex(tmp_path, 1000)
    msg = _flash_into(CaterinaSim(tmp_path, silent=True), tmp_path, hex_path)
    assert "programmer is not responding" in msg and "double-tap" in msg, msg


def test_wrong_board_is_named(tmp_path: Path) -> None:
    require_tool("avrdude")
    hex_path = _image_hex(tmp_path, 1000)
    atmega328p = bytes([0x0F, 0x95, 0x1E])  # 1E 95 0F, low byte first as AVR109 sends it
    msg = _flash_into(CaterinaSim(tmp_path, signature=atmega328p), tmp_path, hex_path)
    assert msg.startswith("wrong board on") and "1E 95 87" in msg, msg


def test_locked_part_gets_advice_that_helps(tmp_path: Path) -> None:
    require_tool("avrdude")
    hex_path = _image_hex(tmp_path, 1000)
    msg = _flash_into(CaterinaSim(tmp_path, locked=True), tmp_path, hex_path)
    assert msg.startswith("verify error at byte 0x0000"), msg
    assert "lock bits" in msg and "flashing again will not help" in msg, msg
    assert "(flash again)" not in msg
