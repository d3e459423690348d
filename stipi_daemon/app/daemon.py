"""The acquisition daemon: probe and camera in, one measurement's session out.

``stipi-daemon --config probe.yaml`` runs :func:`run_measurement`, which runs
:func:`run_daemon` in its own event loop. The daemon decides what S_k is counted with
(:mod:`stipi_daemon.app.imaging`), opens the probe and the camera and creates the session
(:mod:`stipi_daemon.app.devices`), records until the state machine reaches DONE or a fault
(:mod:`stipi_daemon.app.acquisition`: probe and camera pumps, a ticker, the time-ordered
feed into the pure :class:`~stipi_daemon.measurement.pipeline.MeasurementPipeline`, live
rows, the operator console), and finishes (:mod:`stipi_daemon.app.finish`: stores three
representative raw frames, writes ``summary.json``, prints the results and writes the
session's report). It leaves no task running when it returns.

All times are on the session clock (:mod:`stipi_daemon.clock`): real devices run at speed
1, simulated ones may be accelerated (the demo). This module owns the order of those steps
and what a run's end looks like (:class:`RunOutcome`); decoding, clock sync, the state
machine, the analysis and storage live in their own modules.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

from threadpoolctl import threadpool_limits

from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.analysis.results import force_full_scale_n
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.validity import assess_validity
from stipi_daemon.app.acquisition import Acquisition, OnRunning
from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.app.console import OperatorConsole
from stipi_daemon.app.devices import (
    SCENE_LEAD_WALL_S,
    DaemonHandles,
    Devices,
    close_devices,
    open_devices,
)
from stipi_daemon.app.finish import (
    finish_session,
    note_video_left_out,
    percentiles,
    print_results,
    run_stats,
    session_summary,
    storage_failure,
    unfinished_summary,
)
from stipi_daemon.app.frame_measurer import FrameMeasurer
from stipi_daemon.app.imaging import resolve_imaging
from stipi_daemon.app.liveview.live import serving_live_view
from stipi_daemon.app.liveview.state import ViewInfo, roi_dict
from stipi_daemon.app.memory import hold_heap, return_free_memory
from stipi_daemon.clock import ScaledClock, SessionClock, VirtualClock
from stipi_daemon.errors import EXIT_FAULT, EXIT_OK, SessionError, Terminated
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.representative_frames import RepresentativeFrames
from stipi_daemon.measurement.state_machine import Phase
from stipi_daemon.storage.writer import SessionWriter

__all__ = ["SCENE_LEAD_WALL_S", "DaemonHandles", "RunOutcome", "run_daemon", "run_measurement"]


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
        """:data:`~stipi_daemon.errors.EXIT_OK` for a measurement that was made, whatever
        its verdict (a frame left out of the video, an invalid result: the verdict says
        so); :data:`~stipi_daemon.errors.EXIT_FAULT` when a fault stopped it."""
        return EXIT_OK if self.phase == Phase.DONE else EXIT_FAULT


#: Said when a session ended early: its recording may still hold a usable recovery.
_RESCUE_HINT = (
    "the session is incomplete; `stipi-daemon analyze {}` computes what its recording "
    "allows (written beside it, never over it)"
)


def _acquisition_fault(pipeline: MeasurementPipeline, line: str) -> dict[str, Any]:
    """The summary entries of a run the acquisition ended itself (it fell behind, the
    camera's frames changed size)."""
    return {
        "status": "fault",
        "end_reason": line,
        **assess_validity(
            pipeline.result,
            ended_done=False,
            end_reason=line,
            analysis_error=pipeline.analysis_error,
        ),
    }


def _frame_measurer(
    config: DaemonConfig,
    devices: Devices,
    threshold: int,
    roi: CircleROI | RectROI | None,
    keeper: RepresentativeFrames,
    pipeline: MeasurementPipeline,
) -> FrameMeasurer:
    """The camera side: S_k counted, frames stored in the session and its video."""
    measurer = FrameMeasurer(
        devices.clock,
        threshold,
        roi,
        config.imaging.saturation_limit_fraction,
        keeper,
        pipeline,
        # frames later than half the lag bound are not measured (gaps): the run catches up
        skip_late_s=config.run.max_lag_s / 2.0,
        writer=devices.writer,
        frame_size_px=devices.frame_size_px,
    )
    measurer.recorder = devices.recorder  # the session video (storage.video)
    return measurer


def _view_info(
    config: DaemonConfig, writer: SessionWriter, threshold: int, roi: CircleROI | RectROI | None
) -> ViewInfo:
    """What the live view shows that does not change during the run."""
    m = config.measurement
    return ViewInfo(
        session_id=writer.session_id,
        metadata=config.session.model_dump(),
        threshold_p=threshold,
        roi=roi_dict(roi),
        pitting_duration_s=m.pitting_duration_s,
        recovery_max_s=m.recovery_max_s,
        force_band_n=(
            m.target_force_n - m.force_tolerance_n,
            m.target_force_n + m.force_tolerance_n,
        ),
    )


def run_measurement(
    config: DaemonConfig,
    *,
    speed: float | None = None,
    out: TextIO | None = None,
    quiet: bool = False,
    live: bool | None = None,
    on_session: Callable[[SessionWriter], None] | None = None,
) -> RunOutcome:
    """Run one measurement (blocking); see :func:`run_daemon`.

    BLAS runs single-threaded meanwhile: its only work is the live fits' small solves, and
    OpenBLAS's worker threads spin between calls, taking CPU the capture thread, the event
    loop and the video encoder need (2.5 s of CPU in a 125 s demo at speed 10). The C
    heap reuses frame buffers and has two arenas meanwhile (:mod:`.memory`).
    """
    hold_heap()  # frame buffers reused from the heap, two arenas (app/memory.py)
    with threadpool_limits(limits=1, user_api="blas"), _sigterm_as_interrupt() as terminated:
        try:
            return asyncio.run(
                run_daemon(
                    config, speed=speed, out=out, quiet=quiet, live=live, on_session=on_session
                )
            )
        except KeyboardInterrupt:
            if terminated:
                name = signal.Signals(terminated[0]).name
                why = " (the terminal closed)" if terminated[0] == signal.SIGHUP else ""
                raise Terminated(f"terminated ({name}){why}", 128 + terminated[0]) from None
            raise


def _import_scipy() -> None:
    """The analysis imports SciPy where it uses it (other commands start faster): the daemon
    imports it before measuring, not in its first live fit, which would hold the GIL for it
    while frames come in."""
    for module in ("scipy.ndimage", "scipy.optimize"):
        importlib.import_module(module)


#: Signals that stop a measurement as Ctrl-C does: SIGTERM (``kill PID``, a service
#: manager's stop) and SIGHUP (the terminal closed).
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGHUP)


@contextlib.contextmanager
def _sigterm_as_interrupt() -> Iterator[list[int]]:
    """While measuring, SIGTERM (``kill PID``, a service manager's stop) and SIGHUP (its
    terminal closed) stop the daemon as Ctrl-C does: the session is finished ``aborted``
    and the devices are closed, where the default action ends the process with the
    session left unfinished. Yields the list of those signals received. Only in the main
    thread (where Python handles signals) and over the default action (a handler the
    caller set, or SIGHUP ignored by ``nohup``, stays)."""
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def on_stop(signum: int, _frame: object) -> None:
        received.append(signum)
        signal.raise_signal(signal.SIGINT)  # asyncio.run's Ctrl-C: cancels the measurement

    ours = [s for s in STOP_SIGNALS if signal.getsignal(s) is signal.SIG_DFL]
    for s in ours:
        signal.signal(s, on_stop)
    try:
        yield received
    finally:
        for s in ours:
            signal.signal(s, signal.SIG_DFL)


def _say_how_it_ended(
    console: OperatorConsole, status: str, storage_error: SessionError | None, directory: Path
) -> None:
    """After the session is finished: a measurement that did not end says so, and where
    its data is; one whose console output failed raises :class:`Terminated`."""
    if status == "aborted" or storage_error is not None:
        how = "aborted" if storage_error is None else "stopped: storing failed"
        console.line(f"measurement {how}; what was recorded is in {directory}")
        console.line(_RESCUE_HINT.format(directory))
    if console.lost is not None and storage_error is None:
        raise _output_lost(console.lost, status, directory)


def _output_lost(reason: str, status: str, directory: Path) -> Terminated:
    """The one line (and Ctrl-C's exit status) of a measurement whose console output
    failed: stopped then as by Ctrl-C, or, when it failed after the end, finished."""
    if status == "aborted":
        return Terminated(f"stopped: {reason}; the session is finished (aborted): {directory}", 130)
    return Terminated(f"{reason}; the session is finished ({status}): {directory}", 130)


async def run_daemon(
    config: DaemonConfig,
    *,
    speed: float | None = None,
    out: TextIO | None = None,
    quiet: bool = False,
    live: bool | None = None,
    clock: SessionClock | None = None,
    scene_origin_s: float | None = None,
    on_session: Callable[[SessionWriter], None] | None = None,
    on_running: OnRunning | None = None,
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
    clock : SessionClock, optional
        The session clock to run on (default: :func:`session_clock`); lets a caller
        start devices of its own (an emulated probe on a pty, a firmware simulation) on
        the same timeline before the daemon starts.
    scene_origin_s : float, optional
        Session time of scene time 0 for simulated and replayed devices [s] (default:
        :data:`SCENE_LEAD_WALL_S` after start-up); give it when a device started by the
        caller plays the scene from a known instant.
    on_session : callable, optional
        Called with the session's :class:`~.writer.SessionWriter` once it exists.
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
    Terminated
        The console's output failed (closed, full): stopped as by Ctrl-C (one line).
    """
    if clock is None:
        clock = session_clock(config, speed)
    if isinstance(clock, VirtualClock):
        async with clock.running():
            return await _run_daemon(
                config, out, quiet, live, clock, scene_origin_s, on_session, on_running
            )
    return await _run_daemon(
        config, out, quiet, live, clock, scene_origin_s, on_session, on_running
    )


def session_clock(config: DaemonConfig, speed: float | None = None) -> SessionClock:
    """The clock a run of ``config`` runs on: a :class:`VirtualClock` paced at ``speed``
    (default ``run.speed``) when every device is simulated in this process (the emulated
    probe and a scene-playing camera), which waits for the daemon; wall time times
    ``speed`` otherwise (a real device cannot wait) and with ``run.clock: wall``."""
    pace = speed if speed is not None else config.run.speed
    if config.run.clock == "auto" and config.simulated_world:
        return VirtualClock(pace or None)  # run.speed 0: as fast as the daemon goes
    return ScaledClock(pace)


async def _run_daemon(
    config: DaemonConfig,
    out: TextIO | None,
    quiet: bool,
    live: bool | None,
    clock: SessionClock,
    scene_origin_s: float | None,
    on_session: Callable[[SessionWriter], None] | None,
    on_running: OnRunning | None,
) -> RunOutcome:
    """:func:`run_daemon` on its clock."""
    _import_scipy()
    calibration, threshold, roi, truth = resolve_imaging(config)
    reference = load_reference()
    console = OperatorConsole(config.measurement, out, live=live, quiet=quiet)
    wall0 = time.monotonic()
    origin_s = scene_origin_s  # None: open_devices chooses it (after the probe link, if need be)
    devices = await open_devices(config, clock, calibration, threshold, roi, origin_s=origin_s)
    writer = devices.writer
    if on_session is not None:
        on_session(writer)
    pipeline = MeasurementPipeline(
        measurement=config.measurement,
        analysis=config.analysis,
        calibration=calibration,
        reference=reference,
        t_start_s=clock.now(),
    )
    # the load cell's rail, as the session records the probe (analyze reads it back)
    pipeline.force_full_scale_n = force_full_scale_n(devices.probe.info_dict())
    # Which frames the report shows (their pictures are read from the session video).
    keeper = RepresentativeFrames(config.measurement.pitting_duration_s)
    measurer = _frame_measurer(config, devices, threshold, roi, keeper, pipeline)
    # the session's frames are the measurement's: none captured after its end is stored
    pipeline.on_end_known = measurer.store_until
    acquisition = Acquisition(config, devices, pipeline, console, measurer)
    # The live view in the browser, when asked for: it reads what the acquisition publishes.
    view = contextlib.ExitStack()
    served = view.enter_context(
        serving_live_view(config.view, _view_info(config, writer, threshold, roi), console)
    )
    if served is not None:
        acquisition.live = served[0]
        measurer.preview = served[0].frame
    status = "aborted"
    # Until the measurement ends: an interruption (Ctrl-C) or an unexpected error leaves
    # this summary, whose verdict is incomplete.
    stopped = "stopped before the measurement ended (interrupted or an error)"
    summary = unfinished_summary("aborted", stopped)
    storage_error: SessionError | None = None
    try:
        with console:
            await acquisition.run(on_running)
            summary = session_summary(pipeline, truth)
            status = "complete" if pipeline.phase == Phase.DONE else "fault"
            if acquisition.fault_line is not None:
                status = "fault"
                summary |= _acquisition_fault(pipeline, acquisition.fault_line)
    except SessionError as exc:
        # Storage failed (disk full, I/O error, the video's muxer): stop recording now, keep
        # what is stored; the summary says why the measurement did not end.
        storage_error, status = exc, "fault"
        summary = unfinished_summary("fault", f"recording stopped: {exc.__cause__ or exc}")
    finally:
        await acquisition.stop()
        await close_devices(devices)
        return_free_memory()  # before the analysis and the report: large blocks mmapped
        summary["run"] = run_stats(
            devices,
            clock=clock,
            wall_s=time.monotonic() - wall0,
            counts=acquisition.counts,
            latencies_s=acquisition.latencies_s,
            merge_released_by_timeout=acquisition.merger.released_by_timeout,
            keeper=keeper,
        ) | {"lag_s": percentiles(acquisition.lag_s), "max_lag_s": config.run.max_lag_s}
        left_out = 0 if devices.recorder is None else devices.recorder.left_out
        if left_out:  # a fact of the session: an event and its verdict, not a failure
            writer.add_event(clock.now(), "video_frames_left_out", {"count": left_out})
            summary = note_video_left_out(summary, left_out)
        wall = {"wall_s": repr(time.monotonic() - wall0), "clock": type(clock).__name__}
        if isinstance(clock, VirtualClock):
            wall |= {"pace": repr(clock.pace), "clock_steps": str(clock.steps)}
        with view:  # the live view stops once the session is finished, whatever happens
            finish_session(writer, status, summary, storage_error, wall)
        _say_how_it_ended(console, status, storage_error, writer.directory)
    if storage_error is not None:
        raise storage_failure(writer, storage_error) from storage_error
    print_results(console, summary, writer.db_path.parent, acquisition.stop_error)
    if status != "complete":
        console.line(_RESCUE_HINT.format(writer.directory))
    if console.lost is not None:  # failed after the end: the session is whole, say so
        raise _output_lost(console.lost, status, writer.directory)
    return RunOutcome(writer.db_path.parent, pipeline.phase, summary, summary["run"])
