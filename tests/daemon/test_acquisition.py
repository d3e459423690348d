"""The acquisition loop's camera side: S_k measured, the image kept there, a result queued."""

from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace
from typing import Any

import numpy as np

from stipi_daemon.app.acquisition import FrameMeasurer, FrameResult
from stipi_daemon.cameras import CameraFrame, CameraStalled
from stipi_daemon.cameras.threaded import ThreadedCamera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase


def _pipeline(phase: Phase) -> Any:
    state = SimpleNamespace(phase=phase, t_pit_start_s=0.0, t_release_s=None)
    return SimpleNamespace(state=state)


def test_frame_result_carries_no_image_and_the_keeper_gets_it() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    measurer = FrameMeasurer(ScaledClock(1.0), 128, None, 0.5, keeper, _pipeline(Phase.PITTING))
    image = np.zeros((4, 5), dtype=np.uint8)
    image[:2] = 255  # 10 pixels above p: S_k counts the 10 at or below it (Eq. 2)
    result = measurer(CameraFrame(7, 1.0, image, 0))
    assert isinstance(result, FrameResult)
    assert (result.seq, result.t_capture_s, result.s_k, result.dropped_before) == (7, 1.0, 10, 0)
    assert not any(isinstance(getattr(result, f.name), np.ndarray) for f in fields(result))
    chosen = keeper.selected()
    assert [f.kind for f in chosen] == ["pitting", "recovery_start"]
    assert chosen[0].image is image


def test_other_camera_events_pass_unchanged() -> None:
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    measurer = FrameMeasurer(ScaledClock(1.0), 128, None, 0.5, keeper, _pipeline(Phase.ARMED))
    stalled = CameraStalled(3.0, 6, 1.0, "timeout")
    assert measurer(stalled) is stalled
    assert keeper.selected() == ()


# ---------------------------------------------------------------- falling behind (issue 14 case 7)


class _Clock:
    """A session clock the test sets by hand (on wall time: it does not wait for the
    daemon)."""

    waits_for_daemon = False

    def __init__(self, now_s: float, speed: float = 50.0) -> None:
        self.t = now_s
        self.speed = speed

    def now(self) -> float:
        return self.t


class _Writer:
    def __init__(self) -> None:
        self.gaps: list[tuple[Any, ...]] = []
        self.events: list[tuple[Any, ...]] = []
        self.frames: list[Any] = []

    def add_gap(self, *row: Any) -> None:
        self.gaps.append(row)

    def add_event(self, *row: Any) -> None:
        self.events.append(row)

    def add_frames(self, rows: Any) -> None:
        self.frames.extend(rows)

    def commit(self) -> None:
        pass

    def add_transition(self, *row: Any) -> None:
        pass


class _Pipeline:
    """Records what the loop feeds; ``close`` ends it."""

    def __init__(self) -> None:
        self.fed: list[Any] = []
        self.closed_at: float | None = None
        self.state = SimpleNamespace(
            now_s=0.0, phase=Phase.RECOVERY, t_pit_start_s=0.0, t_release_s=1.0
        )

    @property
    def phase(self) -> Phase:
        """The phase, as :attr:`MeasurementPipeline.phase` gives it."""
        phase: Phase = self.state.phase
        return phase

    def feed(self, event: Any) -> list[Any]:
        self.fed.append(event)
        return []

    def force(self, t_s: float, v: float) -> list[Any]:
        self.fed.append(("force", t_s))
        return []

    def frame(self, t_s: float, v: float) -> list[Any]:
        self.fed.append(("frame", t_s))
        return []

    def close(self, t_s: float) -> list[Any]:
        self.closed_at = t_s
        return []


def _acquisition(
    clock: _Clock, max_lag_s: float = 5.0, source: ThreadedCamera[Any] | None = None
) -> tuple[Any, _Writer, _Pipeline]:
    """The loop's handlers on a recording writer and pipeline; ``source``: the camera's
    capture source (its frame hook set, as the daemon's)."""
    from stipi_daemon.app.acquisition import Acquisition

    config = SimpleNamespace(run=SimpleNamespace(speed=clock.speed, max_lag_s=max_lag_s))
    writer, pipeline = _Writer(), _Pipeline()
    camera = SimpleNamespace(stats=SimpleNamespace(fps=lambda: 60.0), camera=source)
    devices = SimpleNamespace(clock=clock, writer=writer, camera=camera, probe=None)
    console = SimpleNamespace(
        line=lambda *a, **k: None, update=lambda *a, **k: None, warn=lambda text: None
    )
    measurer = None if source is None else SimpleNamespace(on_capture=lambda raw: None)
    acq = Acquisition(config, devices, pipeline, console, measurer)  # type: ignore[arg-type]
    return acq, writer, pipeline


def test_a_late_frame_is_a_counted_gap_never_measured() -> None:
    from stipi_daemon.app.acquisition import LATE_GAP_REASON, LateFrame

    clock = _Clock(10.0)
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    pipe = _pipeline(Phase.RECOVERY)
    measurer = FrameMeasurer(clock, 128, None, 0.5, keeper, pipe, skip_late_s=2.5)  # type: ignore[arg-type]
    image = np.zeros((4, 5), dtype=np.uint8)
    assert isinstance(measurer(CameraFrame(1, 8.0, image, 0)), FrameResult)  # 2 s late
    late = measurer(CameraFrame(2, 7.0, image, 3))  # 3 s late
    assert late == LateFrame(2, 7.0, 3.0, 3)
    acq, writer, _ = _acquisition(clock)
    assert acq._on_late_frame(late) == []
    # The frame and the three the camera dropped before it are gaps with their reasons.
    assert writer.gaps == [("frames", -1, 3, 7.0, "camera"), ("frames", 2, 1, 7.0, LATE_GAP_REASON)]
    assert acq.counts["late_frames"] == 1 and acq.counts["dropped_frames"] == 3
    assert acq.lag_s == [3.0] and writer.frames == []


def test_nothing_is_fed_ahead_of_the_camera_and_ticks_lag_behind() -> None:
    """The session cannot end while frames of its window are still on their way."""
    from stipi_daemon.app.acquisition import MERGE_HOLD_S
    from stipi_daemon.measurement.state_machine import Tick

    clock = _Clock(100.0)
    acq, _, pipeline = _acquisition(clock)
    acq._on_frame(FrameResult(1, 96.0, 96.0, 10, (), 0))  # the camera is 4 s behind
    assert acq._lag_now_s == 4.0
    acq.merger.push("force", 97.0, (97.0, 1.0), clock.now())
    clock.t = 101.0  # held 1 s > MERGE_HOLD_S, but only 1 - 4 s on the camera's clock
    released = acq.merger.pop_ready(clock.now() - acq._lag_now_s)
    assert released == [("frame", (96.0, 10.0))]  # the sample at 97 s waits for the camera
    assert len(acq.merger) == 1
    acq._on_tick(Tick(clock.now()))
    ticks = [e for e in pipeline.fed if isinstance(e, Tick)]
    assert all(t.t_s <= 101.0 - MERGE_HOLD_S - 4.0 for t in ticks)


def test_a_lag_beyond_the_bound_ends_the_run_with_one_line() -> None:
    clock = _Clock(50.0)
    acq, writer, pipeline = _acquisition(clock, max_lag_s=5.0)
    acq._on_frame(FrameResult(1, 46.0, 46.0, 10, (), 0))
    assert acq.fault_line is None and pipeline.closed_at is None
    acq._on_frame(FrameResult(2, 44.0, 44.0, 10, (), 0))  # 6 s behind
    assert acq.fault_line is not None
    assert acq.fault_line.startswith("falling behind: a frame was handled 6.0 s after its capture")
    assert "run.max_lag_s 5" in acq.fault_line and "run.speed 50" in acq.fault_line
    assert pipeline.closed_at == 50.0
    assert writer.events[-1][1] == "fault:falling_behind"


class _FirstFrameNotYetMade(ThreadedCamera[None]):
    """A source that waits for its consumer (as the simulator, a file) and knows its first
    frame's capture time; never opened here: that frame has not come (the simulator's
    first frame once took 2 s of wall time, rendered, measured and its video opened)."""

    def __init__(self, clock: Any, t0_s: float) -> None:
        super().__init__(clock, capacity=2, drop_oldest=False, paced=True)
        self.t0_s = t0_s

    @property
    def name(self) -> str:
        return "first frame not yet made"

    @property
    def nominal_fps(self) -> float:
        return 60.0

    def _open_source(self) -> None:
        return None

    def _read(self, handle: None) -> None:
        return None

    def _close_source(self, handle: None) -> None:
        pass

    def _first_capture_s(self) -> float | None:
        return self.t0_s


def test_an_overdue_first_frame_is_the_lag_and_past_the_bound_ends_the_run() -> None:
    """Before any frame, the lag of a source that waits for its consumer is that of its
    first frame, due since its capture time: samples and ticks run behind it, and past
    run.max_lag_s the run ends with one line (it used to measure 110 s without a frame at
    speed 60 when the simulator's first frame took 2 s of wall time, and say only "No
    results: need at least 2 finite samples, got 0")."""
    from stipi_daemon.app.acquisition import MERGE_HOLD_S
    from stipi_daemon.measurement.state_machine import Tick

    clock = _Clock(10.0)
    acq, writer, pipeline = _acquisition(clock, source=_FirstFrameNotYetMade(clock, t0_s=8.0))
    acq._on_tick(Tick(clock.now()))
    assert acq._lag_now_s == 2.0 and acq.fault_line is None
    assert all(e.t_s <= 10.0 - MERGE_HOLD_S - 2.0 for e in pipeline.fed if isinstance(e, Tick))
    acq.merger.push("force", 9.0, (9.0, 1.0), clock.now())
    clock.t = 11.0  # the sample waits for the camera's first frame
    assert acq.merger.pop_ready(clock.now() - acq._lag_now_s) == []
    clock.t = 13.5
    acq._on_tick(Tick(clock.now()))
    assert acq.fault_line == (
        "falling behind: the camera's first frame, due at 8.0 s, had not come 5.5 s later "
        "(more than run.max_lag_s 5 s); this machine does not sustain run.speed 50: lower it"
    )
    assert pipeline.closed_at == 13.5
    assert writer.events[-1][1:] == (
        "fault:falling_behind",
        {"lag_s": 5.5, "max_lag_s": 5.0, "first_frame": True},
    )
    assert ("force", 9.0) in pipeline.fed  # what was held is fed before the end


def test_once_a_frame_came_the_first_frame_no_longer_counts() -> None:
    from stipi_daemon.measurement.state_machine import Tick

    clock = _Clock(20.0)
    source = _FirstFrameNotYetMade(clock, t0_s=8.0)  # 12 s before now
    acq, _, pipeline = _acquisition(clock, source=source)
    acq._on_frame(FrameResult(1, 19.0, 19.0, 10, (), 0))
    acq._on_tick(Tick(clock.now()))
    assert acq._lag_now_s == 1.0 and acq.fault_line is None and pipeline.closed_at is None


def test_the_queue_is_bounded() -> None:
    from stipi_daemon.app.acquisition import QUEUE_MAX_EVENTS

    acq, _, _ = _acquisition(_Clock(0.0))
    assert acq._queue.maxsize == QUEUE_MAX_EVENTS > 0


async def test_stop_names_a_task_that_does_not_end_and_where_it_waits(
    monkeypatch: Any, caplog: Any
) -> None:
    """A task that swallows its cancellation is cancelled again until it ends, and once the
    wait passes STOP_WARN_WALL_S the log names it and the line it waits at."""
    import asyncio
    import logging

    from stipi_daemon.app import acquisition as acq_mod

    monkeypatch.setattr(acq_mod, "STOP_WARN_WALL_S", 0.05)
    acq, _, _ = _acquisition(_Clock(0.0))
    swallowed = 0

    async def stubborn() -> None:
        nonlocal swallowed
        while swallowed < 4:  # ends at the fifth cancellation
            try:
                await asyncio.sleep(10.0)
            except asyncio.CancelledError:
                swallowed += 1

    task = asyncio.create_task(stubborn(), name="stubborn")
    await asyncio.sleep(0)
    acq._tasks = [task]
    with caplog.at_level(logging.WARNING, logger=acq_mod.__name__):
        await asyncio.wait_for(acq.stop(), 10.0)
    assert task.done() and swallowed == 4
    lines = [r.getMessage() for r in caplog.records if "still waiting" in r.getMessage()]
    assert lines and "stubborn" in lines[0] and "await asyncio.sleep(10.0)" in lines[0]
