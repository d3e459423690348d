"""Daemon side of the two-process BLE test, run as its own process.

``python -m tests.ble._loopback_client HCI N SPEED`` opens the daemon's BLE transport
(bleak's public API on Bumble's host stack, ``hci: HCI``) through ProbeLink, exactly as
the daemon does, streams N samples and prints one JSON line: the rows (sample index, ADC
counts, force [N], probe time [µs]), the decoder's counters and the transport's
connection count. Exit code 0 when N samples arrived.
"""

from __future__ import annotations

import asyncio
import json
import sys

from stipi_daemon.clock import ScaledClock
from stipi_daemon.probe.link import ForceRows, Gap, LinkDown, ProbeLink
from stipi_daemon.probe.transports.ble import BleTransport, BleTransportConfig


async def _main(hci: str, n: int, speed: float) -> dict[str, object]:
    clock = ScaledClock(speed)
    transport = BleTransport(
        BleTransportConfig(name="STIPI-01", hci=hci, scan_timeout_s=60, connect_timeout_s=30),
        clock,
    )
    probe = ProbeLink(transport, clock=clock, rate_hz=100)
    rows: list[tuple[int, int, float | None, int]] = []
    gaps = downs = 0
    await probe.connect()
    mtu = transport.mtu_size
    try:
        await probe.start_stream()
        async for ev in probe.events():
            if isinstance(ev, ForceRows):
                rows.extend((r.sample_index, r.adc_counts, r.force_n, r.t_mcu_us) for r in ev.rows)
                if len(rows) >= n:
                    break
            elif isinstance(ev, Gap):
                gaps += 1
            elif isinstance(ev, LinkDown):
                downs += 1
    finally:
        await probe.close()
        await transport.release()
    return {
        "rows": rows[:n],
        "gaps": gaps,
        "link_downs": downs,
        "lost": probe.accounting.lost,
        "decoder": probe.decoder.stats.as_dict(),
        "connections": transport.connections,
        "subscriptions": transport.subscriptions,
        "mtu": mtu,
        "calibration": probe.calibration,
    }


if __name__ == "__main__":
    result = asyncio.run(_main(sys.argv[1], int(sys.argv[2]), float(sys.argv[3])))
    print(json.dumps(result), flush=True)
