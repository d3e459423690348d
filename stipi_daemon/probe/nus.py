"""Nordic UART Service identifiers and the probe's advertising payloads.

This module owns the constants both ends of the BLE link agree on: the Nordic UART
Service (NUS) UUIDs the Bluefruit nRF51822 firmware exposes (docs/protocol.md,
reference/hardware.md), the default ATT MTU and the advertising / scan-response payloads
the emulated probe sends, and the ``loopback:[HOST:]PORT`` HCI spec both ends of a
virtual radio on the loopback interface agree on (``mock-peripheral --transport
loopback:9321`` serves it, a daemon with ``hci: loopback:9321`` connects to it; docs/bench.md).
Pure data, no I/O; no Bumble or bleak objects are built here.
"""

from __future__ import annotations

import ipaddress
from typing import Final

__all__ = [
    "ATT_DEFAULT_MTU",
    "ATT_NOTIFY_OVERHEAD",
    "DEFAULT_LOOPBACK_PORT",
    "DEFAULT_PROBE_NAME",
    "LOOPBACK_SCHEME",
    "NUS_RX_UUID",
    "NUS_SERVICE_UUID",
    "NUS_TX_UUID",
    "advertising_payloads",
    "check_hci_spec_is_local",
    "parse_loopback_spec",
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

#: HCI spec scheme of a virtual radio served on the loopback interface (one machine, two
#: processes): ``loopback:PORT`` or ``loopback:HOST:PORT`` with a loopback HOST.
LOOPBACK_SCHEME: Final = "loopback"
#: Port of ``configs/probe-ble-loopback.yaml`` and docs/bench.md.
DEFAULT_LOOPBACK_PORT: Final = 9321
#: Bumble transport schemes that open a network socket (their host must be a loopback one).
_NETWORK_SCHEMES: Final = ("tcp-client", "tcp-server", "udp", "ws-client", "ws-server")

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


def _loopback_host(host: str, spec: str) -> str:
    """``host`` as an IP address literal if it is a loopback address, else ValueError."""
    if host in ("localhost", "_", ""):
        if host == "localhost":
            return "127.0.0.1"
        raise ValueError(f"{spec!r}: give a loopback address (127.0.0.1 or ::1), not {host!r}")
    try:
        address = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        raise ValueError(f"{spec!r}: {host!r} is not an IP address (use 127.0.0.1)") from None
    if not address.is_loopback:
        raise ValueError(
            f"{spec!r}: {host} is not a loopback address; HCI over a socket stays on this "
            "machine (127.0.0.1 or ::1)"
        )
    return str(address)


def parse_loopback_spec(spec: str, *, allow_any_port: bool = False) -> tuple[str, int]:
    """Host and port of a ``loopback:[HOST:]PORT`` HCI spec.

    Parameters
    ----------
    spec : str
        ``loopback:9321``, ``loopback:127.0.0.1:9321`` or ``loopback:[::1]:9321``. HOST
        defaults to 127.0.0.1 and must be a loopback address.
    allow_any_port : bool
        Accept port 0 (the server picks a free port and prints it).

    Returns
    -------
    tuple of (str, int)
        ``(host, port)``.

    Raises
    ------
    ValueError
        Not a ``loopback:`` spec, HOST not a loopback address, or PORT not 1..65535
        (0..65535 with ``allow_any_port``); the message names the spec.
    """
    scheme, _, rest = spec.partition(":")
    if scheme != LOOPBACK_SCHEME:
        raise ValueError(f"{spec!r} is not a {LOOPBACK_SCHEME}:[HOST:]PORT spec")
    host, _, port_text = rest.rpartition(":")
    host = _loopback_host(host, spec) if host else "127.0.0.1"
    low = 0 if allow_any_port else 1
    try:
        port = int(port_text)
    except ValueError:
        port = -1
    if not low <= port <= 65535:
        raise ValueError(f"{spec!r}: port must be an integer {low}..65535, got {port_text!r}")
    return host, port


def check_hci_spec_is_local(spec: str) -> None:
    """Refuse an HCI spec that would open a socket to or on another machine.

    ``loopback:`` specs and Bumble's network transports (``tcp-client:HOST:PORT``,
    ``tcp-server:HOST:PORT``, ``udp:``, ``ws-client:``, ``ws-server:``) must name loopback
    addresses: HCI carries no authentication, so it never leaves the machine. Other specs
    (``usb:0``, ``hci-socket:0``, ``serial:...``, ``virtual:NAME``) pass unchanged.

    Raises
    ------
    ValueError
        A network spec with a host that is not a loopback address, or a malformed
        ``loopback:`` spec (the message names the spec).
    """
    scheme, _, rest = spec.partition(":")
    if scheme == LOOPBACK_SCHEME:
        parse_loopback_spec(spec)
        return
    if scheme not in _NETWORK_SCHEMES:
        return
    for endpoint in rest.split(","):
        target = endpoint.split("://", 1)[-1].split("/", 1)[0]
        host = target.rsplit(":", 1)[0] if ":" in target else target
        _loopback_host(host, spec)
