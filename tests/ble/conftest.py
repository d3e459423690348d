"""Fixtures for the BLE tests: a virtual radio per test, Bumble devices on it.

Everything here is real Bumble: software controllers on an in-process link, real LL
connections, ACL, L2CAP, ATT and GATT. No Bluetooth adapter is needed and nothing is
skipped.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

from stipi_daemon.probe.link import ClockProbe, ForceRows, Gap, LinkDown, LinkUp, ProbeLink
from stipi_daemon.sim.ble.bleak_backend import BumbleAdapter
from stipi_daemon.sim.ble.mock_probe import SampleLedger
from stipi_daemon.sim.ble.radio import VirtualRadio

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "configs" / "scenes"
_ids = itertools.count()


@pytest.fixture
def radio() -> Iterator[VirtualRadio]:
    """A fresh virtual radio, unregistered at the end of the test."""
    r = VirtualRadio(f"test-{next(_ids)}")
    try:
        yield r
    finally:
        r.close()


@pytest.fixture
async def adapter(radio: VirtualRadio) -> AsyncIterator[BumbleAdapter]:
    """A Bumble central on the test radio (bleak backends via ``adapter.backends()``)."""
    a = await BumbleAdapter.open(radio.spec)
    try:
        yield a
    finally:
        await a.close()


class ProbeRecorder:
    """Consumes :meth:`ProbeLink.events` in a task and keeps what the tests look at."""

    def __init__(self, probe: ProbeLink) -> None:
        self.probe = probe
        self.indices: list[int] = []
        self.gaps: list[Gap] = []
        self.downs: list[LinkDown] = []
        self.ups: list[LinkUp] = []
        self.clock_probes: list[ClockProbe] = []
        self.rows_since_up = 0
        self.error: BaseException | None = None
        self._task = asyncio.get_running_loop().create_task(self._run())

    async def _run(self) -> None:
        try:
            async for ev in self.probe.events():
                if isinstance(ev, ForceRows):
                    self.indices.extend(r.sample_index for r in ev.rows)
                    self.rows_since_up += len(ev.rows)
                elif isinstance(ev, Gap):
                    self.gaps.append(ev)
                elif isinstance(ev, LinkDown):
                    self.downs.append(ev)
                elif isinstance(ev, LinkUp):
                    self.ups.append(ev)
                    self.rows_since_up = 0
                elif isinstance(ev, ClockProbe):
                    self.clock_probes.append(ev)
        except BaseException as exc:
            self.error = exc

    async def until(self, predicate: Callable[[], bool], timeout_s: float = 20.0) -> None:
        """Wait (wall time) until ``predicate()`` holds; fail if the link died."""
        async with asyncio.timeout(timeout_s):
            while not predicate():
                if self.error is not None:
                    raise AssertionError(f"the probe link ended: {self.error!r}")
                await asyncio.sleep(0.002)

    async def stop(self) -> None:
        await self.probe.close()
        await asyncio.wait_for(self._task, 5)


def check_accounting_against_ledger(
    rec: ProbeRecorder, ledger: SampleLedger, connections: int | None = None
) -> int:
    """The host's sample accounting equals the peripheral's ground truth; returns samples lost.

    Over the window from the first received sample to the end of the last received batch:
    the host received only samples the module delivered decodably, no sample twice, and its
    lost count (and its Gap events) equal the samples the probe sent minus those received.
    When every link loss came from the peripheral's side and every connection was one
    ``LinkUp`` (``connections``), the host received exactly what was delivered. When the
    host closed a link itself (watchdog, a command timing out on a loaded machine), bytes
    already on their way are discarded with that connection, so only the inclusion holds.
    """
    idx = rec.indices
    assert idx, "no samples received"
    assert all(b > a for a, b in itertools.pairwise(idx)), "samples repeated or out of order"
    lo, hi = idx[0], idx[-1] + 1
    delivered = {i for i in ledger.delivered_indices() if lo <= i < hi}
    peripheral_side_only = all("disconnected by the peripheral" in d.reason for d in rec.downs)
    missing, extra = sorted(delivered - set(idx)), sorted(set(idx) - delivered)
    why = f"delivered, not received: {missing[:20]} ({len(missing)}); received, not delivered: "
    why += f"{extra[:20]} ({len(extra)}); link downs: {[d.reason for d in rec.downs][:5]}"
    if peripheral_side_only and (connections is None or connections == len(rec.ups)):
        assert not missing and not extra, why
    else:
        assert not extra, why
    emitted = sum(max(0, min(first + n, hi) - max(first, lo)) for first, n in ledger.emitted)
    acc = rec.probe.accounting
    assert acc.received == len(idx)
    assert acc.lost == emitted - len(idx) == (hi - lo) - len(idx)
    assert sum(g.count for g in rec.gaps) == acc.lost
    assert rec.probe.decoder.stats.duplicates == 0
    return acc.lost
