"""The daemon's acquisition loop: probe and camera events in, session rows and results out.

:class:`Acquisition` runs one measurement on opened devices (:mod:`stipi_daemon.app.devices`)
with four asyncio tasks until the state machine finishes:

* the probe pump: force samples (with raw, unwrapped and clock-synchronised times), gaps,
  clock probes and link events from the probe;
* the camera pump: every frame's S_k (Eqs. 1-2), video frame and ``frames`` row, made in
  the camera's capture thread as it arrives (:class:`FrameMeasurer`,
  :mod:`stipi_daemon.app.frame_measurer`: committed at once, at most every
  :data:`COMMIT_SPACING_WALL_S` of wall time), and camera stalls; the queue carries a
  :class:`FrameResult` per frame (a :class:`LateFrame` for a frame too late to measure), and
  the raw image goes to the representative-frame keeper
  (:mod:`stipi_daemon.measurement.representative_frames`) and no further;
* a ticker, so timeouts fire when nothing else arrives;
* the loop itself, which takes each event to its handler (one per event type, in a table),
  streams every other row into the session (:mod:`stipi_daemon.storage`) as it arrives,
  feeds samples and frames in time order
  (:class:`~stipi_daemon.measurement.merge.TimeOrderedMerger`, as an offline replay does)
  into the pure :class:`~stipi_daemon.measurement.pipeline.MeasurementPipeline`, stores live
  parameters and keeps the operator console current. When the measurement ends, frames are
  no longer stored.

Falling behind. On a simulated run's clock (:class:`~stipi_daemon.clock.VirtualClock`)
the daemon is never behind: session time waits until every frame and sample due has been
handled, so the lag is 0 but where a scene's ``processing_stall`` holds frames back on
purpose. On wall time (real devices) it is what the machine makes it. The queue is
bounded (:data:`QUEUE_MAX_EVENTS`; images never enter it), so memory stays bounded at any
``run.speed``: a full queue holds the pumps back, and the
camera's own bounded hand-off then drops (a live camera, counted) or waits (a simulated
one). The lag - session time when a frame is handled minus its capture time - is measured
on every frame and stored (``summary.json`` ``run.lag_s``). Samples and ticks reach the
measurement no further ahead than the camera (the merger's clock and the ticks run the
lag behind), so the session never ends while frames of its window are still queued.
Frames delivered more than half of ``run.max_lag_s`` late are not measured but stored as
gaps (reason ``processing_behind``, missing frames to the analysis, never silent); a lag
above ``run.max_lag_s`` ends the run with a fault and one line (:attr:`Acquisition.fault_line`).
So does a frame of another size than the session's first (a gap, reason
``frame_size_changed``): its S_k would count pixels of another size. Before the first frame
arrives, the lag of a camera that waits for the daemon (simulator, file) is that of its
first frame, due since its known capture time. When no frame has been handled for 0.5 s
of session time the console warns, with what the gap does to the results, and says when
frames come again and which came too late to be measured
(:class:`~stipi_daemon.app.frame_watch.FrameWatch`; events ``frames_not_processed`` and
``frames_processed_again``).

All times are on the session clock [s]. Opening devices, the summary, the stored frames
and the report are not done here (:mod:`stipi_daemon.app.devices`,
:mod:`stipi_daemon.app.finish`).
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import sys
import time
from collections import deque
from collections.abc import AsyncIterator, Callable, Coroutine
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.app.console import OperatorConsole
from stipi_daemon.app.devices import DaemonHandles, Devices
from stipi_daemon.app.frame_measurer import (
    COMMIT_SPACING_WALL_S,
    FrameMeasurer,
    FrameResult,
    LateFrame,
    ResizedFrame,
)
from stipi_daemon.app.frame_watch import FrameWatch
from stipi_daemon.app.liveview.live import live_statuses
from stipi_daemon.app.liveview.state import LiveState
from stipi_daemon.cameras import CameraRecovered as CamRecovered
from stipi_daemon.cameras import CameraStalled as CamStalled
from stipi_daemon.cameras.threaded import ThreadedCamera
from stipi_daemon.clock import SessionClock
from stipi_daemon.measurement.merge import TimeOrderedMerger
from stipi_daemon.measurement.pipeline import LiveParameters, MeasurementPipeline, compute_live
from stipi_daemon.measurement.state_machine import (
    Advisory,
    CameraRecovered,
    CameraStalled,
    Fault,
    LinkLost,
    LinkRestored,
    OperatorPrompt,
    Output,
    PhaseChanged,
    Tick,
)
from stipi_daemon.probe.link import (
    ClockProbe,
    ForceRows,
    Gap,
    LinkDown,
    LinkUp,
    ProbeHealth,
    StatusReport,
)

__all__ = [
    "COMMIT_SPACING_WALL_S",
    "LIVE_INTERVAL_S",
    "MERGE_HOLD_S",
    "QUEUE_MAX_EVENTS",
    "TICK_S",
    "Acquisition",
    "FrameMeasurer",
    "FrameResult",
    "LateFrame",
]

#: Interval between stored live-parameter rows and console updates [s of session time].
LIVE_INTERVAL_S = 1.0
#: Interval of the ticker that lets timeouts fire when no data arrives [s of session time].
TICK_S = 0.05
#: Longest a sample or frame waits for the other stream before it is fed anyway [s].
MERGE_HOLD_S = 0.5
#: Events the acquisition queue holds at most (frames' results, sample batches, ticks).
QUEUE_MAX_EVENTS = 2048
#: Gap reason of frames that arrived too late to be measured.
LATE_GAP_REASON = "processing_behind"
#: Gap reason of frames of another size than the session's first frame (the run ends).
RESIZED_GAP_REASON = "frame_size_changed"
#: Shortest wall time between two frames' S_k shown on the console [s] (it redraws at 4 Hz).
CONSOLE_FRAME_INTERVAL_WALL_S = 0.05
#: Live computations (snapshots taken every LIVE_INTERVAL_S) waiting on the worker thread
#: before the loop waits for the oldest: the loop never falls further behind than this.
LIVE_BACKLOG_MAX = 4
#: Python's thread switch interval while measuring [s] (default 5 ms): a thread that wants
#: the GIL back (the event loop after each select, read, commit) waits for the holder (the
#: live fit's thread) at most this long, so the fit cannot convoy the loop.
SWITCH_INTERVAL_S = 0.0005
#: Wall time :meth:`Acquisition.stop` waits for its tasks before it logs which of them do
#: not end, and where each waits (again every six times as long) [s].
STOP_WARN_WALL_S = 5.0

_log = logging.getLogger(__name__)

OnRunning = Callable[[DaemonHandles], Coroutine[Any, Any, None]]
"""An async callback run as a task while the daemon records (see :class:`DaemonHandles`)."""


class _Stop:
    """Sentinel: a pump ended (its source is exhausted or failed)."""

    def __init__(self, who: str, error: BaseException | None = None) -> None:
        self.who = who
        self.error = error


def _feed(pipeline: MeasurementPipeline, kind: str, value: tuple[float, float]) -> list[Output]:
    t_s, v = value
    return pipeline.force(t_s, v) if kind == "force" else pipeline.frame(t_s, v)


class Acquisition:
    """One measurement's acquisition loop on opened devices.

    Parameters
    ----------
    config : DaemonConfig
        The configuration.
    devices : Devices
        The opened probe, camera and session.
    pipeline : MeasurementPipeline
        The live measurement (not yet armed).
    console : OperatorConsole
        The operator console (entered by the caller).
    measurer : FrameMeasurer
        Measures frames on the camera side.

    Attributes
    ----------
    counts : dict
        Frames, force samples, gaps and dropped frames recorded so far.
    latencies_s : list of float
        Per frame: session time from capture to the row being committed [s].
    merger : TimeOrderedMerger
        Puts samples and frames in time order for the pipeline.
    stop_error : BaseException or None
        Why a source ended, if it failed.
    lag_s : list of float
        Per frame (measured or late): session time when handled minus capture time [s].
    fault_line : str or None
        Why the acquisition ended the run itself (it fell behind by more than
        ``run.max_lag_s``, or the camera's frames changed size), in one line; None
        otherwise.
    """

    def __init__(
        self,
        config: DaemonConfig,
        devices: Devices,
        pipeline: MeasurementPipeline,
        console: OperatorConsole,
        measurer: FrameMeasurer,
    ) -> None:
        self._config = config
        self._devices = devices
        self._clock = devices.clock
        self._writer = devices.writer
        self._pipeline = pipeline
        self._console = console
        self._measurer = measurer
        # S_k is counted and the video stored in the camera's capture thread, beside the
        # event loop (frames that come before this is set are measured on the loop).
        source = getattr(devices.camera, "camera", None)
        self._source = source if isinstance(source, ThreadedCamera) else None
        if isinstance(source, ThreadedCamera):
            source.frame_hook = measurer.on_capture
            measurer.wait_for_encoder = source.waits_for_consumer
        self._queue: asyncio.Queue[object] = asyncio.Queue(maxsize=QUEUE_MAX_EVENTS)
        self._tasks: list[asyncio.Task[None]] = []
        self._next_live_s = 0.0
        # The live fit runs on a worker thread, off the event loop (tens of ms at 60 fps
        # and a long recovery); its rows are stored in the order the snapshots were taken.
        self._live_pool: ThreadPoolExecutor | None = None
        self._live_pending: deque[tuple[float, asyncio.Future[LiveParameters | None]]] = deque()
        self.counts = {
            "frames": 0,
            "samples": 0,
            "gaps": 0,
            "dropped_frames": 0,
            "late_frames": 0,
        }
        self.latencies_s: list[float] = []
        self.lag_s: list[float] = []
        self._lag_now_s = 0.0
        self._next_console_wall_s = float("-inf")
        #: Whether frames are being processed: the console warns when they stop.
        self.frame_watch = FrameWatch()
        self.fault_line: str | None = None
        #: What the live view shows (None: no view); written here, read by its server.
        self.live: LiveState | None = None
        self._clock_offset_s: float | None = None
        # Samples and frames reach the pipeline in time order (as on replay), each held at
        # most MERGE_HOLD_S for the other stream.
        self.merger: TimeOrderedMerger[tuple[float, float]] = TimeOrderedMerger(
            ["force", "frame"], max_hold_s=MERGE_HOLD_S
        )
        self.stop_error: BaseException | None = None
        self._probe_health = ProbeHealth()
        self._handlers: dict[type[Any], Callable[[Any], list[Output]]] = {
            ForceRows: self._on_force,
            FrameResult: self._on_frame,
            LateFrame: self._on_late_frame,
            ResizedFrame: self._on_resized_frame,
            Gap: self._on_gap,
            ClockProbe: self._on_clock_probe,
            LinkDown: self._on_link_down,
            LinkUp: self._on_link_up,
            StatusReport: self._on_status,
            CamStalled: self._on_camera_stalled,
            CamRecovered: self._on_camera_recovered,
            Tick: self._on_tick,
            _Stop: self._on_stop,
        }

    # ------------------------------------------------------------------ the loop

    async def run(self, on_running: OnRunning | None = None) -> None:
        """Arm, stream, and take events to their handlers until the measurement finishes.

        Parameters
        ----------
        on_running : async callable, optional
            Run as a task with the :class:`~stipi_daemon.app.devices.DaemonHandles` once the
            stream has started; cancelled by :meth:`stop`.

        Raises
        ------
        SessionError
            Storing rows failed (the caller stops and keeps what is committed).
        """
        clock, writer, pipeline = self._clock, self._writer, self._pipeline
        self._console.line(f"session {writer.session_id} in {self._config.storage.root}")
        self._record(pipeline.arm(clock.now()))
        writer.add_event(clock.now(), "session_clock", session_clock_detail(clock))
        await self._devices.probe.start_stream()
        self._start_tasks(on_running)
        switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            await self._take_events()
        finally:
            sys.setswitchinterval(switch)

    async def _take_events(self) -> None:
        """Take events to their handlers until the measurement finishes."""
        clock, pipeline = self._clock, self._pipeline
        queue, handlers, merger = self._queue, self._handlers, self.merger
        while True:
            ev = await queue.get()
            handler = handlers.get(type(ev))
            outputs: list[Output] = handler(ev) if handler is not None else []
            # The merger's clock runs the camera's lag behind: nothing is fed ahead of frames
            # that are still on their way.
            for kind, value in merger.pop_ready(clock.now() - self._lag_now_s):
                if pipeline.finished:
                    break
                outputs += _feed(pipeline, kind, value)
            if outputs:
                self._record(outputs)
            if self.live is not None:
                self.live.tick(pipeline.state.now_s, pipeline.state.t_release_s)
            if pipeline.finished:
                self._measurer.stop_storing()  # frames after the end are not stored
                await self._drain_live(wait=True)
                return
            self._store_live()
            if self._live_pending:
                await self._drain_live(wait=len(self._live_pending) > LIVE_BACKLOG_MAX)

    def _start_tasks(self, on_running: OnRunning | None) -> None:
        devices = self._devices
        self._tasks = [
            asyncio.create_task(self._pump("probe", devices.probe.events()), name="probe"),
            asyncio.create_task(
                self._pump("camera", devices.camera.events(), self._measurer), name="camera"
            ),
            asyncio.create_task(self._ticker(), name="ticker"),
        ]
        if on_running is not None:
            handles = DaemonHandles(
                self._clock, devices.probe, devices.camera, self._writer, self._pipeline
            )
            self._tasks.append(asyncio.create_task(on_running(handles), name="on_running"))

    async def stop(self) -> None:
        """Cancel the pumps, the ticker and the ``on_running`` task, and wait for them; end
        the live fit's worker thread (live rows not yet stored are left out)."""
        if self._measurer is not None:  # None only in unit tests of the handlers
            self._measurer.stop_storing()
            self.counts["frames"] = max(self.counts["frames"], self._measurer.stored)
        tasks, self._tasks = self._tasks, []
        pool, self._live_pool = self._live_pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
        self._live_pending.clear()
        pending = set(tasks)
        t_warn = time.monotonic() + STOP_WARN_WALL_S
        while pending:
            if time.monotonic() > t_warn:  # a task that does not end: say which, and where
                t_warn = time.monotonic() + 6 * STOP_WARN_WALL_S
                _log.warning("still waiting for task(s) to end: %s", _task_stacks(pending))
            for t in pending:
                t.cancel()
            while not self._queue.empty():
                self._queue.get_nowait()
            _, pending = await asyncio.wait(pending, timeout=0.05)
        for t in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await t

    async def _pump(
        self,
        who: str,
        events: AsyncIterator[object],
        convert: Callable[[object], object] | None = None,
    ) -> None:
        """Queue a source's events (converted), then a :class:`_Stop` when it ends or fails."""
        try:
            async for ev in events:
                await self._queue.put(ev if convert is None else convert(ev))
        except asyncio.CancelledError:
            raise
        except BaseException as exc:
            await self._queue.put(_Stop(who, exc))
            return
        await self._queue.put(_Stop(who))

    async def _ticker(self) -> None:
        clock = self._clock
        t_s = clock.now()
        while True:
            t_s = max(t_s + TICK_S, clock.now())
            await clock.sleep_until(t_s)
            await self._queue.put(Tick(clock.now()))

    def _record(self, outputs: list[Output]) -> None:
        """Show the pipeline's outputs and store transitions, advisories, faults, prompts."""
        now = self._pipeline.state.now_s
        self._console.outputs(outputs, now)
        if self.live is not None:
            _publish(self.live, outputs)
        writer = self._writer
        for o in outputs:
            if isinstance(o, PhaseChanged):
                writer.add_transition(o.t_s, str(o.old), str(o.new), o.reason)
            elif isinstance(o, Advisory):
                writer.add_event(o.t_s, f"advisory:{o.kind}", {"detail": o.detail})
            elif isinstance(o, Fault):
                writer.add_event(o.t_s, f"fault:{o.kind}", {"reason": o.reason})
            elif isinstance(o, OperatorPrompt):
                writer.add_event(now, "prompt", {"text": o.text})

    def _store_live(self) -> None:
        """Every LIVE_INTERVAL_S after the release: snapshot the series and compute the
        live parameters on the worker thread (stored by :meth:`_drain_live`)."""
        now = self._pipeline.state.now_s
        if now >= self._next_live_s and self._pipeline.state.t_release_s is not None:
            self._next_live_s = now + LIVE_INTERVAL_S
            inputs = self._pipeline.live_inputs()
            if inputs is None:
                return
            if self._live_pool is None:
                self._live_pool = ThreadPoolExecutor(1, thread_name_prefix="stipi-live")
            future = asyncio.get_running_loop().run_in_executor(
                self._live_pool, compute_live, inputs
            )
            self._live_pending.append((now, future))

    async def _drain_live(self, *, wait: bool) -> None:
        """Store and show the finished live parameters, oldest first; with ``wait``, wait
        for the oldest (the backlog is full) or for all of them (the measurement ended)."""
        pending = self._live_pending
        while pending:
            now, future = pending[0]
            if not future.done():
                if not wait:
                    return
                with self._clock.hold():  # a simulated world waits for the live fit
                    await asyncio.wait([future])
            pending.popleft()
            live_params = future.result()
            if live_params is not None:
                self._writer.add_live_parameters(now, live_params.to_dict())
                self._console.update(now, params=live_params)
                if self.live is not None:
                    self.live.live_parameters(live_params, live_statuses(live_params))
            if wait and not self._pipeline.finished:
                return

    # -------------------------------------------------------------- the handlers

    def _on_force(self, ev: ForceRows) -> list[Output]:
        rows = ev.rows
        self._writer.add_force_samples(
            [
                (r.sample_index, r.adc_counts, r.t_mcu_raw_us, r.t_mcu_us, r.t_host_s, r.force_n)
                for r in rows
            ]
        )
        self.counts["samples"] += len(rows)
        for r in rows:
            if r.force_n is not None:
                self.merger.push("force", r.t_host_s, (r.t_host_s, r.force_n), self._clock.now())
        if rows and rows[-1].force_n is not None:
            self._console.update(self._pipeline.state.now_s, force_n=rows[-1].force_n)
            if self.live is not None:
                self.live.force_n(rows[-1].t_host_s, rows[-1].force_n)
        return []

    def _lag(self, t_capture_s: float) -> list[Output]:
        """Measure the lag behind the camera; past ``run.max_lag_s``, end the run (fault)."""
        now = self._clock.now()
        lag = max(0.0, now - t_capture_s)
        self._lag_now_s = lag
        self.lag_s.append(lag)
        bound = self._config.run.max_lag_s
        if lag <= bound or self.fault_line is not None:
            return []
        if self._clock.waits_for_daemon:  # no lag of its own: a scene's processing_stall
            why = "a processing stall of the scene (this clock waits for the daemon otherwise)"
        else:
            why = f"this machine does not sustain run.speed {self._clock.speed:g}: lower it"
        line = (
            f"falling behind: a frame was handled {lag:.1f} s after its capture (more than "
            f"run.max_lag_s {bound:g} s); {why}"
        )
        return self._end_with_fault(now, line, "falling_behind", {"lag_s": lag, "max_lag_s": bound})

    def _end_with_fault(
        self, now: float, line: str, kind: str, detail: dict[str, Any]
    ) -> list[Output]:
        """End the run at session time ``now`` [s] because of ``line`` (the fault's one line,
        :attr:`fault_line`; event ``fault:<kind>`` with ``detail``): what the merger holds
        is fed, then the measurement is closed."""
        self.fault_line = line
        self._writer.add_event(now, f"fault:{kind}", detail)
        self._console.line(f"FAULT {line}")
        outputs: list[Output] = []
        for kind_, value in self.merger.drain():
            outputs += _feed(self._pipeline, kind_, value)
        return outputs + self._pipeline.close(now)

    def _on_resized_frame(self, ev: ResizedFrame) -> list[Output]:
        """A frame of another size than the session's: a gap, and the run ends (fault)."""
        self._camera_gaps(ev.seq, ev.t_capture_s, ev.dropped_before)
        self._writer.add_gap("frames", ev.seq, 1, ev.t_capture_s, RESIZED_GAP_REASON)
        if self.fault_line is not None:
            return []
        now = self._clock.now()
        line = ev.fault_line()
        detail = {
            "seq": ev.seq,
            "shape": list(ev.shape),
            "session_shape": list(ev.session_shape),
            "reported": ev.reported,
        }
        return self._end_with_fault(now, line, "frame_size_changed", detail)

    def _watch_frame(self, t_capture_s: float, *, measured: bool) -> None:
        """Tell the frame watch a frame was handled; show what it says (frames come again
        after a stretch without, or frames came too late to be measured)."""
        now = self._clock.now()
        line = self.frame_watch.frame(
            now, t_capture_s, measured=measured, phase=self._pipeline.phase
        )
        self._console.warn(None)
        if line is not None:
            self._console.line(f"[{now:7.2f} s] note: {line}")
            self._writer.add_event(now, "frames_processed_again", {"detail": line})

    def _watch_silence(self, now: float) -> None:
        """Warn (console, event) when no frame has been handled for a while."""
        line = self.frame_watch.tick(now, self._pipeline.phase)
        if line is None:
            return
        self._console.warn(self.frame_watch.warning)
        self._console.line(f"[{now:7.2f} s] WARNING {line}", style="bold red")
        self._writer.add_event(
            now,
            "frames_not_processed",
            {"detail": line, "last_capture_s": self.frame_watch.last_capture_s},
        )

    def _on_late_frame(self, ev: LateFrame) -> list[Output]:
        self.counts["late_frames"] += 1
        self._watch_frame(ev.t_capture_s, measured=False)
        self._camera_gaps(ev.seq, ev.t_capture_s, ev.dropped_before)
        self._writer.add_gap("frames", ev.seq, 1, ev.t_capture_s, LATE_GAP_REASON)
        return self._lag(ev.t_capture_s)

    def _camera_gaps(self, seq: int, t_capture_s: float, dropped_before: int) -> None:
        if dropped_before:
            self.counts["dropped_frames"] += dropped_before
            self._writer.add_gap(
                "frames", seq - dropped_before, dropped_before, t_capture_s, "camera"
            )

    def _on_frame(self, ev: FrameResult) -> list[Output]:
        if ev.error is not None:  # its row or video frame could not be stored
            raise ev.error
        # The frame's row is stored and committed already (FrameMeasurer, capture thread).
        now = self._clock.now()
        self.latencies_s.append(now - ev.t_capture_s)
        if ev.stored:  # (stop() counts the rows stored after the last one seen)
            self.counts["frames"] += 1
        if ev.dropped_before:
            self._camera_gaps(ev.seq, ev.t_capture_s, ev.dropped_before)
        self._watch_frame(ev.t_capture_s, measured=True)
        self.merger.push("frame", ev.t_capture_s, (ev.t_capture_s, float(ev.s_k)), now)
        wall_s = time.monotonic()
        if wall_s >= self._next_console_wall_s:  # the console shows a few frames a second
            self._next_console_wall_s = wall_s + CONSOLE_FRAME_INTERVAL_WALL_S
            fps = self._devices.camera.stats.fps()
            self._console.update(self._pipeline.state.now_s, s_k=ev.s_k, fps=fps)
            if self.live is not None:
                self._publish_health(fps)
        return self._lag(ev.t_capture_s)

    def _on_gap(self, ev: Gap) -> list[Output]:
        self.counts["gaps"] += 1
        self._writer.add_gap("force", ev.start_index, ev.count, ev.t_host_s, ev.cause)
        return []

    def _on_clock_probe(self, ev: ClockProbe) -> list[Output]:
        self._writer.add_clock_probe(ev.mcu_raw_us, ev.mcu_unwrapped_us, ev.host_s)
        self._clock_offset_s = ev.host_s - ev.mcu_unwrapped_us * 1e-6
        return []

    def _publish_health(self, fps: float) -> None:
        """The link's and the camera's health, for the live view."""
        assert self.live is not None
        counts = self.counts
        self.live.set_health(
            camera_fps=fps,
            frames=counts["frames"],
            dropped_frames=counts["dropped_frames"],
            late_frames=counts["late_frames"],
            gaps=counts["gaps"],
            lag_s=self._lag_now_s,
            clock_offset_s=self._clock_offset_s,
            probe_battery="not reported by the probe",
        )

    def _on_link_down(self, ev: LinkDown) -> list[Output]:
        self._writer.add_event(ev.t_s, "link_down", {"reason": ev.reason})
        return self._pipeline.feed(LinkLost(ev.t_s))

    def _on_status(self, ev: StatusReport) -> list[Output]:
        detail = self._probe_health.observe(ev)
        if detail is not None:  # why the probe started, its BLE module: when it changes
            self._writer.add_event(ev.t_host_s, "probe_health", detail)
        return []

    def _on_link_up(self, ev: LinkUp) -> list[Output]:
        self._probe_health.forget()  # a restarted probe says again why it started
        self._writer.add_event(ev.t_s, "link_up", {})
        return self._pipeline.feed(LinkRestored(ev.t_s))

    def _on_camera_stalled(self, ev: CamStalled) -> list[Output]:
        self._writer.add_event(ev.t_s, "camera_stalled", {"detail": str(ev)})
        return self._pipeline.feed(CameraStalled(ev.t_s))

    def _on_camera_recovered(self, ev: CamRecovered) -> list[Output]:
        self._writer.add_event(ev.t_s, "camera_recovered", {"detail": str(ev)})
        return self._pipeline.feed(CameraRecovered(ev.t_s))

    def _first_frame_lag(self) -> list[Output]:
        """Before the loop has seen a frame, the lag is that of the camera's first frame,
        due since its capture time (a source that waits for its consumer: the simulator, a
        file; rendered, decoded, measured and stored, it may not have come yet), so that the
        merger and the ticks run behind it as behind any late frame, and past
        ``run.max_lag_s`` the run ends (a fault) rather than measuring without frames."""
        if self._source is None or self.lag_s or self.fault_line is not None:
            return []
        due = self._source.first_frame_due_s()
        overdue = 0.0 if due is None else max(0.0, self._clock.now() - due)
        self._lag_now_s = max(self._lag_now_s, overdue)
        bound = self._config.run.max_lag_s
        if overdue <= bound:
            return []
        now = self._clock.now()
        line = (
            f"falling behind: the camera's first frame, due at {now - overdue:.1f} s, had not "
            f"come {overdue:.1f} s later (more than run.max_lag_s {bound:g} s); this machine "
            f"does not sustain run.speed {self._clock.speed:g}: lower it"
        )
        detail = {"lag_s": overdue, "max_lag_s": bound, "first_frame": True}
        return self._end_with_fault(now, line, "falling_behind", detail)

    def _on_tick(self, ev: Tick) -> list[Output]:
        outputs = self._first_frame_lag()
        if self.fault_line is not None:  # the run has ended
            return outputs
        self._watch_silence(ev.t_s)
        # Ticks only let timeouts fire when data stops: they lag the data by the merge hold
        # and never pass a held sample, so while data flows they change nothing (and an
        # offline replay, which has no ticks, agrees).
        # They run the camera's lag behind too, so no timeout ends the session while frames
        # of its window are still on their way.
        t_tick = ev.t_s - MERGE_HOLD_S - self._lag_now_s
        pending = self.merger.oldest_pending_s()
        if pending is not None:
            t_tick = min(t_tick, pending)
        if t_tick > self._pipeline.state.now_s:
            return self._pipeline.feed(Tick(t_tick))
        return []

    def _on_stop(self, ev: _Stop) -> list[Output]:
        # A source ended (e.g. a video file) or failed: close the session.
        self.stop_error = ev.error
        now = self._clock.now()
        self._writer.add_event(
            now, f"{ev.who}_ended", {"error": None if ev.error is None else str(ev.error)}
        )
        outputs: list[Output] = []
        for kind, value in self.merger.drain():
            outputs += _feed(self._pipeline, kind, value)
        return outputs + self._pipeline.close(self._clock.now())


def _publish(live: LiveState, outputs: list[Output]) -> None:
    """The state machine's outputs into the live view: phases, the prompt, notes."""
    for o in outputs:
        if isinstance(o, PhaseChanged):
            live.phase_changed(o.t_s, str(o.old), str(o.new), o.reason)
        elif isinstance(o, OperatorPrompt):
            live.set_prompt(o.text)
        elif isinstance(o, Advisory):
            live.note(f"[{o.t_s:.2f} s] note: {o.kind}: {o.detail}")
        elif isinstance(o, Fault):
            live.note(f"[{o.t_s:.2f} s] FAULT {o.kind}: {o.reason}")


def session_clock_detail(clock: SessionClock) -> dict[str, Any]:
    """What the ``session_clock`` event records: on wall time, how session times map onto
    the host's monotonic clock (``time.monotonic()``); on a simulated run's clock, that it
    waited for the daemon (its times are not wall times, and the same on every run)."""
    if clock.waits_for_daemon:
        return {"kind": "simulated", "waits_for_daemon": True}
    return {
        "kind": "wall",
        "speed": clock.speed,
        "monotonic_origin_s": time.monotonic() - clock.now() / clock.speed,
    }


def _task_stacks(tasks: set[asyncio.Task[None]]) -> str:
    """Each task's name and the stack it waits in, for a log line."""
    buf = io.StringIO()
    for t in sorted(tasks, key=lambda t: t.get_name()):
        buf.write(f"\n{t.get_name()}: ")
        t.print_stack(file=buf)
    return buf.getvalue()
