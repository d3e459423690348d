"""Mutation check of the simulated nRF51 (tests/firmware/nrf51_sim): every spec violation it
can be switched into must make a test fail.

The model is written from Adafruit's SDEP.md; a model that drifted toward the firmware would
let a wrong firmware pass. ``nrf51_sim.c`` names its violations (answers every packet, IRQ high
while busy, IRQ stuck high, IRQ dropping between packets, never 0xFE, errors sent as plain
responses, malformed packets dropped, unread answers discarded, TX accepted while
disconnected, no CS set-up time, no alerts); ``STIPI_NRF51_VIOLATION=<name>`` switches one on
at start-up. For each, the vendor's own driver (compiled from ../shared/reference) and the
host tests that run against the module (the ``nrf51_sim_*`` conformance tests, each naming its
SDEP.md section, and the ``ble_link_*`` tests of the firmware's link) run with it; at least one
must fail. A violation no test catches fails this test. With no violation, all must pass.
"""

from __future__ import annotations

import os
import re
import subprocess

import pytest

from tests.conftest import COLD_BUILD_TIMEOUT_S, REPO_ROOT, require_tool
from tests.firmware.test_vendor_driver import vendor_dir

FIRMWARE_DIR = REPO_ROOT / "firmware" / "feather32u4"
SIM_C = REPO_ROOT / "tests" / "firmware" / "nrf51_sim" / "nrf51_sim.c"
VENDOR_TEST_DIR = REPO_ROOT / "tests" / "firmware" / "vendor_driver"
HOST_TESTS = FIRMWARE_DIR / "test" / "build" / "host_tests"
VECTORS = REPO_ROOT / "tests" / "vectors" / "protocol_vectors.txt"
VENDOR_TEST = VENDOR_TEST_DIR / "build" / "vendor_test"
#: The host tests that run against the module (a substring filter of the runner).
HOST_FILTERS = ("nrf51_sim", "ble_link")
#: The violations nrf51_sim.c must offer at least (each a way a module model went wrong before).
REQUIRED = {
    "answers_every_packet",
    "irq_high_while_busy",
    "irq_stuck_high",
    "irq_drops_between_packets",
    "never_not_ready",
    "errors_as_responses",
    "drops_malformed",
    "discards_unread",
    "tx_while_disconnected",
    "no_cs_setup",
    "no_alerts",
}


def violation_names() -> list[str]:
    text = SIM_C.read_text(encoding="utf-8")
    block = re.search(r"nrf51_sim_violation_names\[[^]]*\] = \{(.*?)\};", text, re.DOTALL)
    assert block is not None, "nrf51_sim.c lost its violation names"
    return re.findall(r'"(\w+)"', block.group(1))


def _run(cmd: list[str], violation: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, STIPI_NRF51_VIOLATION=violation)
    return subprocess.run(
        cmd, capture_output=True, text=True, env=env, timeout=COLD_BUILD_TIMEOUT_S, check=False
    )


def _failing_runs(violation: str) -> list[str]:
    """The runs (vendor driver, host test filters) that failed with ``violation`` on."""
    failed = []
    if _run([str(VENDOR_TEST)], violation).returncode != 0:
        failed.append("vendor driver")
    for f in HOST_FILTERS:
        if _run([str(HOST_TESTS), str(VECTORS), f], violation).returncode != 0:
            failed.append(f"host tests {f}*")
    return failed


# two cold builds, then the vendor driver and the host tests once per violation: a hang
# guard, not a time limit (beside two busy loops the builds alone took minutes)
@pytest.mark.timeout(3 * COLD_BUILD_TIMEOUT_S)
def test_every_spec_violation_of_the_simulated_module_is_caught() -> None:
    require_tool("g++", "gcc", "make", "flock")
    src = vendor_dir()
    assert (src / "Adafruit_BluefruitLE_SPI.cpp").is_file(), f"vendor driver not in {src}"
    for cmd in (
        ["make", "-C", str(FIRMWARE_DIR), "host-test", "-j2"],
        ["make", "-C", str(VENDOR_TEST_DIR), "build/vendor_test", f"STIPI_VENDOR_DIR={src}"],
    ):
        proc = subprocess.run(
            cmd, capture_output=True, text=True, timeout=COLD_BUILD_TIMEOUT_S, check=False
        )
        assert proc.returncode == 0, (proc.stdout + proc.stderr)[-4000:]
    names = violation_names()
    assert names[0] == "spec_true" and REQUIRED <= set(names[1:]), names
    assert _failing_runs("spec_true") == [], "the spec-true module must pass everything"
    caught = {v: _failing_runs(v) for v in names[1:]}
    missed = sorted(v for v, runs in caught.items() if not runs)
    assert not missed, f"spec violations no test catches: {missed} (caught: {caught})"
