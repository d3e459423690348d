"""Representative camera frames of a measurement: chosen while recording, kept as PNGs.

A session stores S_k for every frame but no video, so a report could not show what was
counted. This module owns the choice of three raw frames while the daemon records
(:class:`RepresentativeFrames`: the middle of the pitting hold; the frame with the
smallest S_k from the hold on (nearest S_0, the deepest pit seen); the frame with the
largest S_k once the release is detected (S_max, the recovered tissue)), and their
storage in the
session directory: ``frames/representative_<kind>.png`` (lossless, the camera's pixels
exactly) and ``frames/representative.json`` (frame number, capture time [s] and S_k
[px] each). It does not threshold or count pixels (:mod:`stipi_daemon.analysis.imaging`)
nor draw them (:mod:`stipi_daemon.report.render`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
import numpy.typing as npt

from stipi_daemon.errors import SessionError
from stipi_daemon.measurement.state_machine import Phase

__all__ = [
    "FRAMES_DIR",
    "FRAMES_INDEX",
    "KINDS",
    "RepresentativeFrame",
    "RepresentativeFrames",
    "read_representative_frames",
    "write_representative_frames",
]

#: Sub-directory of the session directory holding the representative frames.
FRAMES_DIR: Final = "frames"
#: Index file (JSON) of the representative frames, inside :data:`FRAMES_DIR`.
FRAMES_INDEX: Final = "representative.json"
#: The kinds of representative frame, in display order, with their captions.
KINDS: Final[dict[str, str]] = {
    "pitting": "middle of the hold",
    "recovery_start": "near S_0, deepest pit",
    "recovered": "largest S_k, recovered",
}


@dataclass(frozen=True)
class RepresentativeFrame:
    """One representative raw frame.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    seq : int
        The camera's frame number (the ``frames`` table's ``seq``).
    t_s : float
        Capture time on the session clock [s].
    s_k_px : int
        S_k measured live for this frame, Eq. (2) [px].
    image : numpy.ndarray
        The raw ``uint8`` frame, gray ``(H, W)`` or BGR ``(H, W, 3)``.
    """

    kind: str
    seq: int
    t_s: float
    s_k_px: int
    image: npt.NDArray[np.uint8]


class RepresentativeFrames:
    """Keeps the representative frames while frames stream in (pure, no I/O).

    Each :meth:`offer` is a few comparisons; images are kept by reference (a camera frame
    is owned by its receiver and never reused), so nothing is copied per frame.

    Parameters
    ----------
    pitting_duration_s : float
        Planned pitting hold [s]; the pitting frame is the one nearest to its middle.
    """

    def __init__(self, pitting_duration_s: float) -> None:
        if not (math.isfinite(pitting_duration_s) and pitting_duration_s > 0.0):
            raise ValueError(f"pitting_duration_s must be finite and > 0, got {pitting_duration_s}")
        self._half_hold_s = 0.5 * pitting_duration_s
        self._pitting: tuple[float, RepresentativeFrame] | None = None
        self._low: RepresentativeFrame | None = None
        self._high: RepresentativeFrame | None = None

    def offer(
        self,
        seq: int,
        t_s: float,
        image: npt.NDArray[np.uint8],
        s_k_px: int,
        phase: Phase,
        t_pit_start_s: float | None,
        t_release_s: float | None,
    ) -> None:
        """Consider one frame.

        Parameters
        ----------
        seq, t_s, image, s_k_px
            The frame: number, capture time [s], pixels, S_k [px].
        phase : Phase
            The measurement's phase when the frame is measured (it may lag the frame's
            capture by the merge hold: the choices above do not depend on the lag).
        t_pit_start_s, t_release_s : float or None
            Start of the pitting hold and the release [s], once known.
        """
        if phase == Phase.PITTING and t_pit_start_s is not None:
            distance = abs(t_s - (t_pit_start_s + self._half_hold_s))
            if self._pitting is None or distance < self._pitting[0]:
                frame = RepresentativeFrame("pitting", seq, t_s, s_k_px, image)
                self._pitting = (distance, frame)
        # S_k follows the force on the probe (Eq. 5): high through the hold, lowest just
        # after the lift (S_0), then rising with the rebound. Its minimum from the hold on
        # is therefore the frame nearest S_0, whatever the phase lag of the offer.
        held = phase in (Phase.PITTING, Phase.RELEASE, Phase.RECOVERY)
        if held and (self._low is None or s_k_px < self._low.s_k_px):
            self._low = RepresentativeFrame("recovery_start", seq, t_s, s_k_px, image)
        recovering = phase == Phase.RECOVERY and t_release_s is not None and t_s >= t_release_s
        if recovering and (self._high is None or s_k_px > self._high.s_k_px):
            self._high = RepresentativeFrame("recovered", seq, t_s, s_k_px, image)

    def selected(self) -> tuple[RepresentativeFrame, ...]:
        """The frames chosen so far, in the order of :data:`KINDS`."""
        out = [] if self._pitting is None else [self._pitting[1]]
        out += [f for f in (self._low, self._high) if f is not None]
        return tuple(out)


def write_representative_frames(
    session_dir: Path, frames: tuple[RepresentativeFrame, ...]
) -> list[Path]:
    """Store ``frames`` as lossless PNGs and an index in ``<session_dir>/frames/``.

    Returns
    -------
    list of Path
        The files written (PNGs, then the index); empty when there is no frame.

    Raises
    ------
    SessionError
        A file cannot be written (path and reason named).
    """
    if not frames:
        return []
    directory = Path(session_dir) / FRAMES_DIR
    try:
        directory.mkdir(exist_ok=True)
    except OSError as exc:
        raise SessionError(f"{directory}: cannot create frames directory: {exc}") from exc
    written: list[Path] = []
    index: dict[str, dict[str, Any]] = {}
    for f in frames:
        path = directory / f"representative_{f.kind}.png"
        try:
            ok = cv2.imwrite(str(path), f.image)
        except cv2.error as exc:
            raise SessionError(f"{path}: cannot write frame: {exc}") from exc
        if not ok:
            raise SessionError(f"{path}: cannot write frame (OpenCV imwrite failed)")
        written.append(path)
        index[f.kind] = {
            "file": path.name,
            "seq": f.seq,
            "t_capture_s": f.t_s,
            "s_k_px": f.s_k_px,
            "shape": list(f.image.shape),
        }
    index_path = directory / FRAMES_INDEX
    try:
        index_path.write_text(json.dumps(index, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise SessionError(f"{index_path}: cannot write: {exc}") from exc
    written.append(index_path)
    return written


def read_representative_frames(session_dir: Path) -> tuple[RepresentativeFrame, ...]:
    """Read the frames :func:`write_representative_frames` stored (none: empty tuple).

    Raises
    ------
    SessionError
        The index is not valid JSON of the expected shape, or a PNG named in it is missing
        or unreadable, or does not have the recorded shape.
    """
    index_path = Path(session_dir) / FRAMES_DIR / FRAMES_INDEX
    if not index_path.is_file():
        return ()
    try:
        index = json.loads(index_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SessionError(f"{index_path}: not readable JSON: {exc}") from exc
    if not isinstance(index, dict):
        raise SessionError(f"{index_path}: expected an object keyed by frame kind")
    out: list[RepresentativeFrame] = []
    for kind in KINDS:
        entry = index.get(kind)
        if entry is None:
            continue
        try:
            name, seq = str(entry["file"]), int(entry["seq"])
            t_s, s_k, shape = float(entry["t_capture_s"]), int(entry["s_k_px"]), entry["shape"]
        except (KeyError, TypeError, ValueError) as exc:
            raise SessionError(f"{index_path}: entry {kind!r} is malformed ({exc})") from exc
        path = index_path.parent / name
        flag = cv2.IMREAD_UNCHANGED
        image = cv2.imread(str(path), flag) if path.is_file() else None
        if image is None:
            raise SessionError(f"{path}: representative frame missing or not a readable PNG")
        if list(image.shape) != list(shape) or image.dtype != np.uint8:
            raise SessionError(
                f"{path}: shape {list(image.shape)} {image.dtype}, index says {shape} uint8"
            )
        out.append(RepresentativeFrame(kind, seq, t_s, s_k, np.asarray(image, dtype=np.uint8)))
    return tuple(out)
