"""CameraStream: stall detection, reopen with backoff and recovery, on real sources."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import pytest

from stipi_daemon.cameras import (
    CameraEvent,
    CameraFrame,
    CameraRecovered,
    CameraStalled,
    CameraStream,
)
from stipi_daemon.cameras.threaded import RawFrame
from stipi_daemon.cameras.video_file import VideoFileCamera
from stipi_daemon.clock import ScaledClock, VirtualClock
from stipi_daemon.errors import CameraError
from stipi_daemon.sim.camera import SimulatorCamera
from tests.cameras._scenes import small_scene
from tests.cameras._video import write_avi


async def test_stall_is_detected_reopened_and_recovered() -> None:
    """On the clock that waits for the daemon (its timing is exact on any machine): a
    1 s freeze of the simulated camera is a stall 0.5 s after its last frame, one reopen,
    and every frame of the frozen second lost and accounted for."""
    scene = small_scene(recovery_s=5.0)
    fps = scene.camera.fps
    clock = VirtualClock()
    cam = SimulatorCamera(scene, clock)
    stream = CameraStream(cam, clock, stall_timeout_s=0.5, backoff_s=0.05)
    events: list[tuple[CameraEvent, float]] = []
    stall_at: float | None = None
    async with clock.running(), stream:
        async for ev in stream.events():
            events.append((ev, clock.now()))
            if isinstance(ev, CameraFrame):
                if stall_at is None and ev.seq == 12:
                    stall_at = clock.now()
                    cam.stall(1.0)
                elif stall_at is not None and ev.t_capture_s > stall_at + 1.3:
                    break
    assert not cam.is_open and stall_at is not None
    kinds = [type(e).__name__ for e, _ in events]
    i_stall = kinds.index("CameraStalled")
    assert kinds.count("CameraStalled") == 1 and kinds[i_stall + 1] == "CameraRecovered"
    stalled = events[i_stall][0]
    assert isinstance(stalled, CameraStalled)
    assert stalled.last_seq == 12 and stalled.reason == "timeout"
    # Detected 0.5 s (session time) after the last frame, to the rounding of times.
    assert stalled.silent_s == pytest.approx(0.5, abs=1e-9)
    assert stalled.t_s - stall_at == pytest.approx(0.5, abs=1e-9)
    recovered = events[i_stall + 1][0]
    assert isinstance(recovered, CameraRecovered)
    assert recovered.attempts == 1 and recovered.t_s >= stall_at + 1.0
    first = events[i_stall + 2][0]
    assert isinstance(first, CameraFrame)
    assert first.t_capture_s >= stall_at + 1.0 - 0.5 / fps
    # Every frame of the frozen second is lost and accounted for.
    assert first.dropped_before == first.seq - 13 >= round(1.0 * fps) - 2
    frames = [e for e, _ in events if isinstance(e, CameraFrame)]
    seqs = [f.seq for f in frames]
    assert seqs == sorted(seqs) and seqs[:13] == list(range(13))
    assert cam.stats.stalls == 1 and cam.stats.reopens == 1
    assert cam.stats.dropped == first.dropped_before


async def test_permanent_stall_gives_up_with_one_line_error() -> None:
    clock = ScaledClock(speed=2.0)
    cam = SimulatorCamera(small_scene(recovery_s=30.0), clock)
    stream = CameraStream(
        cam, clock, stall_timeout_s=0.2, open_timeout_s=0.3, max_reopens=2, backoff_s=0.05
    )
    events: list[CameraEvent] = []
    w0 = time.monotonic()
    with pytest.raises(CameraError) as info:
        async with stream:
            async for ev in stream.events():
                events.append(ev)
                if isinstance(ev, CameraFrame) and ev.seq == 3:
                    cam.stall(1e6)
    assert time.monotonic() - w0 < 5.0
    msg = str(info.value)
    assert msg.startswith(cam.name) and "2 reopen attempts" in msg and "\n" not in msg
    assert isinstance(events[-1], CameraStalled)
    assert not cam.is_open and cam.stats.stalls == 1 and cam.stats.reopens == 0


async def test_reopen_failures_are_retried_then_reported(tmp_path: Path) -> None:
    p = tmp_path / "v.avi"
    write_avi(p, 200, fps=30.0)
    clock = ScaledClock(speed=4.0)
    cam = VideoFileCamera(p, clock)
    stream = CameraStream(cam, clock, stall_timeout_s=0.2, max_reopens=3, backoff_s=0.05)
    with pytest.raises(CameraError, match=r"3 reopen attempts \(last: video file .* not found\)"):
        async with stream:
            async for ev in stream.events():
                if isinstance(ev, CameraFrame) and ev.seq == 5:
                    p.unlink()  # the file disappears (unplugged disk) ...
                    cam.stall(10.0)  # ... and the camera goes silent


async def test_source_end_ends_the_stream_without_stall(tmp_path: Path) -> None:
    p = tmp_path / "v.avi"
    write_avi(p, 20, fps=30.0)
    clock = ScaledClock()
    cam = VideoFileCamera(p, clock, pace=False)
    async with CameraStream(cam, clock) as stream:
        events = [ev async for ev in stream.events()]
    assert all(isinstance(e, CameraFrame) for e in events) and len(events) == 20
    assert cam.stats.stalls == 0


async def test_stall_timeout_covers_three_frame_periods(tmp_path: Path) -> None:
    p = tmp_path / "slow.avi"
    write_avi(p, 3, fps=2.0)
    clock = ScaledClock(speed=10.0)  # the wall-time floor (STALL_MIN_WALL_S) is 1.25 s here
    cam = VideoFileCamera(p, clock)
    async with CameraStream(cam, clock, stall_timeout_s=0.5) as stream:
        assert stream.effective_stall_timeout_s() == pytest.approx(1.5)
        events = [ev async for ev in stream.events()]
    assert [type(e) for e in events] == [CameraFrame] * 3


def test_invalid_settings_rejected() -> None:
    clock = ScaledClock()
    cam = VideoFileCamera("x.avi", clock)
    with pytest.raises(ValueError, match="stall_timeout_s"):
        CameraStream(cam, clock, stall_timeout_s=0.0)
    with pytest.raises(ValueError, match="max_reopens"):
        CameraStream(cam, clock, max_reopens=0)


# ------------------------------------------------------------- behind is not stalled


async def _events_with_hook(
    cam: VideoFileCamera, stream: CameraStream, hook: Callable[[RawFrame], None]
) -> list[tuple[CameraEvent, float]]:
    cam.frame_hook = hook
    out: list[tuple[CameraEvent, float]] = []
    async with stream:
        async for ev in stream.events():
            out.append((ev, stream.clock.now()))
    return out


async def test_a_file_camera_behind_a_slow_consumer_is_late_not_stalled(tmp_path: Path) -> None:
    """The consumer's work in the capture thread (the daemon's S_k, video and row) takes
    three stall timeouts on one frame (a loaded machine): the paced file camera behind it
    delivers every frame late, and that shows as lag, never as a stall and a reopen."""
    p = tmp_path / "v.avi"
    write_avi(p, 24, fps=30.0)
    clock = ScaledClock(speed=4.0)
    cam = VideoFileCamera(p, clock, pace=True)
    stream = CameraStream(cam, clock, stall_timeout_s=1.0)
    timeout_s = stream.effective_stall_timeout_s()

    def slow_consumer(raw: RawFrame) -> None:
        if raw.seq == 5:
            time.sleep(3.0 * timeout_s / clock.speed)  # wall time: 3 stall timeouts

    events = await _events_with_hook(cam, stream, slow_consumer)
    frames = [e for e, _ in events if isinstance(e, CameraFrame)]
    assert [type(e).__name__ for e, _ in events] == ["CameraFrame"] * 24
    assert [f.seq for f in frames] == list(range(24))
    assert cam.stats.stalls == 0 and cam.stats.reopens == 0 and cam.stats.dropped == 0
    # frame 6 came at least 3 stall timeouts after its capture time (paced: after frame 5)
    lag_6 = next(
        now - e.t_capture_s for e, now in events if isinstance(e, CameraFrame) and e.seq == 6
    )
    assert lag_6 >= 3.0 * timeout_s - 1.0 / 30.0
    assert cam.stats.max_lag_s >= lag_6


async def test_a_hooked_camera_that_goes_silent_is_still_stalled(tmp_path: Path) -> None:
    p = tmp_path / "v.avi"
    write_avi(p, 60, fps=30.0)
    clock = ScaledClock(speed=4.0)
    cam = VideoFileCamera(p, clock, pace=True)
    stream = CameraStream(cam, clock, stall_timeout_s=0.5, backoff_s=0.05)

    def hook(raw: RawFrame) -> None:
        if raw.seq == 5:
            cam.stall(0.8)  # the source freezes for 0.8 s of session time

    events = await _events_with_hook(cam, stream, hook)
    kinds = [type(e).__name__ for e, _ in events]
    assert kinds.count("CameraStalled") == 1 and cam.stats.stalls == 1
    stalled = next(e for e, _ in events if isinstance(e, CameraStalled))
    assert stalled.last_seq == 5 and stalled.silent_s >= 0.5
    assert kinds[kinds.index("CameraStalled") + 1] == "CameraRecovered"


async def test_a_file_camera_whose_decode_is_slow_is_late_not_stalled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One JPEG takes three stall timeouts to decode (a loaded machine; the real decoder,
    slowed): the paced file camera is working behind its frames' capture times, so it is
    late, not stalled."""
    p = tmp_path / "v.avi"
    write_avi(p, 24, fps=30.0)
    clock = ScaledClock(speed=4.0)
    cam = VideoFileCamera(p, clock, pace=True)
    stream = CameraStream(cam, clock, stall_timeout_s=1.0)
    timeout_s = stream.effective_stall_timeout_s()
    real_imdecode = cv2.imdecode
    calls = [0]

    def slow_imdecode(*args: Any) -> Any:
        calls[0] += 1
        if calls[0] == 6:
            time.sleep(3.0 * timeout_s / clock.speed)  # wall time: 3 stall timeouts
        return real_imdecode(*args)

    monkeypatch.setattr(cv2, "imdecode", slow_imdecode)
    events = await _events_with_hook(cam, stream, lambda raw: None)
    monkeypatch.undo()
    assert [type(e).__name__ for e, _ in events] == ["CameraFrame"] * 24
    assert cam.stats.stalls == 0 and cam.stats.reopens == 0
    assert cam.stats.max_lag_s >= 3.0 * timeout_s - 1.0 / 30.0
