"""Adafruit's own SDEP driver against the simulated nRF51 (tests/firmware/nrf51_sim).

``Adafruit_BluefruitLE_SPI`` is compiled on the host FROM the shared reference
(``../shared/reference/adafruit_bluefruit_nrf51``, or ``$STIPI_VENDOR_DIR``) against a minimal
Arduino/SPI shim of ours (tests/firmware/vendor_driver); nothing of the vendor is copied into
this tree. begin(), echo off, isConnected(), BLE UART print() of 1-200 bytes, received data,
and a full TX FIFO: if the vendor's driver fails here, the simulated module is wrong.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

from tests.conftest import COLD_BUILD_TIMEOUT_S, REPO_ROOT, require_tool

#: A cold build on busy cores may take minutes: the limit only has to catch a hang.
pytestmark = pytest.mark.timeout(COLD_BUILD_TIMEOUT_S + 60)

VENDOR_TEST_DIR = REPO_ROOT / "tests" / "firmware" / "vendor_driver"


def vendor_dir() -> Path:
    env = os.environ.get("STIPI_VENDOR_DIR")
    if env:
        return Path(env)
    return REPO_ROOT.parent / "shared" / "reference" / "adafruit_bluefruit_nrf51"


def test_vendor_driver_passes_against_simulated_module() -> None:
    require_tool("g++", "gcc", "make")
    src = vendor_dir()
    assert (src / "Adafruit_BluefruitLE_SPI.cpp").is_file(), (
        f"vendor driver not found in {src}: set STIPI_VENDOR_DIR"
    )
    proc = subprocess.run(
        ["make", "-C", str(VENDOR_TEST_DIR), "run", f"STIPI_VENDOR_DIR={src}"],
        capture_output=True,
        text=True,
        timeout=COLD_BUILD_TIMEOUT_S,
        check=False,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-4000:]
    m = re.search(r"vendor driver: (\d+) checks, (\d+) failed", proc.stdout)
    assert m is not None, out[-4000:]
    assert int(m.group(2)) == 0 and int(m.group(1)) >= 400, out[-4000:]
    assert "20100 bytes in 200 prints" in proc.stdout
