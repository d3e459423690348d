"""The acquisition daemon: probe and camera in, one measurement's session out.

``stipi-daemon --config probe.yaml`` runs :func:`run_measurement`. It opens the probe
(a :class:`~stipi_daemon.probe.link.ProbeLink` over the configured transport) and the camera
(a :class:`~stipi_daemon.cameras.stream.CameraStream` over the configured source), creates
the session, and then runs four asyncio tasks until the measurement ends:

* the probe pump: force samples (with raw, unwrapped and clock-synchronised times),
  gaps, clock probes and link events from the probe;
* the camera pump: every frame's S_k (Eqs. 1-2) measured as it arrives, camera stalls;
* a ticker, so timeouts fire when nothing else arrives;
* the main loop, which streams every row into the session (:mod:`stipi_daemon.storage`)
  as it arrives (each frame's row committed at once, with whatever else is buffered),
  feeds samples and frames in time order
  (:class:`~stipi_daemon.measurement.merge.TimeOrderedMerger`, as an offline replay does)
  into the pure :class:`~stipi_daemon.measurement.pipeline.MeasurementPipeline`, and keeps
  the operator console current.

All times are on the session clock (:mod:`stipi_daemon.clock`): real devices run at speed
1, simulated ones may be accelerated (the demo). When the state machine reaches DONE or
a fault, the daemon stops the stream, stores three representative raw frames
(:mod:`stipi_daemon.report.frames`), writes ``summary.json``, prints the results and
writes the session's report (``report/report.html``, :mod:`stipi_daemon.report`; a
report that cannot be drawn is noted, never costs the session). It
owns orchestration only: decoding, clock sync, the state machine, the analysis and
storage live in their own modules.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Callable, Coroutine
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from stipi_daemon import __version__
from stipi_daemon.analysis.imaging import FrameProcessor, sk_kernel
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.app.console import OperatorConsole, format_results
from stipi_daemon.app.imaging import calibration_record, resolve_imaging
from stipi_daemon.clock import ScaledClock
from stipi_daemon.errors import SessionError, StipiError
from stipi_daemon.measurement.merge import TimeOrderedMerger
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.state_machine import (
    Advisory,
    CameraRecovered,
    CameraStalled,
    Fault,
    LinkLost,
    LinkRestored,
    OperatorPrompt,
    Output,
    Phase,
    PhaseChanged,
    Tick,
)
from stipi_daemon.report.frames import RepresentativeFrames, write_representative_frames
from stipi_daemon.storage.writer import SessionWriter, StorageOptions

__all__ = ["DaemonHandles", "RunOutcome", "run_daemon", "run_measurement"]

#: Interval between stored live-parameter rows and console updates [s of session time].
LIVE_INTERVAL_S = 1.0
#: Interval of the ticker that lets timeouts fire when no data arrives [s of session time].
TICK_S = 0.05
#: Wall time between start-up and the shared scene origin of simulated devices [s].
SCENE_LEAD_WALL_S = 1.0
#: Longest a sample or frame waits for the other stream before it is fed anyway [s].
MERGE_HOLD_S = 0.5


def _same(ev: object) -> object:
    return ev


def _feed(pipeline: MeasurementPipeline, kind: str, value: tuple[float, float]) -> list[Output]:
    t_s, v = value
    return pipeline.force(t_s, v) if kind == "force" else pipeline.frame(t_s, v)


@dataclass(frozen=True)
class RunOutcome:
    """How a run ended.

    Attributes
    ----------
    session_dir : Path
        The session directory.
    phase : Phase
        Terminal phase (``DONE`` or a fault).
    summary : dict
        What ``summary.json`` holds.
    stats : dict
        Run statistics: frames, samples, gaps, latency percentiles [s], wall time [s].
    """

    session_dir: Path
    phase: Phase
    summary: dict[str, Any]
    stats: dict[str, Any]

    @property
    def exit_code(self) -> int:
        """0 for a completed measurement with results, 1 otherwise."""
        return 0 if self.phase == Phase.DONE and self.summary.get("results") else 1


@dataclass(frozen=True)
class DaemonHandles:
    """The running daemon's parts, handed to an ``on_running`` callback.

    For supervision and for reliability tests, which inject faults into the real devices
    (``probe.transport.feather.unplug(...)``, ``camera.camera.stall(...)``) while the
    daemon records. The callback must not write to the session.

    Attributes
    ----------
    clock : ScaledClock
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

    clock: ScaledClock
    probe: Any
    camera: Any
    writer: SessionWriter
    pipeline: MeasurementPipeline


@dataclass(frozen=True)
class _FrameResult:
    seq: int
    t_capture_s: float
    t_processed_s: float
    s_k: int
    flags: tuple[str, ...]
    dropped_before: int
    image: npt.NDArray[np.uint8]


class _Stop:
    """Sentinel: a pump ended (its source is exhausted or failed)."""

    def __init__(self, who: str, error: BaseException | None = None) -> None:
        self.who = who
        self.error = error


def run_measurement(
    config: DaemonConfig,
    *,
    speed: float | None = None,
    out: TextIO | None = None,
    quiet: bool = False,
    live: bool | None = None,
    on_session: Callable[[SessionWriter], None] | None = None,
) -> RunOutcome:
    """Run one measurement (blocking); see :func:`run_daemon`."""
    return asyncio.run(
        run_daemon(config, speed=speed, out=out, quiet=quiet, live=live, on_session=on_session)
    )


async def run_daemon(
    config: DaemonConfig,
    *,
    speed: float | None = None,
    out: TextIO | None = None,
    quiet: bool = False,
    live: bool | None = None,
    clock: ScaledClock | None = None,
    scene_origin_s: float | None = None,
    on_session: Callable[[SessionWriter], None] | None = None,
    on_running: Callable[[DaemonHandles], Coroutine[Any, Any, None]] | None = None,
) -> RunOutcome:
    """Record and analyse one measurement as ``config`` says.

    Parameters
    ----------
    config : DaemonConfig
        The configuration (paths resolved).
    speed : float, optional
        Session seconds per wall second; default ``config.run.speed`` (1 for real
        devices; the demo accelerates its simulated devices).
    out, quiet, live
        Console output (see :class:`~stipi_daemon.app.console.OperatorConsole`).
    clock : ScaledClock, optional
        The session clock to run on (default: a new one at ``speed``); lets a caller
        start devices of its own (an emulated probe on a pty, a firmware simulation) on
        the same timeline before the daemon starts.
    scene_origin_s : float, optional
        Session time of scene time 0 for simulated and replayed devices [s] (default:
        :data:`SCENE_LEAD_WALL_S` after start-up); give it when a device started by the
        caller plays the scene from a known instant.
    on_session : callable, optional
        Called with the :class:`~stipi_daemon.storage.writer.SessionWriter` once the
        session exists (e.g. to record commit times in a benchmark).
    on_running : async callable, optional
        Run as a task with the :class:`DaemonHandles` once the stream has started, and
        cancelled when the measurement ends (fault injection in reliability tests).

    Raises
    ------
    StipiError
        A device cannot be opened or the session cannot be created (one line; nothing
        is recorded in that case).
    SessionError
        Storing rows failed while recording (disk full, I/O error): the daemon stops at
        once (within 1 s), keeps every row committed before, leaves the session
        ``interrupted`` (``fault`` if the final state could still be stored) and says why
        in one line.
    """
    from stipi_daemon.cameras import CameraFrame, CameraStream, open_camera
    from stipi_daemon.cameras import CameraRecovered as CamRecovered
    from stipi_daemon.cameras import CameraStalled as CamStalled
    from stipi_daemon.probe.link import (
        ClockProbe,
        ForceRows,
        Gap,
        LinkDown,
        LinkUp,
        ProbeLink,
    )
    from stipi_daemon.probe.transports import open_transport

    if clock is None:
        clock = ScaledClock(speed if speed is not None else config.run.speed)
    run_speed = clock.speed
    calibration, threshold, roi, truth = resolve_imaging(config)
    reference = load_reference()
    console = OperatorConsole(config.measurement, out, live=live, quiet=quiet)
    wall0 = time.monotonic()

    # Simulated and replayed devices (emulated probe, simulator camera, video file) play
    # one scene: they share its time origin, set far enough ahead that all are open and
    # the measurement is armed before the scene starts.
    origin_s = (
        scene_origin_s
        if scene_origin_s is not None
        else clock.now() + SCENE_LEAD_WALL_S * clock.speed
    )
    pc = config.probe
    transport_config = pc.transport
    if transport_config.kind == "emulated" and transport_config.scene_start_s is None:
        transport_config = transport_config.model_copy(update={"scene_start_s": origin_s})
    elif (
        transport_config.kind == "ble"
        and transport_config.emulate is not None
        and transport_config.emulate.scene_start_s is None
    ):
        emulate = transport_config.emulate.model_copy(update={"scene_start_s": origin_s})
        transport_config = transport_config.model_copy(update={"emulate": emulate})
    probe = ProbeLink(
        open_transport(transport_config, clock),
        clock=clock,
        rate_hz=pc.rate_hz,
        led_level=pc.led_level,
        heartbeat_timeout_s=pc.heartbeat_timeout_s,
        reconnect_total_s=pc.reconnect_total_s,
        zero_counts=pc.zero_counts,
        span_un_per_count=pc.span_un_per_count,
    )
    # A paced video file replays the scene too (e.g. the simulator's rendering of it).
    simulated_camera = config.camera.kind == "simulator" or (
        config.camera.kind == "file" and config.camera.pace
    )
    camera = CameraStream(
        open_camera(config.camera, clock, t0_s=origin_s if simulated_camera else None),
        clock,
        # A simulated or replayed camera's first frame comes at the scene origin.
        open_timeout_s=2.0 + max(0.0, origin_s - clock.now() if simulated_camera else 0.0),
    )
    # Devices first: a missing port or camera is one clear line and no empty session.
    await probe.connect()
    try:
        await camera.open()
    except BaseException:
        await probe.close()
        raise
    storage = config.storage
    try:
        writer = SessionWriter.create(
            storage.root,
            config.model_dump(mode="json"),
            calibration_record(
                calibration,
                threshold,
                roi,
                str(config.calibration) if config.calibration else "simulated scene",
            ),
            probe.info_dict(),
            options=StorageOptions(
                commit_interval_s=storage.commit_interval_s,
                min_free_bytes=int(storage.min_free_mb * 1e6),
            ),
            software={"sk_kernel": sk_kernel()},
        )
    except BaseException:
        await camera.close()
        await probe.close()
        raise
    if on_session is not None:
        on_session(writer)

    pipeline = MeasurementPipeline(
        measurement=config.measurement,
        analysis=config.analysis,
        calibration=calibration,
        reference=reference,
        t_start_s=clock.now(),
    )
    queue: asyncio.Queue[object] = asyncio.Queue()
    processor: FrameProcessor | None = None
    # A few raw frames kept for the report (the session stores S_k, not video).
    keeper = RepresentativeFrames(config.measurement.pitting_duration_s)
    latencies: list[float] = []
    counts = {"frames": 0, "samples": 0, "gaps": 0, "dropped_frames": 0}

    async def pump(
        who: str, events: AsyncIterator[object], convert: Callable[[object], object] = _same
    ) -> None:
        """Queue a source's events (converted), then a :class:`_Stop` when it ends or fails."""
        try:
            async for ev in events:
                await queue.put(convert(ev))
        except asyncio.CancelledError:
            raise
        except BaseException as exc:
            await queue.put(_Stop(who, exc))
            return
        await queue.put(_Stop(who))

    def measure(ev: object) -> object:
        """A camera frame's S_k, measured as it arrives; other camera events as they are."""
        nonlocal processor
        if not isinstance(ev, CameraFrame):
            return ev
        if processor is None:
            processor = FrameProcessor(
                ev.image.shape,
                threshold,
                roi,
                saturation_limit_fraction=config.imaging.saturation_limit_fraction,
            )
        m = processor.measure(ev.image)
        return _FrameResult(
            ev.seq,
            ev.t_capture_s,
            clock.now(),
            int(m.s_k_px),
            tuple(sorted(m.flags)),
            ev.dropped_before,
            ev.image,
        )

    async def ticker() -> None:
        while True:
            await asyncio.sleep(clock.wall_seconds(TICK_S))
            await queue.put(Tick(clock.now()))

    def record(outputs: list[Output]) -> None:
        now = pipeline.state.now_s
        console.outputs(outputs, now)
        for o in outputs:
            if isinstance(o, PhaseChanged):
                writer.add_transition(o.t_s, str(o.old), str(o.new), o.reason)
            elif isinstance(o, Advisory):
                writer.add_event(o.t_s, f"advisory:{o.kind}", {"detail": o.detail})
            elif isinstance(o, Fault):
                writer.add_event(o.t_s, f"fault:{o.kind}", {"reason": o.reason})
            elif isinstance(o, OperatorPrompt):
                writer.add_event(now, "prompt", {"text": o.text})

    # Samples and frames reach the pipeline in time order (as on replay), each held at
    # most MERGE_HOLD_S for the other stream.
    merger: TimeOrderedMerger[tuple[float, float]] = TimeOrderedMerger(
        ["force", "frame"], max_hold_s=MERGE_HOLD_S
    )
    tasks: list[asyncio.Task[None]] = []
    status = "aborted"
    summary: dict[str, Any] = {"status": "aborted"}
    next_live = 0.0
    stop_error: BaseException | None = None
    storage_error: SessionError | None = None
    try:
        with console:
            console.line(f"session {writer.session_id} in {storage.root}")
            record(pipeline.arm(clock.now()))
            # How session times map onto the host's monotonic clock (time.monotonic()).
            writer.add_event(
                clock.now(),
                "session_clock",
                {
                    "speed": clock.speed,
                    "monotonic_origin_s": time.monotonic() - clock.now() / clock.speed,
                },
            )
            await probe.start_stream()
            tasks = [
                asyncio.create_task(pump("probe", probe.events()), name="probe"),
                asyncio.create_task(pump("camera", camera.events(), measure), name="camera"),
                asyncio.create_task(ticker(), name="ticker"),
            ]
            if on_running is not None:
                handles = DaemonHandles(clock, probe, camera, writer, pipeline)
                tasks.append(asyncio.create_task(on_running(handles), name="on_running"))
            while True:
                ev = await queue.get()
                outputs: list[Output] = []
                if isinstance(ev, ForceRows):
                    rows = ev.rows
                    writer.add_force_samples(
                        [
                            (
                                r.sample_index,
                                r.adc_counts,
                                r.t_mcu_raw_us,
                                r.t_mcu_us,
                                r.t_host_s,
                                r.force_n,
                            )
                            for r in rows
                        ]
                    )
                    counts["samples"] += len(rows)
                    for r in rows:
                        if r.force_n is not None:
                            merger.push("force", r.t_host_s, (r.t_host_s, r.force_n), clock.now())
                    if rows and rows[-1].force_n is not None:
                        console.update(pipeline.state.now_s, force_n=rows[-1].force_n)
                elif isinstance(ev, _FrameResult):
                    writer.add_frames(
                        [(ev.seq, ev.t_capture_s, ev.t_processed_s, ev.s_k, ev.flags)]
                    )
                    st = pipeline.state
                    keeper.offer(
                        ev.seq,
                        ev.t_capture_s,
                        ev.image,
                        ev.s_k,
                        st.phase,
                        st.t_pit_start_s,
                        st.t_release_s,
                    )
                    latencies.append(clock.now() - ev.t_capture_s)
                    counts["frames"] += 1
                    if ev.dropped_before:
                        counts["dropped_frames"] += ev.dropped_before
                        writer.add_gap(
                            "frames",
                            ev.seq - ev.dropped_before,
                            ev.dropped_before,
                            ev.t_capture_s,
                            "camera",
                        )
                    # Each frame is on disk before the next is due (with it, whatever else
                    # is buffered): a WAL commit at synchronous=NORMAL costs ~15 us, against
                    # up to 3/4 of storage.commit_interval_s of waiting for the commit
                    # thread (docs/performance.md, "Live daemon latency").
                    writer.commit()
                    merger.push(
                        "frame", ev.t_capture_s, (ev.t_capture_s, float(ev.s_k)), clock.now()
                    )
                    console.update(pipeline.state.now_s, s_k=ev.s_k, fps=camera.stats.fps())
                elif isinstance(ev, Gap):
                    counts["gaps"] += 1
                    writer.add_gap("force", ev.start_index, ev.count, ev.t_host_s, ev.cause)
                elif isinstance(ev, ClockProbe):
                    writer.add_clock_probe(ev.mcu_raw_us, ev.mcu_unwrapped_us, ev.host_s)
                elif isinstance(ev, LinkDown):
                    writer.add_event(ev.t_s, "link_down", {"reason": ev.reason})
                    outputs += pipeline.feed(LinkLost(ev.t_s))
                elif isinstance(ev, LinkUp):
                    writer.add_event(ev.t_s, "link_up", {})
                    outputs += pipeline.feed(LinkRestored(ev.t_s))
                elif isinstance(ev, CamStalled):
                    writer.add_event(ev.t_s, "camera_stalled", {"detail": str(ev)})
                    outputs += pipeline.feed(CameraStalled(ev.t_s))
                elif isinstance(ev, CamRecovered):
                    writer.add_event(ev.t_s, "camera_recovered", {"detail": str(ev)})
                    outputs += pipeline.feed(CameraRecovered(ev.t_s))
                elif isinstance(ev, Tick):
                    # Ticks only let timeouts fire when data stops: they lag the data by the
                    # merge hold and never pass a held sample, so while data flows they
                    # change nothing (and an offline replay, which has no ticks, agrees).
                    t_tick = ev.t_s - MERGE_HOLD_S
                    pending = merger.oldest_pending_s()
                    if pending is not None:
                        t_tick = min(t_tick, pending)
                    if t_tick > pipeline.state.now_s:
                        outputs += pipeline.feed(Tick(t_tick))
                elif isinstance(ev, _Stop):
                    # A source ended (e.g. a video file) or failed: close the session.
                    stop_error = ev.error
                    writer.add_event(
                        clock.now(),
                        f"{ev.who}_ended",
                        {"error": None if ev.error is None else str(ev.error)},
                    )
                    for kind, value in merger.drain():
                        outputs += _feed(pipeline, kind, value)
                    outputs += pipeline.close(clock.now())
                for kind, value in merger.pop_ready(clock.now()):
                    if pipeline.finished:
                        break
                    outputs += _feed(pipeline, kind, value)
                if outputs:
                    record(outputs)
                if pipeline.finished:
                    break
                now = pipeline.state.now_s
                if now >= next_live and pipeline.state.t_release_s is not None:
                    next_live = now + LIVE_INTERVAL_S
                    live_params = pipeline.live()
                    if live_params is not None:
                        writer.add_live_parameters(now, live_params.to_dict())
                        console.update(now, params=live_params)
            summary = _summary(pipeline, truth)
            status = "complete" if pipeline.phase == Phase.DONE else "fault"
    except SessionError as exc:
        # Storage failed (disk full, I/O error): stop recording now, keep what is stored.
        storage_error = exc
    finally:
        for t in tasks:
            t.cancel()
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t
        with contextlib.suppress(Exception):
            await probe.stop_stream()
        await camera.close()
        await probe.close()
        summary["run"] = {
            "software": __version__,
            "speed": run_speed,
            "wall_s": time.monotonic() - wall0,
            **counts,
            "frame_latency_s": _percentiles(latencies),
            "merge_released_by_timeout": merger.released_by_timeout,
            "probe": probe.stats_dict(),
            "camera": camera.stats.as_dict() | {"source": camera.camera.metadata()},
            "representative_frames": _store_frames(keeper, writer.directory),
        }
        if storage_error is None:
            writer.finish(status, summary)
            writer.close()
        else:
            # Best effort: the disk that failed may still take the final state.
            with contextlib.suppress(SessionError):
                writer.finish(
                    "fault", summary | {"status": "fault", "storage_error": str(storage_error)}
                )
            with contextlib.suppress(SessionError):
                writer.close()
        if status == "aborted":  # interrupted (Ctrl-C) or an unexpected error
            console.line(f"measurement aborted; what was recorded is in {writer.directory}")
    if storage_error is not None:
        cause = storage_error.__cause__ or storage_error
        raise SessionError(
            f"{writer.directory}: recording stopped, the session could not be stored ({cause}); "
            "the rows committed before are kept"
        ) from storage_error
    for line in format_results(summary):
        console.line(line)
    console.line(f"session written to {writer.db_path.parent}")
    console.line(_write_report(writer.db_path.parent))
    if stop_error is not None and isinstance(stop_error, StipiError):
        console.line(f"source ended with an error: {stop_error}")
    return RunOutcome(writer.db_path.parent, pipeline.phase, summary, summary["run"])


def _store_frames(keeper: RepresentativeFrames, session_dir: Path) -> list[str] | dict[str, str]:
    """Store the representative frames; a failure is recorded, never raised."""
    try:
        return [p.name for p in write_representative_frames(session_dir, keeper.selected())]
    except Exception as exc:
        return {"error": str(exc)}


def _write_report(session_dir: Path) -> str:
    """Write the finished session's report; a failure is noted, never raised."""
    try:
        from stipi_daemon.report.write import write_session_report

        return f"report written to {write_session_report(session_dir).html_path}"
    except Exception as exc:
        note: Path | None = None
        with contextlib.suppress(Exception):
            from stipi_daemon.report.write import record_report_failure

            note = record_report_failure(session_dir, exc)
        return f"report not written: {exc}" + (f" (noted in {note})" if note else "")


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"median": None, "p99": None, "max": None}
    a = np.asarray(values, dtype=np.float64)
    return {
        "median": float(np.median(a)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def _summary(pipeline: MeasurementPipeline, truth: dict[str, Any] | None) -> dict[str, Any]:
    start = pipeline.start
    out: dict[str, Any] = {
        "status": "complete" if pipeline.phase == Phase.DONE else "fault",
        "phase": str(pipeline.phase),
        "end_reason": pipeline.state.end_reason,
        "measurement": None if start is None else asdict(start) | {"t0_refined_s": pipeline.t0_s},
        "measurement_flags": sorted(pipeline.state.flags),
        "results": None if pipeline.result is None else pipeline.result.to_dict(),
        "analysis_error": pipeline.analysis_error,
        "notes": list(pipeline.notes),
    }
    if truth is not None:
        out["ground_truth"] = truth
    return out
