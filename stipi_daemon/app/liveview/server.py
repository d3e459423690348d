"""The view server: one page, read-only, for the operator's browser only.

:class:`ViewServer` serves the view of a :class:`ViewSource` (the live measurement,
:class:`~.state.LiveState`, or a stored session, :mod:`.replay`) with aiohttp, on an event
loop of its own in a thread of its own: the daemon's loop never runs a viewer's work and
its clock never waits for one (a viewer is neither a participant of a simulated run's
:class:`~stipi_daemon.clock.VirtualClock` nor a hold on it).

What it serves, all ``GET``:

* ``/`` the page, ``/static/view.js`` and ``/static/view.css`` (package data, no build);
* ``/ws`` a websocket on which the server sends the state as JSON at most
  :data:`STATE_RATE_HZ` times a second (the traces' new points only) and frames as binary
  messages: live, the server pushes the newest frame to every viewer at most
  :data:`PREVIEW_RATE_HZ` times a second, unasked (beyond four viewers they take turns,
  :data:`FRAME_SENDS_RATE_HZ` frames a second in all); replay, the frame a page asks for
  (``seq:N``: frame N of the stored session). It reads nothing else;
* ``/frame.jpg`` the newest frame (live) or frame ``seq`` (replay) as a preview JPEG
  (:mod:`.preview`), as on the websocket. A live preview is made in the view's thread, once
  a tick of :meth:`ViewServer._tick` while anyone watches, and shared by every viewer: at
  most :data:`PREVIEW_RATE_HZ` encodings a second, however many watch (a stored frame: in a
  worker thread, as the video is read, when a page asks for it).

A viewer that stops reading costs nothing and holds nothing back: at most one frame is in
flight per viewer (the next is sent only once the last has left the server's write buffer
for the socket; until then a newer frame replaces it, latest wins, and the frames in
between are never sent), so a slow viewer gets fewer frames and a stalled one none, the
memory held for it bounded by the socket's send buffer and one frame. Its state is sent
again from where it stopped, never queued; one that stalls a send for
:data:`SEND_TIMEOUT_WALL_S` is disconnected.

Who may see it: every request must carry the run's random token (``?token=``, in the
printed address); its ``Host`` must be the served one (a name that resolves to this
machine by DNS rebinding is refused); an ``Origin``, which a browser sends with a
websocket and with cross-site requests, must be the served origin (a websocket without one
is refused); only ``GET``/``HEAD``. It listens on loopback unless configured otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import json
import secrets
import threading
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from typing import Any, Protocol

from aiohttp import WSMsgType, web

from stipi_daemon.app.liveview.preview import preview_jpeg
from stipi_daemon.app.liveview.state import PreviewFrame
from stipi_daemon.errors import StipiError

__all__ = [
    "FRAME_SENDS_RATE_HZ",
    "PREVIEW_RATE_HZ",
    "STATE_RATE_HZ",
    "PreviewFrame",
    "ViewServer",
    "ViewSource",
    "is_loopback",
]

#: Most state messages a viewer is sent per second [1/s].
STATE_RATE_HZ = 4.0
#: Most preview frames encoded per second for all viewers together, and pushed to each
#: live viewer [1/s]: the view's one timer ticks at this rate while anyone watches (one
#: encoding of the newest frame a tick, shared; the states due on the ticks that reach
#: the next 1/:data:`STATE_RATE_HZ` s).
PREVIEW_RATE_HZ = 10.0
#: Most live frames sent per second to all viewers together [1/s]: up to
#: ``FRAME_SENDS_RATE_HZ / PREVIEW_RATE_HZ`` viewers (4) get every preview, more take
#: turns (20 viewers: 2 frames a second each), so the view's work per tick, and the
#: stretches it holds the interpreter against the daemon's frame thread, stop growing with
#: the number of viewers.
FRAME_SENDS_RATE_HZ = 40.0
#: Wall time a websocket send may take before the viewer is dropped [s].
SEND_TIMEOUT_WALL_S = 60.0
#: Files the page is made of (package data).
_STATIC = {"view.js": "text/javascript", "view.css": "text/css"}
_SECURITY_HEADERS = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": (
        "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob:; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    ),
}


class ViewSource(Protocol):
    """What a view server shows (the live measurement or a stored session)."""

    def info(self) -> dict[str, Any]:
        """What does not change: session, metadata, threshold, ROI, mode."""
        ...

    def snapshot(self, cursor: dict[str, int]) -> dict[str, Any]:
        """The state, with what one viewer has not been sent yet (``cursor`` advanced)."""
        ...

    def preview_frame(self, seq: int | None) -> PreviewFrame | None:
        """Frame ``seq`` (None: the newest), or None when there is none. May block (a
        stored video is read): never called on the daemon's loop."""
        ...


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is this machine's loopback."""
    if host == "localhost":
        return True
    with contextlib.suppress(ValueError):
        return ipaddress.ip_address(host).is_loopback
    return False


def _is_ip_literal(host: str) -> bool:
    with contextlib.suppress(ValueError):
        ipaddress.ip_address(host.strip("[]"))
        return True
    return False


def _split_host(value: str) -> tuple[str, str]:
    """``host[:port]`` (an IPv6 literal in brackets) as (host, port); port '' if none."""
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        return host, rest[1:] if rest.startswith(":") else ""
    host, _, port = value.rpartition(":") if value.count(":") == 1 else (value, "", "")
    return host, port


class _Guard:
    """The checks every request passes: method, Host, token, Origin."""

    def __init__(self, host: str, token: str) -> None:
        self.bind_host = host
        self.token = token
        self.port = 0

    def host_allowed(self, header: str | None) -> bool:
        """A ``Host`` naming the served address (loopback: any loopback name; a wildcard
        address: an IP literal, which no DNS answer can rebind) and the served port."""
        if not header:
            return False
        host, port = _split_host(header.strip().lower())
        if port != str(self.port):
            return False
        if self.bind_host in ("0.0.0.0", "::"):
            return _is_ip_literal(host) or host == "localhost"
        if is_loopback(self.bind_host):
            return is_loopback(host)
        return host == self.bind_host.lower()

    def origin_allowed(self, origin: str) -> bool:
        """An ``Origin`` of ``http://`` and an allowed host (see :meth:`host_allowed`)."""
        scheme, _, rest = origin.strip().lower().partition("://")
        return scheme == "http" and "/" not in rest and self.host_allowed(rest)

    def refusal(self, request: web.Request) -> web.Response | None:
        """Why ``request`` is refused, as the response; None when it may be served."""
        if request.method not in ("GET", "HEAD"):
            return web.Response(status=405, text="read-only", headers={"Allow": "GET, HEAD"})
        if not self.host_allowed(request.headers.get("Host")):
            return web.Response(status=421, text="wrong host")
        given = request.query.get("token", "")
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            return web.Response(status=403, text="token required")
        origin = request.headers.get("Origin")
        is_ws = request.headers.get("Upgrade", "").lower() == "websocket"
        if (origin is None and is_ws) or (origin is not None and not self.origin_allowed(origin)):
            return web.Response(status=403, text="wrong origin")
        return None


def _static_text(name: str) -> str:
    return (resources.files("stipi_daemon.app.liveview") / "static" / name).read_text("utf-8")


class _Previews:
    """Preview JPEGs shared by every viewer, at most :data:`PREVIEW_RATE_HZ` new ones a
    second: the newest frame encoded in the view's thread (about a millisecond at 720p,
    never on the daemon's loop), a stored one read and encoded in a worker thread."""

    def __init__(self, source: ViewSource, threshold_p: int, roi: dict[str, Any] | None) -> None:
        self._source = source
        self._threshold_p = threshold_p
        self._roi = roi
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="stipi-view-jpeg")
        self._lock = asyncio.Lock()
        self._cached: tuple[int, float, int, bytes, int] | None = None  # seq, t, s_k, jpeg, step
        self._cached_wall_s = -float("inf")
        self.encoded = 0

    def _make(
        self, seq: int | None, frame: PreviewFrame | None = None
    ) -> tuple[int, float, int, bytes, int] | None:
        frame = self._source.preview_frame(seq) if frame is None else frame
        if frame is None:
            return None
        jpeg, step = preview_jpeg(frame.image, self._threshold_p, self._roi)
        return frame.seq, frame.t_capture_s, frame.s_k, jpeg, step

    async def get(self, seq: int | None) -> tuple[int, float, int, bytes, int] | None:
        async with self._lock:
            cached = self._cached
            fresh = time.monotonic() - self._cached_wall_s < 1.0 / PREVIEW_RATE_HZ
            if cached is not None and (cached[0] == seq or (seq is None and fresh)):
                return cached
            if seq is None:  # the newest frame, in memory: encoded here, in the view's thread
                newest = self._source.preview_frame(None)
                if cached is not None and newest is not None and newest.seq == cached[0]:
                    return cached  # the daemon has made no newer frame: nothing to encode
                made = self._make(seq, newest)
            else:  # a stored frame is read from the video first: in a worker thread
                loop = asyncio.get_running_loop()
                made = await loop.run_in_executor(self._pool, self._make, seq)
            if made is not None:
                self._cached, self._cached_wall_s = made, time.monotonic()
                self.encoded += 1
            return made

    def newest(self) -> tuple[int, float, int, bytes, int] | None:
        """The newest frame's preview, encoded here (in the view's thread) unless it is the
        one made last; None when there is no frame yet. Called once a tick of the view's
        timer: :data:`PREVIEW_RATE_HZ` encodings a second at most."""
        cached = self._cached
        newest = self._source.preview_frame(None)
        if newest is None or (cached is not None and newest.seq == cached[0]):
            return cached
        made = self._make(None, newest)
        if made is not None:
            self._cached, self._cached_wall_s = made, time.monotonic()
            self.encoded += 1
        return made

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


class ViewServer:
    """Serves a :class:`ViewSource` in a thread of its own (see the module docstring).

    Parameters
    ----------
    source : ViewSource
        What to show.
    host : str
        Address to listen on (default loopback).
    port : int
        Port (0: one the system chooses).
    token : str, optional
        The token requests must carry (default: a new random one).
    """

    def __init__(
        self, source: ViewSource, host: str = "127.0.0.1", port: int = 0, token: str | None = None
    ) -> None:
        self.source = source
        self.host = host
        self.token = token or secrets.token_urlsafe(18)
        self._guard = _Guard(host, self.token)
        self._want_port = port
        self.port = 0
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._sockets: set[web.WebSocketResponse] = set()
        # insertion-ordered, so that viewers take turns for frames in a stable order
        self._viewers: dict[_Viewer, None] = {}
        self._turn = 0
        # this tick's state messages by the cursor they were made for: viewers in step
        # share one snapshot and one JSON encoding
        self._states: dict[tuple[tuple[str, int], ...], tuple[str, dict[str, int]]] = {}
        self._ticker: asyncio.Task[None] | None = None
        info = source.info()
        self._live = info.get("mode") != "replay"
        self._previews = _Previews(source, int(info["threshold_p"]), info.get("roi"))
        self._page = _static_text("index.html").replace("__TOKEN__", self.token)
        #: Viewers connected now (websockets open) [-].
        self.viewers = 0

    @property
    def url(self) -> str:
        """The address to open, token included."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/?token={self.token}"

    @property
    def previews_encoded(self) -> int:
        """Preview JPEGs made so far [-]."""
        return self._previews.encoded

    # -------------------------------------------------------------------- lifecycle

    def start(self) -> str:
        """Listen (in a new thread); return :attr:`url`.

        Raises
        ------
        StipiError
            The address cannot be listened on (a port in use, an address not here).
        """
        self._thread = threading.Thread(target=self._serve, name="stipi-view", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise StipiError(
                f"view: cannot listen on {self.host}:{self._want_port}: {self._error}"
            ) from self._error
        return self.url

    def stop(self) -> None:
        """Close every connection and end the thread (waits at most a few seconds)."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._previews.close()

    def _serve(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # reported by start()
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        app = web.Application(middlewares=[self._guarded])
        app.router.add_get("/", self._index)
        app.router.add_get("/static/{name}", self._static)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/frame.jpg", self._frame)
        runner = web.AppRunner(app, handle_signals=False, access_log=None, shutdown_timeout=0.5)
        await runner.setup()
        try:
            site = web.TCPSite(runner, self.host, self._want_port)
            await site.start()
            # the listening sockets: which port the system chose
            sockets: list[Any] = list(getattr(site._server, "sockets", None) or [])
            self.port = self._guard.port = int(sockets[0].getsockname()[1])
            self._ready.set()
            await self._stop.wait()
            for ws in list(self._sockets):
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(0.5):
                        await ws.close()
        finally:
            await runner.cleanup()

    # -------------------------------------------------------------------- handlers

    @web.middleware
    async def _guarded(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        refused = self._guard.refusal(request)
        response = refused if refused is not None else await handler(request)
        if not response.prepared:
            response.headers.update(_SECURITY_HEADERS)
        return response

    async def _index(self, request: web.Request) -> web.Response:
        return web.Response(text=self._page, content_type="text/html", charset="utf-8")

    async def _static(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in _STATIC:
            raise web.HTTPNotFound()
        return web.Response(text=_static_text(name), content_type=_STATIC[name], charset="utf-8")

    async def _frame(self, request: web.Request) -> web.Response:
        seq_text = request.query.get("seq")
        try:
            seq = None if seq_text is None else int(seq_text)
        except ValueError:
            raise web.HTTPBadRequest(text="seq must be an integer") from None
        made = await self._previews.get(seq)
        if made is None:
            raise web.HTTPNotFound(text="no frame")
        f_seq, t_s, s_k, jpeg, step = made
        headers = {
            "X-Frame-Seq": str(f_seq),
            "X-Frame-T-S": repr(t_s),
            "X-Frame-S-K": str(s_k),
            "X-Preview-Step": str(step),
        }
        return web.Response(body=jpeg, content_type="image/jpeg", headers=headers)

    async def _websocket(self, request: web.Request) -> web.WebSocketResponse:
        # no per-message deflate: JPEGs do not shrink, and deflating costs the daemon's CPU
        ws = web.WebSocketResponse(heartbeat=None, max_msg_size=256, compress=False)
        for k, v in _SECURITY_HEADERS.items():
            ws.headers[k] = v
        transport = request.transport
        await ws.prepare(request)
        self._sockets.add(ws)
        self.viewers += 1
        viewer = _Viewer()
        self._viewers[viewer] = None
        if self._ticker is None or self._ticker.done():
            self._ticker = asyncio.create_task(self._tick())
        sender = asyncio.create_task(self._send(ws, viewer, transport))
        try:
            # What a page sends only chooses which stored frame it is sent next ("seq:N",
            # replay); live frames are pushed unasked, and anything else is ignored.
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    break
                viewer.ask(str(msg.data))
        finally:
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await sender
            self.viewers -= 1
            self._viewers.pop(viewer, None)
            self._sockets.discard(ws)
        return ws

    async def _tick(self) -> None:
        """The view's one timer, for all viewers: every 1/:data:`PREVIEW_RATE_HZ` s (on a
        fixed grid, so ticks do not drift late) the newest live frame is encoded once and
        offered to the viewers whose turn it is (:meth:`_offer`), and on the tick that
        reaches each next 1/:data:`STATE_RATE_HZ` s each viewer's state is due (replay: it
        ticks only for the states,
        :data:`STATE_RATE_HZ` times a second). One wake-up of this thread a tick; the task
        ends with the last viewer."""
        per_s = PREVIEW_RATE_HZ if self._live else STATE_RATE_HZ  # ticks a second [1/s]
        period_s = 1.0 / per_s
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        k = 0
        while self._viewers:
            k += 1
            await asyncio.sleep(max(0.0, t0 + k * period_s - loop.time()))
            if loop.time() - (t0 + k * period_s) > period_s:  # far behind: skip, not catch up
                t0, k = loop.time(), 0
            made = self._previews.newest() if self._live else None
            if made is not None:
                self._offer(made[0], _frame_message(made), int(FRAME_SENDS_RATE_HZ / per_s))
            if int(k * STATE_RATE_HZ / per_s) != int((k - 1) * STATE_RATE_HZ / per_s):
                self._states.clear()
                for viewer in list(self._viewers):
                    viewer.state_due()

    def _offer(self, seq: int, message: bytes, most: int) -> None:
        """Offer frame ``seq`` (its websocket message, made once) to at most ``most``
        viewers, those whose turn it is (round robin)."""
        viewers = list(self._viewers)
        n = min(max(1, most), len(viewers))
        for i in range(n):
            viewers[(self._turn + i) % len(viewers)].offer(seq, message)
        self._turn = (self._turn + n) % len(viewers) if viewers else 0

    def _state_text(self, cursor: dict[str, int]) -> str:
        """The state message for a viewer at ``cursor`` (advanced): made once a tick for
        all viewers at the same cursor."""
        key = tuple(sorted(cursor.items()))
        made = self._states.get(key)
        if made is None:
            text = json.dumps(self.source.snapshot(cursor))
            self._states[key] = (text, dict(cursor))
            return text
        text, after = made
        cursor.update(after)
        return text

    async def _send(
        self, ws: web.WebSocketResponse, viewer: _Viewer, transport: asyncio.BaseTransport | None
    ) -> None:
        """The info once, then the state when due (:meth:`_tick`), the newest live frame
        when one it has not been sent is offered and its last frame has left the write
        buffer (else it is skipped: latest wins), and a stored frame it asked for. It
        sleeps until one of these (no timer of its own)."""
        cursor: dict[str, int] = {}
        try:
            async with asyncio.timeout(SEND_TIMEOUT_WALL_S):
                await ws.send_json({"info": self.source.info()})
            while not ws.closed:
                if viewer.state_is_due:
                    viewer.state_is_due = False
                    async with asyncio.timeout(SEND_TIMEOUT_WALL_S):  # a stalled viewer waits
                        await ws.send_str(self._state_text(cursor))
                offered, viewer.offered = viewer.offered, None
                if offered is not None and offered[0] != viewer.sent_seq and _drained(transport):
                    viewer.sent_seq = offered[0]
                    async with asyncio.timeout(SEND_TIMEOUT_WALL_S):
                        await ws.send_bytes(offered[1])
                if viewer.wants is not None:  # replay: the stored frame asked for
                    wants, viewer.wants = int(viewer.wants), None
                    made = await self._previews.get(wants)
                    if made is not None:
                        async with asyncio.timeout(SEND_TIMEOUT_WALL_S):
                            await ws.send_bytes(_frame_message(made))
                await viewer.wait()
        except (TimeoutError, ConnectionError):
            await ws.close()


def _drained(transport: asyncio.BaseTransport | None) -> bool:
    """Whether everything sent on ``transport`` has left its write buffer for the socket
    (the last frame is no longer in flight in this process)."""
    if transport is None or transport.is_closing():
        return False
    size = getattr(transport, "get_write_buffer_size", None)
    return size is None or int(size()) == 0


class _Viewer:
    """What one page is to be sent next: the live frame offered (latest wins), the stored
    frame it asked for (``seq``, replay), whether its state is due; and the wake-up of its
    sender."""

    def __init__(self) -> None:
        self.wants: str | None = None
        self.offered: tuple[int, bytes] | None = None
        """The live frame offered: its ``seq`` and websocket message."""
        self.sent_seq: int | None = None
        self.state_is_due = True
        self._woken = asyncio.Event()

    def ask(self, text: str) -> None:
        if text.startswith("seq:") and text[4:].isdigit():
            self.wants = text[4:]
            self._woken.set()

    def offer(self, seq: int, message: bytes) -> None:
        if seq != self.sent_seq:
            self.offered = (seq, message)
            self._woken.set()

    def state_due(self) -> None:
        self.state_is_due = True
        self._woken.set()

    async def wait(self) -> None:
        await self._woken.wait()
        self._woken.clear()


def _frame_message(made: tuple[int, float, int, bytes, int]) -> bytes:
    """A frame as one binary websocket message: a 4-byte big-endian length, a JSON header
    (``seq``, ``t_s``, ``s_k``, ``step``), the JPEG."""
    seq, t_s, s_k, jpeg, step = made
    head = json.dumps({"seq": seq, "t_s": t_s, "s_k": s_k, "step": step}).encode()
    return len(head).to_bytes(4, "big") + head + jpeg
