"""ProbeLink over the real serial path (pyserial on a pty) to the emulated Feather.

Every test runs the emulated probe on an accelerated session clock (speed 4) behind a pty;
ProbeLink opens it through SerialTransport exactly as it opens /dev/ttyACM0. The reference
for each check is independent of ProbeLink: the scene's own samples (sim.Pipeline), the
emulator's MCU clock (true session time of each MCU timestamp) and its sample counters.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import DeviceNotFoundError, LinkLostError
from stipi_daemon.probe.link import (
    LINK_MIN_WALL_S,
    ClockProbe,
    DecoderErrors,
    ForceRow,
    ForceRows,
    Gap,
    LinkDown,
    LinkUp,
    ProbeEvent,
    ProbeHealth,
    ProbeLink,
    StatusReport,
    wall_floored_timeout_s,
)
from stipi_daemon.probe.transports.serial import SerialTransport, SerialTransportConfig
from stipi_daemon.protocol import BleState, ResetCause, StatusFlags
from stipi_daemon.sim import Pipeline, load_scene
from stipi_daemon.sim.emulated_transport import EmulatedTransport, EmulatedTransportConfig
from stipi_daemon.sim.feather import EmulatedFeather

SCENE = Path(__file__).resolve().parents[1] / "configs" / "scenes" / "grade2.yaml"
SPEED = 4.0


class Collector:
    """Consumes ProbeLink.events() in the background."""

    def __init__(self, link: ProbeLink) -> None:
        self.link = link
        self.events: list[ProbeEvent] = []
        self.error: BaseException | None = None
        self.task = asyncio.create_task(self._run())

    async def _run(self) -> None:
        try:
            async for ev in self.link.events():
                self.events.append(ev)
        except LinkLostError as exc:
            self.error = exc

    def of(self, kind: type[Any]) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def rows(self) -> list[ForceRow]:
        return [r for e in self.of(ForceRows) for r in e.rows]

    async def until(self, pred: Callable[[], bool], what: str, wall_s: float = 8.0) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + wall_s
        while not pred():
            if loop.time() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            if self.task.done() and not pred():
                raise AssertionError(f"event stream ended ({self.error}) before {what}")
            await asyncio.sleep(0.01)

    async def session_s(self, clock: ScaledClock, t_s: float) -> None:
        await clock.sleep_until(clock.now() + t_s)


Factory = Callable[..., Awaitable[tuple[ProbeLink, EmulatedFeather, Collector, ScaledClock]]]


@pytest.fixture
async def probe() -> AsyncIterator[Factory]:
    made: list[tuple[ProbeLink, Collector]] = []

    async def make(
        emu: dict[str, Any] | None = None, speed: float = SPEED, **link_kw: Any
    ) -> tuple[ProbeLink, EmulatedFeather, Collector, ScaledClock]:
        clock = ScaledClock(speed)
        transport = EmulatedTransport(EmulatedTransportConfig(scene=SCENE, **(emu or {})), clock)
        link = ProbeLink(transport, clock=clock, **link_kw)
        collector: Collector | None = None
        try:
            await link.connect()
            collector = Collector(link)
            made.append((link, collector))
            await link.start_stream()
        except BaseException:
            await link.close()
            raise
        return link, transport.feather, collector, clock

    try:
        yield make
    finally:
        for link, collector in made:
            await link.close()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(collector.task, 5)


def scene_counts() -> np.ndarray:
    return Pipeline(load_scene(SCENE)).force_batch().adc_counts


def assert_exact_accounting(rows: list[ForceRow], gaps: list[Gap]) -> None:
    """Every index from the first received to the last is received or in a gap, once."""
    got = [r.sample_index for r in rows]
    assert len(set(got)) == len(got), "a sample was delivered twice"
    lost = [i for g in gaps for i in range(g.start_index, g.start_index + g.count)]
    assert len(set(lost)) == len(lost)
    assert not set(got) & set(lost)
    assert sorted(got + lost) == list(range(min(got), max(got) + 1))


async def test_stream_forces_rate_clock_and_commands(probe: Factory) -> None:
    link, feather, col, _clock = await probe()
    info = link.info
    assert info is not None
    assert (info.proto, info.fw_major, info.adc_bits, info.batch) == (1, 1, 10, 10)
    assert link.calibration == (102, 54297) and link.calibration_source == "probe"
    ups = col.of(LinkUp)
    assert len(ups) == 1 and not ups[0].reconnect and ups[0].info == info
    await col.until(lambda: len(col.rows()) >= 800, "8 s of samples")

    rows = col.rows()
    idx = np.array([r.sample_index for r in rows])
    adc = np.array([r.adc_counts for r in rows])
    # the probe read the scene: index i is scene sample i, sent without loss
    assert not col.of(Gap), (col.of(Gap), link.decoder.stats, feather.frames_dropped)
    assert idx[0] == 0 and np.array_equal(idx, np.arange(len(idx)))
    assert np.array_equal(adc, scene_counts()[: len(idx)])
    force = np.array([r.force_n for r in rows], dtype=np.float64)
    assert np.allclose(force, (adc - 102) * 54297e-6)
    assert not col.of(Gap)
    # rate from the probe's clock and from the mapped session times
    t_mcu = np.array([r.t_mcu_us for r in rows]) * 1e-6
    t_host = np.array([r.t_host_s for r in rows])
    assert abs((len(idx) - 1) / (t_mcu[-1] - t_mcu[0]) / 100 - 1) < 0.01
    assert abs((len(idx) - 1) / (t_host[-1] - t_host[0]) / 100 - 1) < 0.01
    # clock sync: mapped time vs the true session time of each MCU timestamp
    true_s = np.array([feather.mcu_clock.session_s(r.t_mcu_us) for r in rows])
    err_s = t_host - true_s
    settled = np.abs(err_s[len(err_s) // 4 :])
    # Lower-envelope fit: late by the least transport delay. Quiet machine: ~1 ms of session
    # time; with the CPUs oversubscribed scheduler delays of a few wall ms (x4 in session
    # time) tilt the young fit: bounds of 10 / 15 ms wall.
    assert np.quantile(settled, 0.95) < 0.040 and np.max(settled) < 0.060, (
        np.median(settled),
        np.quantile(settled, 0.95),
        np.max(settled),
    )
    assert len(col.of(ClockProbe)) == len(col.of(ForceRows))
    assert [r.t_mcu_raw_us for r in rows[:3]] == [r.t_mcu_us % 2**32 for r in rows[:3]]

    # commands take effect: LED in STATUS, rate in the batches' period
    await link.set_led(77)
    n_status = len(col.of(StatusReport))
    await col.until(lambda: len(col.of(StatusReport)) > n_status, "a STATUS")
    assert col.of(StatusReport)[-1].led_level == 77 and feather.core.led_level == 77
    await link.set_rate(250)
    n = len(col.rows())
    await col.until(lambda: len(col.rows()) > n + 300, "samples at 250 Hz")
    new = [r for r in col.rows()[n:] if r.t_mcu_us > rows[-1].t_mcu_us]
    periods = np.diff([r.t_mcu_us for r in new[-200:]])
    assert np.all(periods == 4000)
    assert not col.of(Gap) and not col.of(DecoderErrors), (col.of(Gap), col.of(DecoderErrors))
    zero = await link.tare()
    assert zero == feather.core.zero_counts and link.calibration == (zero, 54297)


async def test_unplug_and_return_gives_linkdown_linkup_and_exact_gaps(probe: Factory) -> None:
    link, feather, col, _clock = await probe()
    await col.until(lambda: len(col.rows()) >= 200, "2 s of samples")
    feather.unplug(duration_s=1.5)
    await col.until(lambda: len(col.of(LinkUp)) >= 2, "the link back")
    down = col.of(LinkDown)
    assert len(down) == 1 and "lost" in down[0].reason
    n = len(col.rows())
    await col.until(lambda: len(col.rows()) >= n + 200, "samples after the return")
    gaps = col.of(Gap)
    assert gaps and all(g.cause == "link" for g in gaps)
    rows = col.rows()
    assert_exact_accounting(rows, gaps)
    # the gap covers the time unplugged (at least 1.5 s = 150 samples)
    assert sum(g.count for g in gaps) >= 150
    assert link.accounting.lost == sum(g.count for g in gaps)
    assert link.accounting.received == len(rows)
    # samples after the return are still the scene's
    counts = scene_counts()
    assert all(r.adc_counts == counts[r.sample_index] for r in rows)
    assert link.connects == 2 and link.is_up
    stats = link.stats_dict()
    assert stats["samples_sent"] == stats["samples_received"] + stats["samples_lost"]
    assert (stats["gaps_link"], stats["gaps_probe"], stats["connects"]) == (len(gaps), 0, 2)
    up = col.of(LinkUp)[-1]
    assert up.reconnect and up.t_s > down[0].t_s


async def test_silent_link_trips_the_watchdog(probe: Factory) -> None:
    # No wall-time floor: the timeout is exactly 2.5 s of session time (see the next test).
    _link, feather, col, clock = await probe(heartbeat_timeout_s=2.5, min_wall_s=0.0)
    await col.until(lambda: len(col.rows()) >= 100, "1 s of samples")
    t_silence = clock.now()
    feather.silence(4.0)
    await col.until(lambda: bool(col.of(LinkDown)), "the watchdog")
    down = col.of(LinkDown)[0]
    assert "no frame" in down.reason
    # the last frame came at most one batch (0.1 s) before the silence started
    assert t_silence + 2.5 - 0.15 <= down.t_s <= t_silence + 2.5 + 0.25, down.t_s - t_silence
    await col.until(lambda: len(col.of(LinkUp)) >= 2, "the link back after the silence")
    assert col.of(LinkUp)[-1].t_s >= t_silence + 4.0
    n = len(col.rows())
    await col.until(lambda: len(col.rows()) >= n + 50, "samples after the silence")
    assert_exact_accounting(col.rows(), col.of(Gap))


def test_wall_floored_timeout_edges() -> None:
    f = wall_floored_timeout_s
    assert f(2.5, 1.0, 1.0) == 2.5  # real devices (speed 1): unchanged
    assert f(2.5, 0.5, 1.0) == 2.5  # a slowed clock: unchanged
    assert f(2.5, 10.0, 0.0) == 2.5  # no floor: scaled with the clock exactly
    assert f(2.5, 10.0, 1.0) == 10.0  # 1 s of wall time
    assert f(0.5, 10.0, 1.0) == 5.0  # a timeout shorter than the floor keeps its wall length
    assert f(2.5, 2.0, 1.0) == 2.5  # 1.25 s of wall time is already above the floor
    assert f(1e-9, 1e6, 1.0) == pytest.approx(1e-3)


async def test_a_silence_shorter_than_the_wall_floor_keeps_the_link_at_speed_10(
    probe: Factory,
) -> None:
    """At speed 10 the default 2.5 s heartbeat timeout is 0.25 s of wall time, less than a
    loaded host's hiccup; with the floor (LINK_MIN_WALL_S, 1 s of wall time = 10 s of session
    time) a 5 s silence is not a lost link; without it (min_wall_s=0), the same silence is."""
    assert LINK_MIN_WALL_S == 1.0
    for min_wall_s, lost in ((LINK_MIN_WALL_S, False), (0.0, True)):
        _link, feather, col, clock = await probe(speed=10.0, min_wall_s=min_wall_s)
        await col.until(lambda col=col: len(col.rows()) >= 100, "1 s of samples")
        feather.silence(5.0)
        t_end = clock.now() + 5.0
        n = len(col.rows())
        await col.until(
            lambda col=col, n=n, clock=clock, t_end=t_end: (
                clock.now() > t_end + 0.5 and len(col.rows()) > n + 20
            ),
            "samples after the silence",
        )
        downs = col.of(LinkDown)
        assert bool(downs) is lost, [d.reason for d in downs]
        if lost:
            assert "no frame from the probe for 2.5 s" in downs[0].reason
        assert_exact_accounting(col.rows(), col.of(Gap))


async def test_garbage_and_bit_flips_lose_only_damaged_frames(probe: Factory) -> None:
    _link, feather, col, clock = await probe(emu={"seed": 11})
    await col.until(lambda: len(col.rows()) >= 50, "samples")
    feather.bit_error_rate = 3e-4  # ~9 % of 39-byte SAMPLES frames damaged
    for _ in range(10):
        feather.inject_garbage(n_bytes=40)
        await col.session_s(clock, 0.3)
    await col.until(lambda: len(col.rows()) >= 800, "8 s of samples")
    feather.bit_error_rate = 0.0
    rows, gaps = col.rows(), col.of(Gap)
    assert gaps and all(g.cause == "link" for g in gaps)
    assert_exact_accounting(rows, gaps)
    # every damaged frame was rejected: no corrupted sample got through
    counts = scene_counts()
    assert all(r.adc_counts == counts[r.sample_index] for r in rows)
    errors: dict[str, int] = {}
    for e in col.of(DecoderErrors):
        for k, v in e.delta.items():
            errors[k] = errors.get(k, 0) + v
    assert errors.get("frames_lost", 0) > 0 and errors.get("bytes_discarded", 0) > 0
    assert feather.bits_flipped > 0 and feather.garbage_bytes == 400
    # lost samples are whole batches of damaged frames
    assert all(g.count % 10 == 0 for g in gaps)
    assert not col.of(LinkDown)


async def test_probe_side_drops_are_gaps_caused_by_the_probe(probe: Factory) -> None:
    _link, feather, col, _clock = await probe()
    await col.until(lambda: len(col.rows()) >= 100, "samples")
    feather.stall(1.5)
    await col.until(lambda: any(g.cause == "probe" for g in col.of(Gap)), "the probe's gap")
    n = len(col.rows())
    await col.until(lambda: len(col.rows()) >= n + 20, "samples after the stall")
    gaps = col.of(Gap)
    assert [g.cause for g in gaps] == ["probe"]
    assert gaps[0].count == feather.core.dropped > 0
    assert_exact_accounting(col.rows(), gaps)
    await col.until(lambda: col.of(StatusReport)[-1].dropped == feather.core.dropped, "STATUS")


async def test_missing_serial_port_is_one_line(tmp_path: Path) -> None:
    port = tmp_path / "ttyACM7"
    link = ProbeLink(SerialTransport(SerialTransportConfig(port=str(port))), clock=ScaledClock())
    with pytest.raises(DeviceNotFoundError) as exc:
        await link.connect()
    assert str(exc.value) == f"serial port {port} not found"
    await link.close()


async def test_reconnect_gives_up_after_the_budget(probe: Factory) -> None:
    _link, feather, col, clock = await probe(reconnect_total_s=2.0)
    await col.until(lambda: len(col.rows()) >= 50, "samples")
    t0 = clock.now()
    feather.unplug()  # for good
    await col.until(lambda: col.task.done(), "the end of the event stream", wall_s=5)
    assert isinstance(col.error, LinkLostError)
    assert "not back" in str(col.error) and "\n" not in str(col.error)
    assert clock.now() - t0 < 2.0 + 2.5 + 1.0
    assert len(col.of(LinkDown)) == 1


async def test_a_link_lost_during_stream_start_starts_the_stream_on_its_return() -> None:
    # the probe goes away as STREAM_START is written: start_stream() only records the wish
    # (as while the link is down), and the reconnection starts the stream
    clock = ScaledClock(SPEED)
    transport = EmulatedTransport(EmulatedTransportConfig(scene=SCENE), clock)
    link = ProbeLink(transport, clock=clock, reconnect_initial_s=0.1)
    await link.connect()
    col = Collector(link)
    try:
        transport.feather.unplug(duration_s=1.0)
        await link.start_stream()  # raised LinkLostError before
        await col.until(lambda: len(col.of(LinkUp)) >= 2, "the link back")
        await col.until(lambda: len(col.rows()) >= 100, "samples after the return")
        assert len(col.of(LinkDown)) == 1 and link.connects == 2
        assert not col.of(Gap)  # nothing was streamed before the drop: nothing lost
    finally:
        await link.close()
    with contextlib.suppress(asyncio.CancelledError):
        await asyncio.wait_for(col.task, 5)


async def test_a_probe_that_does_not_answer_stream_start_still_raises(probe: Factory) -> None:
    link, feather, col, _clock = await probe(command_retries=0)
    await col.until(lambda: len(col.rows()) >= 20, "samples")
    real_handle = feather.core._handle
    feather.core._handle = lambda seq, msg: None  # the MCU ignores every command
    try:
        with pytest.raises(LinkLostError, match="no answer to StreamStart"):
            await link.start_stream()
    finally:
        feather.core._handle = real_handle
    assert link.is_up


async def test_uncalibrated_probe_gives_no_force_unless_configured(probe: Factory) -> None:
    link, _, col, _ = await probe(emu={"calibrated": False})
    assert link.calibration is None and link.calibration_source == "none"
    await col.until(lambda: len(col.rows()) >= 20, "samples")
    assert all(r.force_n is None for r in col.rows())
    link2, _, col2, _ = await probe(
        emu={"calibrated": False}, zero_counts=100, span_un_per_count=50_000
    )
    assert link2.calibration_source == "config"
    await col2.until(lambda: len(col2.rows()) >= 20, "samples")
    assert all(r.force_n == (r.adc_counts - 100) * 50_000 * 1e-6 for r in col2.rows())
    assert link2.info_dict()["span_un_per_count_used"] == 50_000


async def test_clock_sync_follows_mcu_drift_and_wrap(probe: Factory) -> None:
    # speed 2: scheduler delays (wall time) weigh half as much in session time
    link, feather, col, _clock = await probe(
        emu={"rate_error_ppm": 3000.0, "boot_offset_us": 2**32 - 3_000_000}, speed=2.0
    )
    await col.until(lambda: len(col.rows()) >= 1000, "10 s of samples")
    rows = col.rows()
    assert rows[-1].t_mcu_raw_us < rows[0].t_mcu_raw_us  # the u32 clock wrapped
    assert rows[-1].t_mcu_us > 2**32
    assert np.all(np.diff([r.t_mcu_us for r in rows]) > 0)
    true_s = np.array([feather.mcu_clock.session_s(r.t_mcu_us) for r in rows])
    err = np.array([r.t_host_s for r in rows]) - true_s
    late = np.abs(err[-300:])
    drift = link.clock_sync.drift_ppm
    assert np.median(late) < 0.010 and np.quantile(late, 0.95) < 0.020, (
        np.median(late),
        np.quantile(late, 0.95),
        drift,
    )
    assert abs(drift - (1 / 1.003 - 1) * 1e6) < 1500, drift


def _status(
    t_s: float, cause: ResetCause | None, state: BleState | None, restarts: int | None
) -> StatusReport:
    return StatusReport(t_s, 0, 0, 100, 0, 5000, StatusFlags.NONE, state, restarts, cause)


def test_probe_health_is_recorded_first_and_when_it_changes() -> None:
    """STATUS of firmware 1.1 carries why the probe started and its BLE module's state; the
    session records it once, then on every change, and again after the link came back."""
    health = ProbeHealth()
    wd, up, booting = ResetCause.WATCHDOG, BleState.UP, BleState.BOOTING
    assert health.observe(_status(0.5, wd, booting, 0)) == {
        "reset_cause": "watchdog",
        "ble_state": "booting",
        "ble_restarts": 0,
    }
    assert health.observe(_status(1.0, wd, booting, 0)) is None  # unchanged: not again
    assert health.observe(_status(1.5, wd, up, 0)) == {
        "reset_cause": "watchdog",
        "ble_state": "up",
        "ble_restarts": 0,
    }
    assert health.observe(_status(9.0, wd, up, 1))["ble_restarts"] == 1  # type: ignore[index]
    health.forget()  # the link came back: a restarted probe says why again
    either = ResetCause.EXTERNAL | ResetCause.BROWN_OUT
    assert health.observe(_status(12.0, either, up, 0)) == {
        "reset_cause": "external or brown_out",
        "ble_state": "up",
        "ble_restarts": 0,
    }
    assert health.observe(_status(13.0, None, None, None)) is None  # a probe before 1.1


async def test_a_probe_without_health_fields_still_reports_status(probe: Factory) -> None:
    """The emulated Feather speaks firmware 1.0's 10-byte STATUS: decoded as before."""
    _link, _feather, col, _clock = await probe()
    await col.until(lambda: len(col.of(StatusReport)) >= 2, "two STATUS heartbeats")
    report = col.of(StatusReport)[-1]
    assert (report.ble_state, report.ble_restarts, report.reset_cause) == (None, None, None)
    assert ProbeHealth().observe(report) is None
