"""Advertising payloads of the emulated probe (pure)."""

from __future__ import annotations

import pytest

from stipi_daemon.probe.nus import NUS_SERVICE_UUID, advertising_payloads


def _structures(payload: bytes) -> list[tuple[int, bytes]]:
    out, i = [], 0
    while i < len(payload):
        n = payload[i]
        out.append((payload[i + 1], payload[i + 2 : i + 1 + n]))
        i += 1 + n
    assert i == len(payload)
    return out


def test_short_name_fits_with_uuid_in_the_advertisement() -> None:
    adv, scan = advertising_payloads("STIPI-01")
    assert len(adv) == 31 and len(scan) <= 31
    s = dict(_structures(adv))
    assert s[0x01] == b"\x06"
    assert s[0x07] == bytes.fromhex(NUS_SERVICE_UUID.replace("-", ""))[::-1]
    assert s[0x09] == b"STIPI-01"
    assert dict(_structures(scan))[0x09] == b"STIPI-01"


def test_long_name_is_shortened_in_the_advertisement_and_whole_in_the_scan_response() -> None:
    adv, scan = advertising_payloads("STIPI-probe-laboratory-7")
    assert len(adv) <= 31
    s = dict(_structures(adv))
    assert s[0x08] == b"STIPI-pr"
    assert dict(_structures(scan))[0x09] == b"STIPI-probe-laboratory-7"


@pytest.mark.parametrize("name", ["", "x" * 30])
def test_bad_names_are_refused(name: str) -> None:
    with pytest.raises(ValueError, match="BLE name"):
        advertising_payloads(name)
