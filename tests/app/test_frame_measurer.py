"""The camera side: a frame's S_k, video frame and row made together in the capture thread.

Real parts throughout: a session writer on disk, the passthrough video recorder (PyAV), the
S_k kernel, and a thread of its own as the camera's capture thread.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pytest

from stipi_daemon.app.acquisition import Acquisition
from stipi_daemon.app.frame_measurer import FrameMeasurer, FrameResult, LateFrame, ResizedFrame
from stipi_daemon.cameras import CameraFrame
from stipi_daemon.cameras.threaded import RawFrame, ThreadedCamera
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import SessionError
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.video import VideoRecorder

OPTS = StorageOptions(min_free_bytes=0, background_commit=False)


def _frame(k: int) -> tuple[np.ndarray, bytes]:
    """A 48x64 frame whose S_k (p = 128) is 64 * k px, its JPEG, and the JPEG's decode."""
    image = np.full((48, 64), 200, np.uint8)
    image[:k] = 20
    packet = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 100])[1].tobytes()
    gray = cv2.imdecode(np.frombuffer(packet, np.uint8), cv2.IMREAD_GRAYSCALE)
    return np.asarray(gray, np.uint8), packet


def _measurer(
    tmp_path: Path, clock: ScaledClock, frame_size_px: tuple[int, int] | None = None
) -> tuple[FrameMeasurer, SessionWriter]:
    writer = SessionWriter.create(tmp_path, {}, {}, session_id="s", video=True, options=OPTS)
    assert writer.video_path is not None
    pipeline = SimpleNamespace(
        state=SimpleNamespace(phase=Phase.PITTING, t_pit_start_s=0.0, t_release_s=None)
    )
    keeper = RepresentativeFrames(pitting_duration_s=2.0)
    measurer = FrameMeasurer(
        clock,
        128,
        None,
        0.5,
        keeper,
        pipeline,
        skip_late_s=5.0,
        writer=writer,  # type: ignore[arg-type]
        frame_size_px=frame_size_px,
    )
    measurer.recorder = VideoRecorder(writer.video_path, writer, "passthrough")
    return measurer, writer


def _in_thread(measurer: FrameMeasurer, raws: list[RawFrame], period_s: float = 0.0) -> list[Any]:
    """``on_capture`` of each frame, in a thread of its own (as the camera's), one every
    ``period_s`` of wall time."""
    out: list[Any] = []

    def capture() -> None:
        for r in raws:
            out.append(measurer.on_capture(r))
            time.sleep(period_s)

    t = threading.Thread(target=capture)
    t.start()
    t.join(10.0)
    return out


def test_the_frame_row_and_video_frame_are_made_where_the_frame_arrives(tmp_path: Path) -> None:
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    frames = [_frame(k) for k in range(1, 6)]
    raws = [RawFrame(10 + k, clock.now(), gray, pk) for k, (gray, pk) in enumerate(frames)]
    # a 50 fps camera: each frame comes more than COMMIT_SPACING_WALL_S after the previous
    captured = _in_thread(measurer, raws, period_s=0.02)
    # on disk before the loop has seen anything: committed by the capture thread
    with SessionReader(writer.directory) as r:
        rows = r.frames()
    assert rows["seq"].tolist() == [10, 11, 12, 13, 14]
    assert rows["s_k"].tolist() == [int(np.count_nonzero(g <= 128)) for g, _ in frames]
    results = [
        measurer(CameraFrame(raw.seq, raw.t_capture_s, raw.image, 0, raw.packet, c))
        for raw, c in zip(raws, captured, strict=True)
    ]
    assert all(isinstance(x, FrameResult) and x.error is None for x in results)
    assert [x.s_k for x in results] == rows["s_k"].tolist()
    assert [x.t_processed_s for x in results] == rows["t_host_s"].tolist()
    assert measurer.recorder is not None
    measurer.recorder.close()
    writer.finish("complete")
    writer.close()
    with SessionReader(tmp_path / "s") as r:
        assert r.video_frames()["seq"].tolist() == [10, 11, 12, 13, 14]
        assert r.integrity_check().ok


def test_after_the_measurement_ends_frames_are_no_longer_stored(tmp_path: Path) -> None:
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    gray, pk = _frame(3)
    _in_thread(measurer, [RawFrame(0, clock.now(), gray, pk)])
    measurer.stop_storing()
    (late,) = _in_thread(measurer, [RawFrame(1, clock.now(), gray, pk)])
    result = measurer(CameraFrame(1, late.t_done_s, gray, 0, pk, late))
    assert isinstance(result, FrameResult) and result.s_k == 3 * 64  # measured all the same
    assert measurer.recorder is not None
    measurer.recorder.close()
    writer.commit()
    with SessionReader(writer.directory) as r:
        assert r.frames()["seq"].tolist() == [0]
        assert r.video_frames()["seq"].tolist() == [0]
    writer.close()


def test_frames_captured_after_the_measurements_end_are_not_stored(tmp_path: Path) -> None:
    """Once the end is known (the pipeline tells it), a frame captured after it is measured
    for the loop but neither stored nor offered as a representative frame, whenever it is
    delivered; the end can move (the analysis starts before the window's end)."""
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    measurer.store_until(3.5)
    measurer.store_until(2.5)  # settled: the analysis starts before the window's end
    # S_k falls frame after frame: the keeper's recovery_start would be the last offered
    frames = [_frame(k) for k in (5, 4, 3, 1)]
    raws = [RawFrame(k, 1.0 + k, gray, pk) for k, (gray, pk) in enumerate(frames)]
    captured = _in_thread(measurer, raws)
    results = [
        measurer(CameraFrame(raw.seq, raw.t_capture_s, raw.image, 0, raw.packet, c))
        for raw, c in zip(raws, captured, strict=True)
    ]
    assert [(r.seq, r.s_k, r.stored) for r in results] == [
        (0, 5 * 64, True),
        (1, 4 * 64, True),
        (2, 3 * 64, False),  # captured at 3.0 s, after the end at 2.5 s: measured all the same
        (3, 1 * 64, False),
    ]
    assert [(f.kind, f.seq) for f in measurer._keeper.selected()] == [
        ("pitting", 0),
        ("recovery_start", 1),
    ]
    assert measurer.stored == 2
    assert measurer.recorder is not None
    measurer.recorder.close()
    writer.commit()
    with SessionReader(writer.directory) as r:
        assert r.frames()["seq"].tolist() == [0, 1]
        assert r.video_frames()["seq"].tolist() == [0, 1]
    writer.close()


def test_a_late_frame_is_neither_measured_nor_stored(tmp_path: Path) -> None:
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    gray, pk = _frame(2)
    (c,) = _in_thread(measurer, [RawFrame(4, clock.now() - 6.0, gray, pk)])  # 6 s > 5 s
    late = measurer(CameraFrame(4, clock.now() - 6.0, gray, 1, pk, c))
    assert isinstance(late, LateFrame) and late.lag_s > 5.0 and late.dropped_before == 1
    writer.commit()
    with SessionReader(writer.directory) as r:
        assert r.frames().size == 0 and r.video_frames().size == 0
    assert measurer.recorder is not None
    measurer.recorder.close()
    writer.close()


def test_a_frame_of_another_shape_is_neither_measured_nor_stored(tmp_path: Path) -> None:
    """S_k counts pixels: a frame of another size (or gray after colour) than the session's
    first is not the session's quantity, nor can its video stream take it. It becomes a
    ResizedFrame naming both shapes (the loop ends the run); the frames before are kept."""
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    gray, pk = _frame(2)
    small = np.ascontiguousarray(gray[:24, :32])
    small_pk = cv2.imencode(".jpg", small)[1].tobytes()
    bgr = np.ascontiguousarray(np.dstack([gray] * 3))
    raws = [
        RawFrame(0, clock.now(), gray, pk),
        RawFrame(1, clock.now(), small, small_pk),
        RawFrame(2, clock.now(), bgr, pk),
    ]
    captured = _in_thread(measurer, raws)
    results = [
        measurer(CameraFrame(r.seq, r.t_capture_s, r.image, 2 * (r.seq == 1), r.packet, c))
        for r, c in zip(raws, captured, strict=True)
    ]
    assert isinstance(results[0], FrameResult) and results[0].s_k == 2 * 64
    assert results[1] == ResizedFrame(1, raws[1].t_capture_s, (24, 32), (48, 64), 2)
    assert results[2] == ResizedFrame(2, raws[2].t_capture_s, (48, 64, 3), (48, 64), 0)
    writer.commit()
    with SessionReader(writer.directory) as r:
        assert r.frames()["seq"].tolist() == [0]
    assert measurer.recorder is not None
    assert measurer.recorder.failed is None and measurer.recorder.frames == 1
    measurer.recorder.close()
    writer.close()


def test_a_first_frame_of_another_size_than_the_camera_reported_is_not_measured(
    tmp_path: Path,
) -> None:
    """The ROI and the calibration were checked against the size the camera reported on
    opening (a V4L2 driver's granted size, a file's header); a camera that then delivers
    frames of another size would have set the session's size with its first frame, and S_k
    were counted on pixels the calibration was not made for, unflagged. The first frame
    must have the reported size: otherwise a ResizedFrame (``reported``), which the loop
    turns into a fault naming both sizes; a frame of the reported size is measured."""
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock, frame_size_px=(32, 24))
    gray, pk = _frame(2)  # 64x48
    (captured,) = _in_thread(measurer, [RawFrame(0, clock.now(), gray, pk)])
    result = measurer(CameraFrame(0, captured.t_done_s, gray, 0, pk, captured))
    assert result == ResizedFrame(0, captured.t_done_s, (48, 64), (24, 32), 0, reported=True)
    assert measurer.shape is None
    assert isinstance(result, ResizedFrame) and result.fault_line() == (
        "camera: frame 0 is 64x48 gray, but the camera reported 32x24 px frames on opening, "
        "the size the ROI and the calibration were checked against; the measurement "
        "stopped there"
    )
    small = np.ascontiguousarray(gray[:24, :32])
    (ok,) = _in_thread(measurer, [RawFrame(1, clock.now(), small, None)])
    assert measurer(CameraFrame(1, ok.t_done_s, small, 0, None, ok)).s_k == 2 * 32
    assert measurer.shape == (24, 32)
    assert measurer.recorder is not None
    measurer.recorder.close()
    writer.close()


def test_a_storage_failure_travels_with_the_frame_and_stops_the_run(tmp_path: Path) -> None:
    """A full disk seen in the capture thread (the writer's or the video's error) reaches the
    loop with the frame's result; the loop raises it, and nothing more is stored."""
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    gray, pk = _frame(1)
    _in_thread(measurer, [RawFrame(0, clock.now(), gray, pk)])
    writer.fail(SessionError("session.sqlite: database or disk is full"))
    failed = _in_thread(measurer, [RawFrame(k, clock.now(), gray, pk) for k in (1, 2)])
    assert all(c.error is not None for c in failed)
    result = measurer(CameraFrame(1, clock.now(), gray, 0, pk, failed[0]))
    assert isinstance(result, FrameResult) and result.error is not None
    devices = SimpleNamespace(clock=clock, writer=writer, camera=None, probe=None)
    config = SimpleNamespace(run=SimpleNamespace(speed=1.0, max_lag_s=5.0))
    acq = Acquisition(config, devices, None, None, measurer)  # type: ignore[arg-type]
    with pytest.raises(SessionError, match="disk is full"):
        acq._on_frame(result)
    assert measurer.recorder is not None
    assert measurer.recorder.frames == 1  # the video stopped with the rows
    measurer.recorder.close()
    writer.close()
    with SessionReader(tmp_path / "s") as r:
        assert r.frames()["seq"].tolist() == [0]


class _JpegCamera(ThreadedCamera[list[int]]):
    """A source of ``n`` MJPG frames (48x64, their JPEG packets), as fast as it is read, one
    of which waits for its consumer (a file): the capture thread runs the real hook path."""

    def __init__(self, clock: ScaledClock, n: int) -> None:
        super().__init__(clock, capacity=4, drop_oldest=False, paced=False)
        self.n = n

    @property
    def name(self) -> str:
        return "jpeg"

    @property
    def nominal_fps(self) -> float:
        return 60.0

    def _open_source(self) -> list[int]:
        return [0]

    def _read(self, handle: list[int]) -> RawFrame | None:
        k = handle[0]
        if k >= self.n:
            return None
        handle[0] += 1
        gray, packet = _frame(1 + k % 40)
        return RawFrame(k, k / 60, gray, packet)

    def _close_source(self, handle: list[int]) -> None:
        pass


@pytest.mark.parametrize("failure", ["ExternalError", "RuntimeError"])
async def test_a_video_error_of_any_ffmpeg_class_stops_the_video_without_a_second_row(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, failure: str
) -> None:
    """PyAV raises ``av.ExternalError`` (neither an OSError nor a ValueError) while muxing
    frame 6, through the camera's real capture thread and hook: the video stops cleanly
    (its cause in the recorder's error and a ``video_stopped`` event), the error travels
    with the frame to the loop, and no frame gets a second ``frames`` row (the camera
    measures a frame again on the loop when its hook raised). Any other exception there (a
    bug) stops the run the same way, never with a second row."""
    import av

    from stipi_daemon.storage import video as video_module

    write = video_module.write_video_frame
    calls = [0]

    def failing_at_the_7th(*args: Any, **kwargs: Any) -> None:
        calls[0] += 1
        if calls[0] == 7:
            if failure == "ExternalError":
                raise av.ExternalError(-1, "injected muxer failure")  # type: ignore[call-arg]
            raise RuntimeError("injected muxer failure")
        write(*args, **kwargs)

    monkeypatch.setattr(video_module, "write_video_frame", failing_at_the_7th)
    clock = ScaledClock(1.0)
    measurer, writer = _measurer(tmp_path, clock)
    camera = _JpegCamera(clock, 12)
    camera.frame_hook = measurer.on_capture
    await camera.open()
    results = [measurer(ev) async for ev in camera.frames()]
    await camera.close()
    assert measurer.recorder is not None
    measurer.recorder.close()
    errors = [r.error for r in results if isinstance(r, FrameResult)]
    assert errors[:6] == [None] * 6 and all(e is not None for e in errors[6:])
    assert failure in str(errors[6]) and "injected muxer failure" in str(errors[6])
    error = measurer.recorder.stats()["error"]
    if failure == "ExternalError":  # the video's own failure: recorded as such
        assert error is not None and "ExternalError: " in error and "video.mkv" in error
    summary = {"storage_error": str(errors[6]), "run": {"video": measurer.recorder.stats()}}
    writer.finish("fault", summary)
    writer.close()
    with SessionReader(tmp_path / "s") as r:
        seqs = r.frames()["seq"].tolist()
        assert len(seqs) == len(set(seqs))  # never a second row of one frame
        assert seqs == list(range(7))  # the failing frame's row, then nothing more
        assert r.video_frames()["seq"].tolist() == list(range(6))
        stopped = [e.detail["error"] for e in r.events() if e.kind == "video_stopped"]
        assert stopped == ([error] if failure == "ExternalError" else [])
        assert r.integrity_check().ok, r.integrity_check().problems
