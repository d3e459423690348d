"""Nordic UART Service identifiers and the probe's advertising payloads.

This module owns the constants both ends of the BLE link agree on: the Nordic UART
Service (NUS) UUIDs the Bluefruit nRF51822 firmware exposes (docs/protocol.md,
reference/hardware.md), the default ATT MTU and the advertising / scan-response payloads
the emulated probe sends. Pure data, no I/O; no Bumble or bleak objects are built here.
"""

from __future__ import annotations

from typing import Final

__all__ = [
    "ATT_DEFAULT_MTU",
    "ATT_NOTIFY_OVERHEAD",
    "DEFAULT_PROBE_NAME",
    "NUS_RX_UUID",
    "NUS_SERVICE_UUID",
    "NUS_TX_UUID",
    "advertising_payloads",
]

#: Nordic UART Service.
NUS_SERVICE_UUID: Final = "6e400001-b5a3-f393-e0a9-e50e24dcca9e"
#: RX characteristic: the central writes host → probe bytes here.
NUS_RX_UUID: Final = "6e400002-b5a3-f393-e0a9-e50e24dcca9e"
#: TX characteristic: the probe notifies probe → host bytes here.
NUS_TX_UUID: Final = "6e400003-b5a3-f393-e0a9-e50e24dcca9e"

#: ATT MTU before any exchange [bytes]; notifications then carry 20 bytes.
ATT_DEFAULT_MTU: Final = 23
#: Bytes of an ATT Handle Value Notification that are not payload (opcode + handle).
ATT_NOTIFY_OVERHEAD: Final = 3
#: Name the emulated probe advertises unless told otherwise.
DEFAULT_PROBE_NAME: Final = "STIPI-01"

_AD_FLAGS: Final = 0x01
_AD_COMPLETE_128: Final = 0x07
_AD_SHORT_NAME: Final = 0x08
_AD_COMPLETE_NAME: Final = 0x09
_FLAGS_LE_GENERAL_NO_BREDR: Final = 0x06
_LEGACY_AD_MAX: Final = 31


def _ad_structure(ad_type: int, payload: bytes) -> bytes:
    return bytes((len(payload) + 1, ad_type)) + payload


def advertising_payloads(name: str) -> tuple[bytes, bytes]:
    """Advertising data and scan-response data of the probe.

    The advertisement carries the flags (LE general discoverable, no BR/EDR), the NUS UUID
    and the local name - complete when it fits into the 31-byte legacy payload (names of up
    to 8 bytes, such as ``STIPI-01``), else shortened to the bytes that fit. The scan
    response always carries the complete local name, so an active scanner sees it whole.
    (Bumble's software controller answers scan requests with the advertising data, so on a
    virtual radio only the advertisement's name is seen.)

    Parameters
    ----------
    name : str
        Complete local name, 1..29 bytes of UTF-8 (a legacy scan response holds 31 bytes).

    Returns
    -------
    tuple of bytes
        ``(advertising_data, scan_response_data)``, each at most 31 bytes.
    """
    encoded = name.encode("utf-8")
    if not 1 <= len(encoded) <= _LEGACY_AD_MAX - 2:
        raise ValueError(
            f"BLE name must be 1..{_LEGACY_AD_MAX - 2} bytes of UTF-8, got {len(encoded)}: {name!r}"
        )
    uuid_le = bytes.fromhex(NUS_SERVICE_UUID.replace("-", ""))[::-1]
    head = _ad_structure(_AD_FLAGS, bytes((_FLAGS_LE_GENERAL_NO_BREDR,))) + _ad_structure(
        _AD_COMPLETE_128, uuid_le
    )
    room = _LEGACY_AD_MAX - len(head) - 2
    if len(encoded) <= room:
        adv = head + _ad_structure(_AD_COMPLETE_NAME, encoded)
    else:
        short = encoded[:room].decode("utf-8", errors="ignore").encode("utf-8")
        adv = head + _ad_structure(_AD_SHORT_NAME, short)
    scan_response = _ad_structure(_AD_COMPLETE_NAME, encoded)
    return adv, scan_response
