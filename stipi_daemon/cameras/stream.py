"""Stall detection and recovery around any camera: the stream the daemon consumes.

This module owns :class:`CameraStream`: it opens a :class:`~.base.Camera`, yields its frames
as :data:`~.base.CameraEvent` values, and when no frame arrives within the stall timeout
(or the source fails) it yields :class:`~.base.CameraStalled`, closes and reopens the camera
with bounded retries and exponential backoff, and yields :class:`~.base.CameraRecovered`
before the first frame after the outage. When every retry fails it raises
:class:`~stipi_daemon.errors.CameraError` (one line naming the camera). It does not read
devices itself.

Time base. All timeouts are in session time (:meth:`~stipi_daemon.clock.SessionClock.timeout`):
on a wall clock ``timeout / clock.speed`` of wall time, on a simulated run's clock (which
waits for the daemon) the session time itself. Real cameras run at speed 1, so their stall
timeout is wall time, as it must be for a driver; simulated cameras pace themselves on the
session clock, so at speed 4 their
timeout shrinks with their frame period and a stall is detected after the same number of
missed frames as in real time. The stall timeout is never shorter than three nominal frame
periods (a 2 fps camera is not "stalled" after 0.5 s), nor than
:data:`STALL_MIN_WALL_S` of wall time: a host's scheduling hiccup does not shrink with the
clock's speed, so a simulation accelerated past 4x is not "stalled" by one.

Behind is not stalled. A stall is the source's own silence: for a camera with a capture
thread (:meth:`~.threaded.ThreadedCamera.source_silent_s`) the time its thread spends
handing frames over to the consumer (the frame hook: S_k, the session video, the row) does
not count, nor, for a source that waits for its consumer (a paced video file, the
simulator), the time it spends producing its next frame (reading, decoding, rendering; up
to :data:`~.threaded.SOURCE_HANG_WALL_S` of wall time), unless an injected stall froze it.
So such a source on a machine that cannot keep up with ``run.speed`` delivers its frames
late, and the daemon reports that lag (``run.max_lag_s``), not a stall that would end the
measurement's phases at once with the frames still to come.
"""

from __future__ import annotations

import logging
import math
from collections.abc import AsyncIterator
from types import TracebackType

from stipi_daemon.cameras.base import (
    Camera,
    CameraEvent,
    CameraFrame,
    CameraRecovered,
    CameraStalled,
    CameraStats,
)
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import CameraError

__all__ = ["STALL_MIN_WALL_S", "CameraStream"]

#: Session time [s] below which a remaining wait is rounding, not time.
_TIME_ROUNDING_S = 1e-9
#: Shortest stall timeout in wall time [s] (at speed 1-4 the default 0.5 s of session time
#: is longer; at speed 10 it becomes 1.25 s of session time).
STALL_MIN_WALL_S = 0.125

_log = logging.getLogger(__name__)


class CameraStream:
    """A camera's frames with stall detection and automatic reopen.

    Parameters
    ----------
    camera : Camera
        Any camera source.
    clock : SessionClock
        The session clock (the one the camera stamps frames with).
    stall_timeout_s : float
        Longest silence between frames before a stall is declared [s of session time],
        raised to three nominal frame periods when that is longer.
    open_timeout_s : float
        Longest wait for the first frame after an open or reopen [s of session time]
        (cameras take a while to start streaming).
    max_reopens : int
        Reopen attempts per stall before giving up with :class:`CameraError`.
    backoff_s : float
        Pause before the first reopen attempt [s]; doubled after each failed attempt,
        capped at ``max_backoff_s``.
    max_backoff_s : float
        Longest pause between attempts [s].
    """

    def __init__(
        self,
        camera: Camera,
        clock: SessionClock,
        *,
        stall_timeout_s: float = 0.5,
        open_timeout_s: float = 2.0,
        max_reopens: int = 5,
        backoff_s: float = 0.1,
        max_backoff_s: float = 2.0,
    ) -> None:
        for label, value in (
            ("stall_timeout_s", stall_timeout_s),
            ("open_timeout_s", open_timeout_s),
        ):
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{label} must be a finite number > 0, got {value}")
        if max_reopens < 1:
            raise ValueError(f"max_reopens must be >= 1, got {max_reopens}")
        if not (0.0 <= backoff_s <= max_backoff_s):
            raise ValueError(
                f"need 0 <= backoff_s <= max_backoff_s, got {backoff_s}, {max_backoff_s}"
            )
        self.camera = camera
        self.clock = clock
        self.stall_timeout_s = stall_timeout_s
        self.open_timeout_s = open_timeout_s
        self.max_reopens = max_reopens
        self.backoff_s = backoff_s
        self.max_backoff_s = max_backoff_s
        self._opened = False

    @property
    def stats(self) -> CameraStats:
        return self.camera.stats

    def effective_stall_timeout_s(self) -> float:
        """The stall timeout in use [s of session time]: the configured one, three frame
        periods or :data:`STALL_MIN_WALL_S` of wall time, whichever is longest."""
        fps = self.camera.nominal_fps
        periods = 3.0 / fps if fps > 0.0 and math.isfinite(fps) else 0.0
        return max(self.stall_timeout_s, periods, STALL_MIN_WALL_S * self.clock.speed)

    async def open(self) -> None:
        """Open the camera (raises :class:`CameraError` naming it if it cannot be used)."""
        await self.camera.open()
        self._opened = True

    async def close(self) -> None:
        """Close the camera; idempotent."""
        self._opened = False
        await self.camera.close()

    async def __aenter__(self) -> CameraStream:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def _next(
        self, frames: AsyncIterator[CameraFrame], timeout_s: float
    ) -> CameraFrame | None:
        """The next frame, None at the source's end; TimeoutError after ``timeout_s``."""
        try:
            # a timer on this task, no task of its own per frame (wait_for)
            async with self.clock.timeout(timeout_s):
                return await anext(frames)
        except StopAsyncIteration:
            return None

    async def events(self) -> AsyncIterator[CameraEvent]:
        """Frames, stalls and recoveries, until the source ends.

        Raises
        ------
        CameraError
            The camera cannot be opened, or stays silent after ``max_reopens`` attempts.
        """
        if not self._opened:
            await self.open()
        clock = self.clock
        frames = self.camera.frames()
        last_frame_t = clock.now()
        last_seq = -1
        limit_s = wait_s = self.open_timeout_s  # the silence allowed; the wait for it
        while True:
            reason = "timeout"
            try:
                frame = await self._next(frames, wait_s)
            except TimeoutError:
                more_s = self._not_silent_for(limit_s)
                if more_s is not None:  # producing or handing over frames: behind
                    frames, wait_s = self.camera.frames(), more_s  # (that one is closed)
                    continue
                frame = None
                reason = "timeout"
            except CameraError as exc:
                frame = None
                reason = str(exc)
            else:
                if frame is None:
                    return
                last_frame_t = clock.now()
                last_seq = frame.seq
                limit_s = wait_s = self.effective_stall_timeout_s()
                yield frame
                continue
            now = clock.now()
            self.camera.stats.stalls += 1
            _log.warning(
                "%s: stalled (%s) %.3f s after its last frame",
                self.camera.name,
                reason,
                now - last_frame_t,
            )
            yield CameraStalled(
                t_s=now, last_seq=last_seq, silent_s=now - last_frame_t, reason=reason
            )
            frames, first, attempts = await self._reopen()
            if first is None:
                return
            self.camera.stats.reopens += 1
            now = clock.now()
            yield CameraRecovered(t_s=now, attempts=attempts, outage_s=now - last_frame_t)
            last_frame_t = now
            last_seq = first.seq
            limit_s = wait_s = self.effective_stall_timeout_s()
            yield first

    def _not_silent_for(self, limit_s: float) -> float | None:
        """After a wait for a frame timed out: the session time [s] still to wait when the
        source has been silent for less than ``limit_s`` [s] (its capture thread was busy
        handing over or producing frames meanwhile), else None (a stall; also for a camera
        that cannot tell)."""
        silent = getattr(self.camera, "source_silent_s", None)
        if silent is None:
            return None
        silent_s = float(silent())
        # less than the rounding of session times left: silent for the limit (on a clock
        # that waits for the daemon, a wait for 1e-17 s would end at the same instant)
        return limit_s - silent_s if silent_s < limit_s - _TIME_ROUNDING_S else None

    async def _reopen(self) -> tuple[AsyncIterator[CameraFrame], CameraFrame | None, int]:
        """Close and reopen until a first frame arrives; (frames, first frame, attempts).

        ``first`` is None when the source ended right after reopening.
        """
        clock = self.clock
        pause_s = self.backoff_s
        last_problem = "no frame"
        for attempt in range(1, self.max_reopens + 1):
            await self.camera.close()
            if pause_s > 0.0:
                await clock.sleep_until(clock.now() + pause_s)
            pause_s = min(self.max_backoff_s, max(pause_s * 2.0, 0.05))
            try:
                await self.camera.open()
            except CameraError as exc:
                last_problem = str(exc)
                continue
            frames = self.camera.frames()
            try:
                first = await self._next(frames, self.open_timeout_s)
            except TimeoutError:
                last_problem = f"no frame within {self.open_timeout_s:g} s of reopening"
                continue
            except CameraError as exc:
                last_problem = str(exc)
                continue
            return frames, first, attempt
        await self.camera.close()
        self._opened = False
        raise CameraError(
            f"{self.camera.name}: no frames after {self.max_reopens} reopen attempts "
            f"(last: {last_problem})"
        )
