"""The daemon's devices: session clock origin, probe link, camera stream and session.

This module owns the daemon's set-up and tear-down of its I/O: :func:`open_devices` builds
the probe (a :class:`~stipi_daemon.probe.link.ProbeLink` over the configured transport) and
the camera (a :class:`~stipi_daemon.cameras.stream.CameraStream` over the configured
source), connects and opens them, checks that the ROI lies within the camera's frame
(:func:`~stipi_daemon.app.imaging.check_roi_fits`) and that the calibration was made at
the camera's frame size (:meth:`Calibration.frame_size_problem`), and only then creates
the session (:class:`~stipi_daemon.storage.writer.SessionWriter`), so a missing port or
camera, an ROI outside the frame or a calibration of another frame size is one clear line
and no empty session; :func:`close_devices` stops and closes them.

Simulated and replayed devices (emulated probe, simulator camera, paced video file) play
one scene: they share its time origin on the session clock (:func:`scene_origin`), set
far enough ahead that all are open and the measurement is armed before the scene starts.
A probe the daemon does not emulate in its own process (``serial``, ``ble`` without
``emulate``: e.g. ``mock-peripheral`` in another process) plays its scene from the
STREAM_START it receives; next to a simulated or replayed camera, the origin is then
chosen once the probe link is open and the probe's STREAM_START is sent at it
(:class:`SceneStartProbeLink`), so both streams start the scene together (docs/bench.md).
Which transport or camera a config names is chosen by its ``kind`` (simulated ones through
:mod:`stipi_daemon.registry`); which calibration, threshold and ROI apply is decided before
(:mod:`stipi_daemon.app.imaging`). Nothing here measures or records rows.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.imaging import (
    CircleROI,
    FrameProcessor,
    RectROI,
    describe_roi,
    sk_kernel,
    to_gray,
)
from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.app.imaging import calibration_record, check_roi_fits, roi_field
from stipi_daemon.app.session_metadata import session_metadata
from stipi_daemon.cameras import CameraStream, open_camera
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import ConfigError
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.probe.link import ProbeLink
from stipi_daemon.probe.transports import TransportConfig, open_transport
from stipi_daemon.storage.video import VideoRecorder
from stipi_daemon.storage.writer import SessionWriter, StorageOptions

__all__ = [
    "SCENE_LEAD_WALL_S",
    "DaemonHandles",
    "Devices",
    "SceneStartProbeLink",
    "close_devices",
    "open_devices",
    "scene_origin",
]

#: Wall time between start-up and the shared scene origin of simulated devices [s]; for a
#: probe that plays its scene from STREAM_START, between its link being open and the origin.
SCENE_LEAD_WALL_S = 1.0


#: Wall time before a scheduled STREAM_START from which the loop polls the clock for it [s].
STREAM_START_SPIN_WALL_S = 0.005


@dataclass(frozen=True)
class Devices:
    """The opened devices and the session they record into.

    Attributes
    ----------
    clock : SessionClock
        The session clock.
    probe : ProbeLink
        The connected probe link (not yet streaming).
    camera : CameraStream
        The opened camera stream.
    writer : SessionWriter
        The new session.
    recorder : VideoRecorder or None
        Stores the measured frames in the session's ``video.mkv`` (None: ``storage.video``
        is ``off``).
    frame_size_px : tuple of int or None
        ``(width, height)`` the camera reported on opening [px], which the ROI and the
        calibration were checked against (None: it reported none).
    """

    clock: SessionClock
    probe: ProbeLink
    camera: CameraStream
    writer: SessionWriter
    recorder: VideoRecorder | None = None
    frame_size_px: tuple[int, int] | None = None


@dataclass(frozen=True)
class DaemonHandles:
    """The running daemon's parts, handed to an ``on_running`` callback.

    For supervision and for reliability tests, which inject faults into the real devices
    (``probe.transport.feather.unplug(...)``, ``camera.camera.stall(...)``) while the
    daemon records. The callback must not write to the session.

    Attributes
    ----------
    clock : SessionClock
        The session clock.
    probe : ProbeLink
        The probe link.
    camera : CameraStream
        The camera stream.
    writer : SessionWriter
        The session being recorded.
    pipeline : MeasurementPipeline
        The live measurement (``pipeline.phase`` is the state machine's phase).
    """

    clock: SessionClock
    probe: Any
    camera: Any
    writer: SessionWriter
    pipeline: MeasurementPipeline


def scene_origin(clock: SessionClock, given_s: float | None) -> float:
    """Session time of scene time 0 for simulated and replayed devices [s].

    ``given_s`` when a caller's own device plays the scene from a known instant, else
    :data:`SCENE_LEAD_WALL_S` of wall time from now.
    """
    return given_s if given_s is not None else clock.now() + SCENE_LEAD_WALL_S * clock.speed


class SceneStartProbeLink(ProbeLink):
    """A :class:`ProbeLink` whose first STREAM_START waits for a session time.

    For a probe that plays its scene from the STREAM_START it receives (``mock-peripheral``,
    a Feather emulated in another process) next to a simulated or replayed camera: the
    daemon's first :meth:`start_stream` sleeps until :attr:`stream_start_at_s`, so the
    probe's scene starts at the camera's scene origin. Reconnections start the stream at
    once, as :class:`ProbeLink` does (the scene goes on in the probe).
    """

    stream_start_at_s: float | None = None
    """Session time to send the first STREAM_START at [s] (None: at once)."""
    on_stream_start: Callable[[float, float, bool], None] | None = None
    """Called with the scheduled and the actual session time of that STREAM_START [s] and
    whether the probe acknowledged it (False: the link was down or went down before the
    ACK; the probe may then have started its scene only with the reconnection's)."""

    async def start_stream(self) -> bool:
        at, self.stream_start_at_s = self.stream_start_at_s, None
        if at is None:
            return await super().start_stream()
        # A timer wakes the loop late on a busy host (milliseconds of wall time, times the
        # clock's speed): sleep to just before the instant, then yield until it comes.
        clock = self.clock
        if clock.waits_for_daemon:  # its time is exact: no timer wakes it late
            await clock.sleep_until(at)
        else:
            await clock.sleep_until(at - STREAM_START_SPIN_WALL_S * clock.speed)
            while clock.now() < at:
                await asyncio.sleep(0)
        sent_s = clock.now()
        acknowledged = await super().start_stream()
        if self.on_stream_start is not None:
            self.on_stream_start(at, sent_s, acknowledged)
        return acknowledged


def plays_scene_from_stream_start(config: DaemonConfig) -> bool:
    """Whether the probe's scene starts with STREAM_START next to a scene-playing camera.

    True for a probe the daemon does not emulate in its own process (``serial``, ``ble``
    without ``emulate``) and a simulator camera or a paced video file: the two play one
    scene on separate clocks, and only STREAM_START ties the probe's to the session's.
    """
    tc = config.probe.transport
    in_process = tc.kind == "emulated" or (tc.kind == "ble" and tc.emulate is not None)
    return _plays_scene(config) and not in_process


def _plays_scene(config: DaemonConfig) -> bool:
    """Whether the camera plays the scene on the session clock (simulator, paced file)."""
    # A paced video file replays the scene too (e.g. the simulator's rendering of it).
    return config.camera.kind == "simulator" or (
        config.camera.kind == "file" and config.camera.pace
    )


def _follow_probe_link(clock: SessionClock, probe: SceneStartProbeLink) -> float:
    """The scene origin chosen once the probe link is open [s]; schedules STREAM_START.

    The origin is :data:`SCENE_LEAD_WALL_S` of wall time from now: the camera opens, the
    session is created and the measurement armed before it. STREAM_START goes one sample
    period before it: the firmware restarts its sample timer on STREAM_START and takes the
    first sample one period later (``firmware/feather32u4/src/hal_avr.cpp``, CTC mode from
    TCNT1 = 0; :class:`~stipi_daemon.sim.feather.FeatherCore` likewise), and that sample is
    the probe's scene time 0.
    """
    origin_s = clock.now() + SCENE_LEAD_WALL_S * clock.speed
    probe.stream_start_at_s = origin_s - 1.0 / probe.rate_hz
    return origin_s


def _transport_config(config: DaemonConfig, origin_s: float) -> TransportConfig:
    """The probe's transport config, an emulated probe's scene started at ``origin_s``."""
    tc = config.probe.transport
    if tc.kind == "emulated" and tc.scene_start_s is None:
        return tc.model_copy(update={"scene_start_s": origin_s})
    if tc.kind == "ble" and tc.emulate is not None and tc.emulate.scene_start_s is None:
        emulate = tc.emulate.model_copy(update={"scene_start_s": origin_s})
        return tc.model_copy(update={"emulate": emulate})
    return tc


def _probe_link(
    config: DaemonConfig, clock: SessionClock, origin_s: float, *, scheduled_start: bool = False
) -> ProbeLink:
    """The probe link the config describes (not yet connected); with ``scheduled_start`` a
    :class:`SceneStartProbeLink`."""
    pc = config.probe
    cls = SceneStartProbeLink if scheduled_start else ProbeLink
    return cls(
        open_transport(_transport_config(config, origin_s), clock),
        clock=clock,
        rate_hz=pc.rate_hz,
        led_level=pc.led_level,
        heartbeat_timeout_s=pc.heartbeat_timeout_s,
        reconnect_total_s=pc.reconnect_total_s,
        zero_counts=pc.zero_counts,
        span_un_per_count=pc.span_un_per_count,
    )


def _camera_stream(config: DaemonConfig, clock: SessionClock, origin_s: float) -> CameraStream:
    """The camera stream the config describes (not yet opened)."""
    simulated = _plays_scene(config)
    return CameraStream(
        open_camera(config.camera, clock, t0_s=origin_s if simulated else None),
        clock,
        # A simulated or replayed camera's first frame comes at the scene origin.
        open_timeout_s=2.0 + max(0.0, origin_s - clock.now() if simulated else 0.0),
    )


def _create_session(
    config: DaemonConfig,
    calibration: Calibration,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    probe: ProbeLink,
    size: tuple[int, int] | None,
) -> SessionWriter:
    """Create the session: config, calibration record (with the camera's frame ``size``
    [px]), probe info, software versions, metadata (subject, site, operator, note)."""
    storage = config.storage
    return SessionWriter.create(
        storage.root,
        config.model_dump(mode="json"),
        calibration_record(
            calibration,
            threshold_p,
            roi,
            str(config.calibration) if config.calibration else "simulated scene",
            size,
        ),
        probe.info_dict(),
        options=StorageOptions(
            commit_interval_s=storage.commit_interval_s,
            min_free_bytes=int(storage.min_free_mb * 1e6),
            min_free_setting=f"config field storage.min_free_mb = {storage.min_free_mb:g} MB",
        ),
        software={"sk_kernel": sk_kernel()},
        video=storage.video != "off",
        metadata=session_metadata(config),
    )


def _video_recorder(
    config: DaemonConfig,
    writer: SessionWriter,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    clock: SessionClock,
    camera_metadata: dict[str, Any],
    frame_rate_hz: float | None = None,
) -> VideoRecorder | None:
    """The session video's recorder as ``storage.video`` says (None: ``off``).

    Every source is recorded, at any clock speed: ``passthrough`` (the default) stores the
    JPEG packets of a source that delivers them (an MJPG camera or file, a simulated MJPG
    camera) as received and records any other source (raw, YUYV, gray cameras; the
    simulator's clean frames) losslessly, as ``lossless`` does; the simulator and a video
    file wait for the encoders rather than leave frames out (docs/storage.md).
    ``video_roi_only`` stores the gray bounding box of the ROI of lossless frames; a
    passthrough of JPEG packets stores the whole frame (a packet cannot be cropped without
    re-encoding it): said at start (:func:`_note_roi_only_ignored`).
    """
    storage, path = config.storage, writer.video_path
    if storage.video == "off" or path is None:
        return None

    def roi_box(shape: tuple[int, ...]) -> tuple[int, int, int, int] | None:
        if roi is None:
            return None
        y0, y1, x0, x1 = FrameProcessor(shape, threshold_p, roi).bounding_box
        return x0, y0, x1, y1

    if storage.video_roi_only:
        if storage.video == "passthrough" and delivers_jpeg_packets(camera_metadata):
            _note_roi_only_ignored(writer, clock.now(), camera_metadata)
        recorder = VideoRecorder(
            path, writer, storage.video, crop=roi_box, to_gray=to_gray, frame_rate_hz=frame_rate_hz
        )
    else:
        recorder = VideoRecorder(path, writer, storage.video, frame_rate_hz=frame_rate_hz)
    if clock.waits_for_daemon:  # a simulated world waits for the encoders: no frame left out
        recorder.wait_max_s = math.inf
    return recorder


def delivers_jpeg_packets(metadata: dict[str, Any]) -> bool:
    """Whether an opened camera delivers each frame's JPEG packet, by its metadata.

    The simulator when its scene's camera is MJPG (``jpeg_quality`` set); a video file
    read as raw MJPG packets (``decoder``); a V4L2 camera that takes the driver's JPEGs raw
    and decodes them itself (``applied.jpeg_packets``, or its ``applied.decode`` mode).
    """
    from stipi_daemon.cameras.video_file import DECODER_JPEG

    applied = metadata.get("applied")
    applied = applied if isinstance(applied, dict) else {}
    v4l2 = applied.get("jpeg_packets", applied.get("decode") in ("jpeg_gray", "jpeg_bgr"))
    return (
        metadata.get("jpeg_quality") is not None
        or metadata.get("decoder") == DECODER_JPEG
        or v4l2 is True
    )


def _note_roi_only_ignored(writer: SessionWriter, t_s: float, metadata: dict[str, Any]) -> None:
    """Event ``video_roi_only_ignored`` and one warning line on stderr: ``video_roi_only``
    with a passthrough of JPEG packets stores the whole frame."""
    reason = (
        "storage.video_roi_only is ignored: storage.video passthrough stores the camera's "
        "JPEG packets as received, whole (a packet cannot be cropped without re-encoding); "
        "set storage.video: lossless to store the ROI's gray box"
    )
    _warn(writer, t_s, "video_roi_only_ignored", reason, camera=metadata.get("kind"), crop=None)


def _warn(writer: SessionWriter, t_s: float, kind: str, reason: str, **detail: Any) -> None:
    """A warning at start: event ``kind`` at session time ``t_s`` [s] (``reason`` and
    ``detail``) in the session, and one line on stderr."""
    writer.add_event(t_s, kind, {"reason": reason, **detail})
    print(f"stipi-daemon: warning: {reason}", file=sys.stderr)


def frame_size(metadata: dict[str, Any]) -> tuple[int, int] | None:
    """An opened camera's frame size ``(width, height)`` [px] from its metadata, or None.

    Cameras record it as ``size: [w, h]`` (simulator, video file) or, for V4L2, what the
    driver granted as ``applied: {width, height}`` (top-level ``width`` and ``height`` are
    read too).
    """
    size = metadata.get("size")
    applied = metadata.get("applied")
    if isinstance(size, list | tuple) and len(size) == 2:
        w, h = size
    elif isinstance(applied, dict) and "width" in applied:
        w, h = applied.get("width"), applied.get("height")
    else:
        w, h = metadata.get("width"), metadata.get("height")
    if isinstance(w, int) and isinstance(h, int) and w > 0 and h > 0:
        return w, h
    return None


def _check_frame(
    config: DaemonConfig,
    camera: CameraStream,
    roi: CircleROI | RectROI | None,
    calibration: Calibration,
) -> tuple[int, int] | None:
    """The camera's frame size [px] (None: it does not say), once the ROI fits it and the
    calibration was made at it; :class:`ConfigError` naming the field otherwise."""
    size = frame_size(camera.camera.metadata())
    if size is None:
        return None
    if roi is not None:
        check_roi_fits(roi, size[0], size[1], roi_field(config, calibration))
    where = f"field 'calibration' ({config.calibration})" if config.calibration else "the scene"
    problem = calibration.frame_size_problem(size[0], size[1], "the camera")
    if problem is not None:
        w, h = calibration.frame_size_px or size
        raise ConfigError(
            f"{where}: {problem}; set the camera to {w}x{h} or calibrate at {size[0]}x{size[1]}"
        )
    return size


def _warn_unrecorded(
    config: DaemonConfig,
    writer: SessionWriter,
    calibration: Calibration,
    size: tuple[int, int] | None,
    roi: CircleROI | RectROI | None,
    t_s: float,
) -> None:
    """Record (events ``calibration_frame_size_unknown``, ``calibration_roi_unknown`` at
    session time ``t_s`` [s]) and print what the calibration does not say it was made at,
    so that nothing checked it against the camera's frame ``size`` [px] or the ``roi`` (a
    scene's calibration records both)."""
    if config.calibration is None:
        return
    cal = f"the calibration {config.calibration} does not record"
    if calibration.frame_size_px is None and size is not None:
        reason = (
            f"{cal} the frame size it was made at (field 'frame_size_px'): D_p and F_r are "
            f"right only if that was {size[0]}x{size[1]} px, the camera's "
            "(`stipi-daemon calibrate --frame-size`)"
        )
        _warn(writer, t_s, "calibration_frame_size_unknown", reason, camera=size)
    if calibration.roi is None:
        reason = (
            f"{cal} the ROI it was made in (field 'roi'): D_p and F_r are right only if that "
            f"was {describe_roi(roi)}, the one counted in (`stipi-daemon calibrate --roi`)"
        )
        detail = None if roi is None else roi.model_dump(mode="json")
        _warn(writer, t_s, "calibration_roi_unknown", reason, roi=detail)


async def open_devices(
    config: DaemonConfig,
    clock: SessionClock,
    calibration: Calibration,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    *,
    origin_s: float | None,
) -> Devices:
    """Connect the probe, open the camera, then create the session.

    Parameters
    ----------
    config : DaemonConfig
        The configuration (paths resolved).
    clock : SessionClock
        The session clock.
    calibration, threshold_p, roi
        What S_k is counted with (:mod:`stipi_daemon.app.imaging`), for the manifest.
    origin_s : float or None
        Session time of scene time 0 for simulated and replayed devices [s], given when a
        device the caller started plays the scene from that instant (kept as it is); None:
        :func:`scene_origin` chooses it, and for a probe that plays its scene from
        STREAM_START next to a scene-playing camera (:func:`plays_scene_from_stream_start`)
        it is chosen again once the probe link is open, and STREAM_START sent at it.

    Raises
    ------
    StipiError
        A device cannot be opened, the ROI does not lie within the camera's frame or the
        calibration was made at another frame size than the camera's
        (:class:`~stipi_daemon.errors.ConfigError` naming the field), or the session
        cannot be created (one line; what was opened is closed again and nothing is
        recorded).
    """
    # A probe playing its scene from STREAM_START: the camera's origin is chosen once the
    # probe link is open (connecting over BLE can take longer than the lead).
    follow = origin_s is None and plays_scene_from_stream_start(config)
    origin_s = scene_origin(clock, origin_s)
    probe = _probe_link(config, clock, origin_s, scheduled_start=follow)
    camera = None if follow else _camera_stream(config, clock, origin_s)
    await probe.connect()
    try:
        if camera is None:
            assert isinstance(probe, SceneStartProbeLink)
            origin_s = _follow_probe_link(clock, probe)
            camera = _camera_stream(config, clock, origin_s)
        await camera.open()
        size = _check_frame(config, camera, roi, calibration)
    except BaseException:
        if camera is not None:
            with contextlib.suppress(Exception):
                await camera.close()
        await probe.close()
        raise
    try:
        writer = _create_session(config, calibration, threshold_p, roi, probe, size)
    except BaseException:
        await camera.close()
        await probe.close()
        raise
    _warn_unrecorded(config, writer, calibration, size, roi, clock.now())
    if isinstance(probe, SceneStartProbeLink):
        _record_stream_start(writer, probe, origin_s)
    recorder = _video_recorder(
        config,
        writer,
        threshold_p,
        roi,
        clock,
        camera.camera.metadata(),
        camera.camera.nominal_fps,
    )
    return Devices(clock, probe, camera, writer, recorder, size)


def _record_stream_start(
    writer: SessionWriter, probe: SceneStartProbeLink, origin_s: float
) -> None:
    """Record, when it is sent, when the probe's STREAM_START was due and went out.

    Event ``stream_start``: the camera's scene origin, the scheduled and the actual session
    time of STREAM_START [s]; ``late_s`` > 0 shifts the probe's scene after the camera's by
    that much (the release's image/force check flags more than a few frame periods).
    ``acknowledged`` false: the link was down or went down before the probe's ACK, so the
    probe may have started its scene only with the STREAM_START of the reconnection, later
    than ``sent_s`` by an amount not known here (``note`` says so).
    """

    def record(at_s: float, sent_s: float, acknowledged: bool) -> None:
        detail: dict[str, object] = {
            "scene_origin_s": origin_s,
            "scheduled_s": at_s,
            "sent_s": sent_s,
            "late_s": sent_s - at_s,
            "acknowledged": acknowledged,
            "rule": "the probe plays its scene from STREAM_START (docs/bench.md)",
        }
        if not acknowledged:
            detail["note"] = (
                "the link went down before the probe acknowledged STREAM_START: its scene "
                "started with this STREAM_START or the reconnection's, so late_s is a lower "
                "bound (the release's image/force check flags a larger shift)"
            )
        writer.add_event(sent_s, "stream_start", detail)

    probe.on_stream_start = record


async def close_devices(devices: Devices) -> None:
    """Stop the probe's stream (best effort), close the camera and the video, then the probe."""
    with contextlib.suppress(Exception):
        await devices.probe.stop_stream()
    await devices.camera.close()
    if devices.recorder is not None:
        devices.recorder.close()
    await devices.probe.close()
