"""The FC22's supply on the ELF in simavr: ratiometric correction when the 5 V rail is
measured, STATUS.flags bit 4 when it is not.

The FC22's output is proportional to its supply. At 5.00 V a force gives 1234 mV at A0; the
same force on a 4.75 V rail gives 1234 * 4.75 / 5 = 1172 mV. With the 5 V sense wired (A1 =
ADC6 through a 1:2 divider: 2375 mV, ``--hold 6:2375``), the firmware scales every sample by
nominal / measured and reports the count the 5 V rail would have given; the default build has
no sense input, sends the uncorrected count and sets bit 4.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.protocol.messages import AckStatus, StatusFlags, StreamStart
from tests.conftest import require_path, require_tool
from tests.firmware.simavr_probe import (
    FIRMWARE_ELF,
    FIRMWARE_SUPPLY5_ELF,
    SIMAVR_HEADER,
    SimProbe,
    build,
    counts_of_mv,
    flatten,
)

pytestmark = pytest.mark.toolchain

AT_5V_MV = 1234.0
AT_475_MV = round(AT_5V_MV * 4.75 / 5.0)  # 1172 mV


@pytest.fixture(scope="module")
def built() -> None:
    require_tool("avr-gcc", "avr-g++", "cc", "make")
    require_path(SIMAVR_HEADER, "libsimavr-dev headers")
    build("harness", "firmware", "firmware-supply5")


def _run(elf: Path, extra: list[str]) -> tuple[np.ndarray, StatusFlags, int]:
    probe = SimProbe(f"const:{AT_475_MV}", extra, elf=elf)
    try:
        assert probe.command(StreamStart()).status == AckStatus.OK
        s = flatten(probe.collect_samples(50))
        status = probe.next_status()
    finally:
        probe.close()
    return s.adc, status.flags, status.supply_mv


def test_measured_rail_corrects_the_force(built: None) -> None:
    want = int(counts_of_mv(np.array([AT_5V_MV]))[0])  # 382: the count at 5.00 V
    raw = int(counts_of_mv(np.array([AT_475_MV]))[0])  # 363: what the ADC sees at 4.75 V
    adc, flags, supply_mv = _run(FIRMWARE_SUPPLY5_ELF, ["--hold", "6:2375"])
    assert not flags & StatusFlags.SUPPLY_UNCORRECTED
    assert abs(supply_mv - 4750) <= 12  # one 10-bit step of the divider = 6.4 mV at the rail
    assert np.all(np.abs(adc - want) <= 1), (adc[:5], want, raw)
    # The default build (no sense input): the raw count, and the flag says so.
    adc, flags, _ = _run(FIRMWARE_ELF, [])
    assert flags & StatusFlags.SUPPLY_UNCORRECTED
    assert np.all(adc == raw)
    # A sense input reading nonsense (divider open: 0 V) is not trusted: uncorrected, flagged.
    adc, flags, _ = _run(FIRMWARE_SUPPLY5_ELF, ["--hold", "6:0"])
    assert flags & StatusFlags.SUPPLY_UNCORRECTED
    assert np.all(adc == raw)
