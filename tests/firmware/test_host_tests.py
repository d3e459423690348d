"""Run the firmware core's host unit tests (``make -C firmware/feather32u4 host-test``).

The C++ core (codec, sampler, command handler, heartbeat, SDEP driver, EEPROM layout) is
compiled with g++ and tested against fakes for the hardware and against the shared vectors in
``tests/vectors/protocol_vectors.txt``. The Makefile serialises concurrent builds with flock.
"""

from __future__ import annotations

import re
import subprocess

import pytest

from tests.conftest import COLD_BUILD_TIMEOUT_S, REPO_ROOT, require_tool

FIRMWARE_DIR = REPO_ROOT / "firmware" / "feather32u4"


@pytest.mark.timeout(COLD_BUILD_TIMEOUT_S + 60)  # a cold sanitizer build on busy cores
def test_host_tests_pass() -> None:
    require_tool("g++", "make", "flock")
    proc = subprocess.run(
        ["make", "-C", str(FIRMWARE_DIR), "host-test", "-j2"],
        capture_output=True,
        text=True,
        timeout=COLD_BUILD_TIMEOUT_S,
        check=False,
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-4000:]
    summary = re.search(r"^(\d+) passed, (\d+) failed$", proc.stdout, re.MULTILINE)
    assert summary is not None, output[-4000:]
    passed, failed = int(summary.group(1)), int(summary.group(2))
    assert failed == 0, output[-4000:]
    assert passed >= 50, f"only {passed} host tests ran"
