"""The capture-thread machinery shared by every camera source.

OpenCV's ``VideoCapture.read`` and the simulator's renderer block, so each open camera runs
one dedicated capture thread that reads frames and hands them to asyncio through a bounded
:class:`FrameHandoff`. This module owns that hand-off (drop-oldest for live sources, with
counting; back-pressure for sources that must not lose frames), the thread's life cycle
(open in an executor, stop and join with a bounded wait on close), pacing on the session
clock, the fault injection :meth:`ThreadedCamera.stall`, and the conversion of source frame
numbers into ``dropped_before`` and :class:`~.base.CameraStats`. It does not know any
particular source: subclasses implement ``_open_source``, ``_read`` and ``_close_source``.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from stipi_daemon.cameras.base import CameraFrame, CameraStats
from stipi_daemon.clock import SessionClock
from stipi_daemon.errors import CameraError

__all__ = ["FrameHandoff", "RawFrame", "ThreadedCamera"]

_log = logging.getLogger(__name__)

T = TypeVar("T")
H = TypeVar("H")

#: Longest wall time :meth:`ThreadedCamera.close` waits for the capture thread [s].
JOIN_TIMEOUT_S = 2.0
#: Longest wall time [s] a source that waits for its consumer (a file, the simulator) may
#: take to produce one frame (read, decode, render) before that counts as silence: it is
#: working behind its frames' capture times on a busy machine, not frozen, until then.
SOURCE_HANG_WALL_S = 2.0


@dataclass(frozen=True, slots=True)
class RawFrame:
    """A frame as the capture thread produces it (before drop accounting); ``packet`` is
    the encoded frame ``image`` was decoded from, when the source has one."""

    seq: int
    t_capture_s: float
    image: npt.NDArray[np.uint8]
    packet: bytes | None = None
    measured: object = None


@dataclass(frozen=True, slots=True)
class _End:
    """End of the stream: the source ended (``error`` None) or failed."""

    error: CameraError | None


class FrameHandoff(Generic[T]):
    """Bounded queue from one producer thread to one asyncio consumer.

    Parameters
    ----------
    loop : asyncio.AbstractEventLoop
        The consumer's event loop.
    capacity : int
        Items held at most, >= 1.
    drop_oldest : bool
        When full, ``put`` discards the oldest item and counts it in :attr:`dropped`
        (a live camera: the newest frame matters); otherwise ``put`` blocks until the
        consumer takes one (a file or simulator: no frame may be lost).
    """

    def __init__(self, loop: asyncio.AbstractEventLoop, capacity: int, drop_oldest: bool) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._loop = loop
        self._capacity = capacity
        self._drop_oldest = drop_oldest
        self._items: deque[T] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._waiter: asyncio.Future[None] | None = None
        #: Items discarded by the drop-oldest policy [-].
        self.dropped = 0

    @property
    def closed(self) -> bool:
        return self._closed

    def full(self) -> bool:
        """Whether the hand-off holds ``capacity`` items (producer side)."""
        return len(self._items) >= self._capacity

    def count_dropped(self) -> None:
        """Count an item the producer left out itself (the hand-off was full)."""
        with self._cond:
            self.dropped += 1

    def put(self, item: T, *, force: bool = False) -> bool:
        """Producer side (any thread): add ``item``; False once the hand-off is closed.

        ``force`` appends even when full (used for the end-of-stream marker under the
        drop-oldest policy, so that it is never the item discarded).
        """
        with self._cond:
            if self._drop_oldest or force:
                while len(self._items) >= self._capacity and not force:
                    self._items.popleft()
                    self.dropped += 1
            else:
                while len(self._items) >= self._capacity and not self._closed:
                    self._cond.wait()
            if self._closed:
                return False
            self._items.append(item)
            waiter = self._waiter
            self._waiter = None
        if waiter is not None:
            self._loop.call_soon_threadsafe(_wake, waiter)
        return True

    def close(self) -> None:
        """Stop both sides: a blocked ``put`` returns False, ``get`` returns what is left."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            waiter = self._waiter
            self._waiter = None
        if waiter is not None:
            self._loop.call_soon_threadsafe(_wake, waiter)

    async def get(self) -> T | None:
        """Consumer side: the next item; None once closed and empty."""
        while True:
            with self._cond:
                if self._items:
                    item = self._items.popleft()
                    if len(self._items) <= self._capacity // 2:
                        # a blocked producer refills from half full: one wake-up per few
                        # items rather than per item
                        self._cond.notify()
                    return item
                if self._closed:
                    return None
                waiter: asyncio.Future[None] = self._loop.create_future()
                self._waiter = waiter
            await waiter


@dataclass(slots=True)
class _Progress:
    """A capture thread's progress (:meth:`ThreadedCamera.source_silent_s`): the session time
    [s] it last had a frame for its consumer or finished handing one over; whether it is
    handing one over now (in the frame hook or the hand-off); the session time [s] its
    current ``_read`` began (None: not reading); whether an injected stall swallowed a frame
    since the last hand-over."""

    last_s: float
    handing_over: bool = False
    read_since_s: float | None = None
    frozen: bool = False


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class ThreadedCamera(ABC, Generic[H]):
    """A camera whose frames come from a blocking reader run in a capture thread.

    Subclasses implement three blocking hooks, each given the handle returned by
    ``_open_source`` (so a thread still stuck in an old handle never touches a new one):

    * ``_open_source() -> H``: open the device or file (run in an executor); raise
      :class:`CameraError` with one line naming it.
    * ``_read(handle) -> RawFrame | None``: the next frame (capture thread); None at the
      end of a finite source; raise ``CameraError`` on failure.
    * ``_close_source(handle)``: release it (capture thread, when it exits).

    Parameters
    ----------
    clock : SessionClock
        The session clock: pacing, delivery times and stall injection use it.
    capacity : int
        Hand-off capacity [frames].
    drop_oldest : bool
        Hand-off policy (see :class:`FrameHandoff`).
    paced : bool
        Deliver each frame no earlier than its ``t_capture_s`` on the session clock: the
        capture thread waits for that time before the frame goes on (a file's JPEG is
        decoded then, as a camera delivers it; the hand-off only absorbs the consumer's
        jitter).
    """

    def __init__(
        self, clock: SessionClock, *, capacity: int, drop_oldest: bool, paced: bool
    ) -> None:
        self._clock = clock
        self._capacity = capacity
        self._drop_oldest = drop_oldest
        self._paced = paced
        self._stats = CameraStats()
        self._notes: list[str] = []
        self._thread: threading.Thread | None = None
        self._stop: threading.Event | None = None
        self._handoff: FrameHandoff[RawFrame | _End] | None = None
        self._queue_dropped_closed = 0
        self._last_seq: int | None = None
        self._stall_from_s = self._stall_until_s = float("-inf")
        self._thread_state = threading.local()  # the capture thread's own stop event
        self._progress = _Progress(float("-inf"))  # that of the current capture thread
        self._first_read_s: float | None = None  # capture time of the first frame made [s]
        self._waited_for_s = float("-inf")  # the latest capture time waited for [s]

    # -- hooks ------------------------------------------------------------------------------

    @property
    @abstractmethod
    def name(self) -> str: ...

    @property
    @abstractmethod
    def nominal_fps(self) -> float: ...

    @abstractmethod
    def _open_source(self) -> H: ...

    @abstractmethod
    def _read(self, handle: H) -> RawFrame | None: ...

    @abstractmethod
    def _close_source(self, handle: H) -> None: ...

    #: Called in the capture thread with each frame as it is delivered (a paced source's at
    #: or after its capture time, never a frame an injected stall swallows); what it returns
    #: travels with the frame (:attr:`~.base.CameraFrame.measured`). The daemon measures S_k
    #: and records the session video there, beside the event loop rather than on it, and a
    #: source that waits for its consumer (a file, the simulator) then also waits for the
    #: video's encoder. A hooked live source whose hand-off is full leaves out the newest
    #: frame before the hook, so that every frame the hook saw reaches the consumer. None:
    #: nothing is computed.
    frame_hook: Callable[[RawFrame], object] | None = None

    @property
    def waits_for_consumer(self) -> bool:
        """True for a source that waits when its consumer lags (a file, the simulator),
        False for a live camera, which leaves frames out instead."""
        return not self._drop_oldest

    def _first_seq(self) -> int:
        """``seq`` the very first frame would have (gaps before it count as dropped)."""
        return 0

    def _first_capture_s(self) -> float | None:
        """Capture time of the very first frame [s of session time], where the source knows
        it before it is made (a file, the simulator: their frames' times are set at the
        open); None: not known (a live camera)."""
        return None

    def first_frame_due_s(self) -> float | None:
        """Capture time [s of session time] of the first frame of a source that waits for
        its consumer: until the consumer has that frame, the source is behind by at least
        the time since (its lag, otherwise known only once a frame arrives).

        The capture time of the first frame the capture thread has made; before it has
        made one, the earliest it can still make: not before the source's first capture
        time (known at the open: the simulator's, a file's), the capture time it last waited
        for (a paced file waits through the damaged frames it skips) or the end of an
        injected stall (:meth:`stall`; the frames before it are lost, not late). None for a
        live camera, whose frames are not captured before they come (its silence is a
        stall, :meth:`source_silent_s`), and where the first capture time is not known."""
        if self._drop_oldest:
            return None
        if self._first_read_s is not None:
            return self._first_read_s
        due = self._first_capture_s()
        # frames it waited for (a paced source skipping damaged frames) were not late
        return None if due is None else max(due, self._waited_for_s, self._stall_until_s)

    def _metadata(self) -> dict[str, Any]:
        """Source-specific settings for :meth:`metadata`."""
        return {}

    # -- public API -------------------------------------------------------------------------

    def _wait_until(self, t_s: float) -> bool:
        """Capture thread: block until session time ``t_s`` (a source that paces itself
        before decoding, as a camera delivers a frame when it is captured); False when the
        camera is being closed meanwhile."""
        stop: threading.Event | None = getattr(self._thread_state, "stop", None)
        self._waited_for_s = max(self._waited_for_s, t_s)
        return self._clock.wait_until_blocking(t_s, stop)

    def _consumer_busy_until_s(self, t_capture_s: float) -> float | None:
        """Session time [s] until which the consumer does not take the frame captured at
        ``t_capture_s`` (a simulated processing stall), or None: it takes it now."""
        return None

    def source_silent_s(self) -> float:
        """How long the source itself has been silent [s of session time]: the time since
        the capture thread last had a frame for its consumer or finished handing one over
        (since the open, before the first frame), but 0 while it hands a frame over (the
        consumer's :attr:`frame_hook`: S_k, video and row; or a full hand-off), and for a
        source that waits for its consumer also while it produces the next frame (reads,
        decodes, renders), for up to :data:`SOURCE_HANG_WALL_S` of wall time, unless an
        injected stall (:meth:`stall`) has swallowed a frame since the last hand-over.

        :class:`~.stream.CameraStream` declares a stall on this, not on the time between
        frames alone: a file or simulated camera running behind its frames' capture times
        because the machine is slower than ``run.speed`` asks (a slow decode, a slow
        consumer) delivers late, and its lag is measured on every frame; it has not
        stopped delivering.
        """
        progress, now = self._progress, self._clock.now()
        if progress.handing_over:
            return 0.0
        reading = progress.read_since_s
        if (
            reading is not None
            and not progress.frozen
            and not self._drop_oldest
            and (now - reading) / self._clock.speed < SOURCE_HANG_WALL_S
        ):
            return 0.0
        return max(0.0, now - progress.last_s)

    @property
    def stats(self) -> CameraStats:
        return self._stats

    @property
    def is_open(self) -> bool:
        return self._thread is not None

    @property
    def notes(self) -> list[str]:
        """Things the user should know about this run (truncation, settings refused)."""
        return list(self._notes)

    def metadata(self) -> dict[str, Any]:
        return {"name": self.name, **self._metadata(), "notes": list(self._notes)}

    def _note(self, text: str) -> None:
        if text not in self._notes:
            self._notes.append(text)
            _log.warning("%s", text)

    def stall(self, duration_s: float) -> None:
        """Fault injection: deliver nothing for ``duration_s`` of session time [s].

        Frames captured meanwhile, or due meanwhile, are lost (they show up as
        ``dropped_before`` on the first frame after the stall), exactly as when a real camera
        freezes (a frame handed over before the freeze still arrives); reopening does not
        end the stall early. Meant for reliability tests of
        the stream's stall handling.
        """
        if not duration_s >= 0.0:
            raise ValueError(f"stall duration must be >= 0 s, got {duration_s}")
        now = self._clock.now()
        self._stall_from_s, self._stall_until_s = now, now + duration_s

    def _stalled(self, t_capture_s: float) -> bool:
        """Whether an injected stall swallows a frame captured at ``t_capture_s`` and due
        now (it is delivered while frozen, or was captured while frozen)."""
        return self._clock.now() < self._stall_until_s or (
            self._stall_from_s <= t_capture_s < self._stall_until_s
        )

    async def open(self) -> None:
        if self._thread is not None:
            return
        loop = asyncio.get_running_loop()
        with self._clock.hold():  # a simulated world waits for the device to open
            handle = await loop.run_in_executor(None, self._open_source)
        handoff: FrameHandoff[RawFrame | _End] = FrameHandoff(
            loop, self._capacity, self._drop_oldest
        )
        stop = threading.Event()
        progress = self._progress = _Progress(self._clock.now())
        thread = threading.Thread(
            target=self._run,
            args=(handle, handoff, stop, progress),
            name=f"capture {self.name}",
            daemon=True,
        )
        self._handoff, self._stop, self._thread = handoff, stop, thread
        if self._last_seq is None:
            self._last_seq = self._first_seq() - 1
        thread.start()

    async def close(self) -> None:
        thread, stop, handoff = self._thread, self._stop, self._handoff
        self._thread = self._stop = None
        if thread is None or stop is None or handoff is None:
            return
        stop.set()
        handoff.close()
        self._queue_dropped_closed += handoff.dropped
        with self._clock.hold():
            await asyncio.get_running_loop().run_in_executor(None, thread.join, JOIN_TIMEOUT_S)
        if thread.is_alive():
            self._note(
                f"{self.name}: capture thread still blocked in the driver {JOIN_TIMEOUT_S:g} s "
                "after close; it releases the device when the driver returns"
            )

    async def frames(self) -> AsyncIterator[CameraFrame]:
        handoff = self._handoff
        if handoff is None or self._thread is None:
            raise CameraError(f"{self.name}: frames() called on a camera that is not open")
        clock = self._clock
        while True:
            item = await handoff.get()
            if item is None:  # closed by close()
                return
            if isinstance(item, _End):
                if item.error is not None:
                    raise item.error
                return
            now = clock.now()  # a paced frame is due: the capture thread waited for it
            self._stats.queue_dropped = self._queue_dropped_closed + handoff.dropped
            last = self._last_seq if self._last_seq is not None else item.seq - 1
            frame = CameraFrame(
                seq=item.seq,
                t_capture_s=item.t_capture_s,
                image=item.image,
                dropped_before=max(0, item.seq - last - 1),
                packet=item.packet,
                measured=item.measured,
            )
            self._last_seq = item.seq
            self._stats.record(frame, now)
            yield frame

    # -- capture thread ---------------------------------------------------------------------

    def _run(
        self,
        handle: H,
        handoff: FrameHandoff[RawFrame | _End],
        stop: threading.Event,
        progress: _Progress,
    ) -> None:
        # the session clock waits for this thread while it reads and hands frames over
        with self._clock.participant():
            self._capture(handle, handoff, stop, progress)

    def _capture(
        self,
        handle: H,
        handoff: FrameHandoff[RawFrame | _End],
        stop: threading.Event,
        progress: _Progress,
    ) -> None:
        end = _End(None)
        self._thread_state.stop = stop
        try:
            while not stop.is_set():
                progress.read_since_s = self._clock.now()
                raw = self._read(handle)
                progress.read_since_s = None
                if raw is None:
                    break
                if self._paced and not self._wait_until(raw.t_capture_s):
                    return  # closed while waiting for the frame's capture time
                if self._stalled(raw.t_capture_s):
                    progress.frozen = True
                    continue  # injected stall: delivered nothing, or captured while frozen
                if self._first_read_s is None:
                    self._first_read_s = raw.t_capture_s
                progress.last_s, progress.handing_over = self._clock.now(), True
                progress.frozen = False
                busy_until_s = self._consumer_busy_until_s(raw.t_capture_s)
                if busy_until_s is not None and not self._clock.wait_until_blocking(
                    busy_until_s, stop
                ):
                    return  # closed while the consumer was stalled
                try:
                    if not self._hand_over(raw, handoff):
                        return
                finally:
                    progress.last_s, progress.handing_over = self._clock.now(), False
        except CameraError as exc:
            end = _End(exc)
        except Exception as exc:  # a bug or an OpenCV failure: report it, do not hang
            end = _End(CameraError(f"{self.name}: capture failed: {type(exc).__name__}: {exc}"))
        finally:
            try:
                self._close_source(handle)
            finally:
                if not stop.is_set():
                    handoff.put(end, force=True)

    def _hand_over(self, raw: RawFrame, handoff: FrameHandoff[RawFrame | _End]) -> bool:
        """Capture thread: run the frame hook on ``raw`` and put it on the hand-off; False
        once the hand-off is closed."""
        hook = self.frame_hook
        if hook is not None:
            if self._drop_oldest and handoff.full():
                handoff.count_dropped()  # the newest, before the hook saw it
                return True
            try:
                measured = hook(raw)
            except Exception:  # the consumer computes it again and sees the error
                measured = None
            raw = RawFrame(raw.seq, raw.t_capture_s, raw.image, raw.packet, measured)
        return handoff.put(raw)
