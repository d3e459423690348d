"""The view over a stored session (``stipi-daemon view SESSION``).

:class:`ReplaySource` reads a session once (:class:`~stipi_daemon.storage.SessionReader`:
frames with S_k, force samples, phase transitions, the manifest's threshold and ROI, the
summary) and serves it to :class:`~.server.ViewServer` as the live view's state, whole, with
the frame list the page scrubs through and the frames that set the results:

* ``s0``: the first frame at or after T_0 (the release), whose S_k is S_0;
* ``s_max``: the frame of the largest S_k in the recovery window (S_max, Eq. (5));
* ``t_r``: the first frame at or after T_s = T_0 + T_r (Eq. (6)).

A frame's picture is read from the session video by its ``seq`` with the project's reader
(:func:`~stipi_daemon.storage.video_readback.read_video_image`), only when the page asks
for it; a video that stores only the ROI's box is placed at its offset in the camera
frame (the rest :data:`NOT_STORED_FILL`), so the ROI is drawn where S_k was counted.
All times are on the session clock [s]; nothing is written.
"""

from __future__ import annotations

import contextlib
import math
import sys
import threading
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.imaging import roi_from_record
from stipi_daemon.app.liveview.server import ViewServer, is_loopback
from stipi_daemon.app.liveview.state import PreviewFrame, roi_dict
from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader
from stipi_daemon.storage.video_readback import probe_video, read_video_image

__all__ = ["MARK_LABELS", "NOT_STORED_FILL", "ReplaySource", "result_marks", "serve_session"]

#: Gray level of the part of a frame an ROI-cropped video did not store [8-bit].
NOT_STORED_FILL = 255
#: Captions of the marked frames.
MARK_LABELS = {"s0": "S_0 (T_0)", "s_max": "S_max", "t_r": "T_r (T_s)"}


def _first_at_or_after(t_s: npt.NDArray[np.float64], t: float) -> int | None:
    i = int(np.searchsorted(t_s, t, side="left"))
    return i if i < t_s.size else None


def result_marks(
    t_s: npt.NDArray[np.float64], s_k: npt.NDArray[np.float64], pitting: dict[str, Any] | None
) -> dict[str, int]:
    """Index (into the time-ordered frames ``t_s``, ``s_k``) of the frames that set S_0,
    S_max and T_r, from the summary's ``results.pitting`` (T_0 ``t0_s``, T_s ``ts_s``);
    a result the summary lacks has no mark."""
    marks: dict[str, int] = {}
    if not pitting or t_s.size == 0:
        return marks
    t0 = pitting.get("t0_s")
    if isinstance(t0, int | float) and math.isfinite(t0):
        i0 = _first_at_or_after(t_s, float(t0))
        if i0 is not None:
            marks["s0"] = i0
            ts = pitting.get("ts_s")
            end = t_s.size
            if isinstance(ts, int | float) and math.isfinite(ts):
                its = _first_at_or_after(t_s, float(ts))
                if its is not None:
                    marks["t_r"] = its
            marks["s_max"] = i0 + int(np.argmax(s_k[i0:end]))
    return marks


class ReplaySource:
    """A stored session as a :class:`~.server.ViewSource` (see the module docstring).

    Parameters
    ----------
    session_dir : Path
        The session directory.

    Raises
    ------
    SessionError
        The session cannot be read.
    """

    def __init__(self, session_dir: Path) -> None:
        with SessionReader(session_dir) as reader:
            frames = reader.frames()
            force = reader.force_samples()
            self._transitions = [
                [t.t_host_s, t.old_state, t.new_state, t.reason] for t in reader.transitions()
            ]
            self._video = reader.video_path
            video_rows = reader.video_frames() if self._video is not None else None
            summary = reader.summary or {}
            manifest = reader.manifest
            self._session_id = reader.session_id
            self._metadata = {k: v for k, v in reader.metadata.items()}
        order = np.argsort(frames["t_capture_host_s"], kind="stable")
        self._seq = np.asarray(frames["seq"])[order].astype(np.int64)
        self._t_s = np.asarray(frames["t_capture_host_s"], dtype=np.float64)[order]
        self._s_k = np.asarray(frames["s_k"], dtype=np.float64)[order]
        self._index_of_seq: dict[int, int] = {}
        if video_rows is not None:
            for seq, k in zip(video_rows["seq"], video_rows["frame_index"], strict=True):
                self._index_of_seq[int(seq)] = int(k)
        ok = np.isfinite(np.asarray(force["force_n"], dtype=np.float64))
        self._force = np.column_stack(
            [np.asarray(force["t_host_s"], dtype=np.float64)[ok], np.asarray(force["force_n"])[ok]]
        )
        cal = manifest.get("calibration") or {}
        self._threshold_p = int(cal.get("threshold_p", 0))
        self._roi = roi_dict(roi_from_record(cal.get("roi")))
        self._crop: tuple[int, int, int, int] | None = None
        self._frame_size: tuple[int, int] | None = None
        if self._video is not None and self._video.is_file():
            with contextlib.suppress(SessionError):
                video_info = probe_video(self._video)
                self._crop, self._frame_size = video_info.crop, video_info.frame_size
        results = summary.get("results") or {}
        self._pitting = results.get("pitting")
        self._summary = summary

    def info(self) -> dict[str, Any]:
        """Session, metadata, threshold and ROI, mode ``replay``."""
        return {
            "mode": "replay",
            "session_id": self._session_id,
            "metadata": self._metadata,
            "threshold_p": self._threshold_p,
            "roi": self._roi,
            "pitting_duration_s": None,
            "recovery_max_s": None,
            "force_band_n": None,
        }

    def marks(self) -> dict[str, dict[str, Any]]:
        """The marked frames: index, ``seq``, capture time [s], S_k [px], caption."""
        return {
            k: {
                "index": i,
                "seq": int(self._seq[i]),
                "t_s": float(self._t_s[i]),
                "s_k": float(self._s_k[i]),
                "label": MARK_LABELS[k],
            }
            for k, i in result_marks(self._t_s, self._s_k, self._pitting).items()
        }

    def snapshot(self, cursor: dict[str, int]) -> dict[str, Any]:
        """The whole session on the first call; afterwards the same state, no new points."""
        first = not cursor.get("sent", 0)
        cursor["sent"] = 1
        t0 = None if not self._pitting else self._pitting.get("t0_s")
        end_t = float(self._t_s[-1]) if self._t_s.size else 0.0
        verdict = self._summary.get("verdict") or {}
        msg: dict[str, Any] = {
            "mode": "replay",
            "now_s": end_t,
            "phase": str(self._transitions[-1][2]) if self._transitions else "-",
            "phase_since_s": self._transitions[-1][0] if self._transitions else 0.0,
            "prompt": str(verdict.get("line") or ""),
            "t_release_s": t0,
            "params": None,
            "health": {"frames": int(self._seq.size), "verdict": verdict.get("status")},
            "finished": True,
            "frame_seq": None,
            "force": self._force.tolist() if first else [],
            "s_k": np.column_stack([self._t_s, self._s_k]).tolist() if first else [],
            "transitions": self._transitions if first else [],
            "notes": [],
        }
        if first:
            msg["frames"] = np.column_stack(
                [self._seq.astype(np.float64), self._t_s, self._s_k]
            ).tolist()
            msg["marks"] = self.marks()
        return msg

    def _camera_frame(self, image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
        """A stored image in camera coordinates: a cropped one placed at its offset."""
        if self._crop is None or self._frame_size is None:
            return image
        x0, y0, x1, y1 = self._crop
        width, height = self._frame_size
        if image.shape[:2] != (y1 - y0, x1 - x0) or x1 > width or y1 > height:
            raise SessionError(f"the video's crop {self._crop} does not fit its frames")
        canvas = np.full((height, width, *image.shape[2:]), NOT_STORED_FILL, dtype=np.uint8)
        canvas[y0:y1, x0:x1] = image
        return canvas

    def preview_frame(self, seq: int | None) -> PreviewFrame | None:
        """Frame ``seq`` read from the session video (None: the first frame); None when the
        session has no such frame or its video does not hold it."""
        if self._seq.size == 0 or self._video is None:
            return None
        seq = int(self._seq[0]) if seq is None else seq
        i = np.flatnonzero(self._seq == seq)
        k = self._index_of_seq.get(seq)
        if i.size == 0 or k is None:
            return None
        try:
            image = self._camera_frame(read_video_image(self._video, k))
        except SessionError:
            return None
        return PreviewFrame(seq, float(self._t_s[i[0]]), int(self._s_k[i[0]]), image)


def serve_session(
    session_dir: Path,
    host: str = "127.0.0.1",
    port: int = 0,
    *,
    out: TextIO | None = None,
    until: threading.Event | None = None,
) -> int:
    """Serve the view of a stored session until Ctrl-C (or ``until`` is set); prints its
    address (and a warning when ``host`` is not loopback) on ``out`` (default stdout).
    Returns the exit status (0).

    Raises
    ------
    SessionError
        The session cannot be read.
    StipiError
        The address cannot be listened on.
    """
    out = out if out is not None else sys.stdout
    server = ViewServer(ReplaySource(session_dir), host, port)
    url = server.start()
    try:
        print(f"view of {session_dir.name}: {url}", file=out, flush=True)
        if not is_loopback(host):
            print(
                f"warning: the view listens on {host}, not loopback: other machines can reach "
                "it (the token in the address is all that keeps them out)",
                file=out,
                flush=True,
            )
        stop = until if until is not None else threading.Event()
        with contextlib.suppress(KeyboardInterrupt):
            while not stop.wait(0.5):
                pass
    finally:
        server.stop()
    return 0
