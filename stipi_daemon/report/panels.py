"""Representative frames as the report shows them: raw, thresholded, with the ROI.

Each frame stored with the session (:mod:`.frames`) is thresholded again with the session's
p and ROI (Eq. 1) and counted again (Eq. 2), so the page shows the recount beside the S_k
measured live and the one the ``frames`` table holds. It is pure: the frames come in a
:class:`~.inputs.ReportInput`; drawing them is :func:`.render.draw_frames`'s job.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.imaging import (
    CircleROI,
    RectROI,
    occluded_pixel_count,
    roi_from_record,
    roi_mask,
    threshold_binary_inverted,
    to_gray,
)
from stipi_daemon.errors import SessionError
from stipi_daemon.report.frames import KINDS
from stipi_daemon.report.inputs import ReportInput

__all__ = ["FramePanel", "frame_panels", "roi_from_mapping"]


@dataclass(frozen=True)
class FramePanel:
    """A raw frame and its Eq. (1) thresholding, with the ROI.

    Attributes
    ----------
    kind, caption : str
        Which representative frame (:data:`~stipi_daemon.report.frames.KINDS`).
    seq : int
        Camera frame number.
    t_s : float
        Capture time [s].
    t_since_t0_s : float or None
        Capture time since T_0 [s].
    raw : numpy.ndarray
        The raw frame as recorded (``uint8``, gray or BGR).
    binary : numpy.ndarray
        Eq. (1) over the whole frame: 1 where gray <= p (``uint8``).
    roi_mask : numpy.ndarray
        ``bool`` (H, W), True inside the ROI.
    roi : RectROI or CircleROI or None
        The ROI (None: whole frame).
    threshold_p : int
        p of Eq. (1) [8-bit].
    s_k_recount_px : int
        S_k counted again from the stored frame, Eq. (2) [px].
    s_k_live_px : int
        S_k measured live for this frame [px].
    s_k_table_px : float or None
        S_k the session's ``frames`` table holds for ``seq`` [px].
    """

    kind: str
    caption: str
    seq: int
    t_s: float
    t_since_t0_s: float | None
    raw: npt.NDArray[np.uint8]
    binary: npt.NDArray[np.uint8]
    roi_mask: npt.NDArray[np.bool_]
    roi: RectROI | CircleROI | None
    threshold_p: int
    s_k_recount_px: int
    s_k_live_px: int
    s_k_table_px: float | None


def roi_from_mapping(value: Any, where: str) -> RectROI | CircleROI | None:
    """The ROI a manifest records (``{"kind": "circle", ...}``), or None.

    Raises
    ------
    SessionError
        The value is not a valid ROI (``where`` names the place).
    """
    try:
        return roi_from_record(value)
    except ValueError as exc:
        raise SessionError(f"{where}: {exc}") from None


def frame_panels(inp: ReportInput) -> tuple[FramePanel, ...]:
    """The representative frames thresholded with the session's p and ROI.

    Raises
    ------
    SessionError
        The manifest's calibration has no threshold p or an invalid ROI while the session
        holds representative frames.
    """
    if not inp.representative:
        return ()
    p = inp.calibration.get("threshold_p")
    if isinstance(p, bool) or not isinstance(p, int):
        raise SessionError(
            f"session {inp.session_id}: manifest calibration has no integer threshold_p ({p!r})"
        )
    roi = roi_from_mapping(inp.calibration.get("roi"), f"session {inp.session_id}: calibration.roi")
    by_seq = dict(zip(inp.frame_seq.tolist(), inp.s_k_px.tolist(), strict=True))
    t0 = inp.t0_s
    out = []
    for f in inp.representative:
        gray = to_gray(f.image)
        out.append(
            FramePanel(
                kind=f.kind,
                caption=KINDS.get(f.kind, f.kind),
                seq=f.seq,
                t_s=f.t_s,
                t_since_t0_s=None if t0 is None else f.t_s - t0,
                raw=f.image,
                binary=threshold_binary_inverted(gray, p),
                roi_mask=roi_mask(f.image.shape, roi),
                roi=roi,
                threshold_p=p,
                s_k_recount_px=occluded_pixel_count(f.image, p, roi),
                s_k_live_px=f.s_k_px,
                s_k_table_px=by_seq.get(f.seq),
            )
        )
    return tuple(out)
