"""Which calibration, threshold p and ROI apply to a measurement: one rule for every caller.

The acquisition daemon (:func:`resolve_imaging`) and the offline ``analyze`` command
(:mod:`stipi_daemon.app.analyze`) both ask :func:`choose_imaging`. Each source says what
it knows as an :class:`ImagingSource`; the most specific source that sets a quantity wins:

* calibration: command-line override, config (its calibration file), stored manifest,
  simulated scene;
* threshold p of Eq. (1): command-line override, config (``imaging.threshold_p``),
  stored manifest (the threshold the live run counted with), the chosen calibration's own
  ``threshold_p``, simulated scene;
* ROI: command-line override (``full`` is a choice too: the whole frame), config
  (``imaging.roi``), stored manifest (the ROI the live run counted in), the chosen
  calibration's own ``roi``, simulated scene (its waveguide disc); none: the whole frame.

S is counted with a threshold and in an ROI, and a calibration holds only for S counted
as it was made: the daemon refuses a threshold or an ROI other than the calibration's
(:func:`resolve_imaging`); ``analyze`` flags results counted otherwise.

A simulated scene is read through the lazy registry (``"scene:imaging"``,
:mod:`stipi_daemon.registry`), so a run on real devices never loads the simulator; a
simulator's ``ground_truth.json`` offers the same as the scene (:func:`truth_source`).
The manifest's calibration record is written (:func:`calibration_record`) and read back
(:func:`recorded_source`) here, so both sides keep every field the analysis reads.

An ROI must lie entirely within the camera's frame (:func:`check_roi_fits`): one that lies
outside it, wholly or in part, is a config error before anything is recorded. Wholly
outside, every S_k would be 0 (a pit of full depth, no recovery); partly outside, the
pixels beyond the border are never counted, so S_k - and D_p through the calibration
(Eqs. 4-5), which was fitted on whole-ROI counts - would read low with nothing to show
it. Pixel membership is the analysis's own (:mod:`stipi_daemon.analysis.imaging`:
pixel centres within the circle's radius, or the rectangle's pixels).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import numpy as np
from pydantic import ValidationError

from stipi_daemon import registry
from stipi_daemon.analysis.calibration import Calibration, load_calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor, RectROI, describe_roi
from stipi_daemon.app.config import DaemonConfig, ImagingSettings
from stipi_daemon.errors import ConfigError
from stipi_daemon.measurement.replay import calibration_from_mapping

__all__ = [
    "Choice",
    "Imaging",
    "ImagingSource",
    "calibration_record",
    "check_roi_fits",
    "choose_imaging",
    "recorded_source",
    "resolve_imaging",
    "roi_field",
    "roi_fit_problem",
    "roi_from_truth",
    "scene_source",
    "settings_source",
    "truth_source",
]

_T = TypeVar("_T")

#: Source name of a simulated scene's calibration, threshold and ROI (daemon).
SIMULATED_SCENE = "simulated scene"
#: Source name of the stored manifest's calibration (``analyze SESSION``).
SESSION_MANIFEST = "session manifest"


@dataclass(frozen=True)
class Choice(Generic[_T]):
    """A value and the source it came from (a file path, ``--threshold``, ...)."""

    value: _T
    source: str


@dataclass(frozen=True)
class ImagingSource:
    """What one source says about the imaging; None where it says nothing.

    Attributes
    ----------
    calibration : Choice of Calibration or None
        Eqs. (4)-(5) coefficients.
    threshold_p : Choice of int or None
        Threshold p of Eq. (1) [8-bit intensity].
    roi : Choice of (CircleROI or RectROI or None) or None
        Region of interest [px]; ``Choice(None, ...)`` chooses the whole frame.
    truth : dict or None
        A simulator's ground truth (``ground_truth.json``'s document).
    """

    calibration: Choice[Calibration] | None = None
    threshold_p: Choice[int] | None = None
    roi: Choice[CircleROI | RectROI | None] | None = None
    truth: dict[str, Any] | None = None


@dataclass(frozen=True)
class Imaging:
    """The calibration, threshold and ROI that apply, each with its source.

    Attributes
    ----------
    calibration : Choice of Calibration or None
        None when no source has one.
    threshold_p : Choice of int or None
        None when no source has one.
    roi : Choice of (CircleROI or RectROI or None) or None
        None when no source sets one (the whole frame is counted).
    truth : dict or None
        The simulator's ground truth, when a source has one.
    """

    calibration: Choice[Calibration] | None
    threshold_p: Choice[int] | None
    roi: Choice[CircleROI | RectROI | None] | None
    truth: dict[str, Any] | None

    @property
    def roi_value(self) -> CircleROI | RectROI | None:
        """The ROI to count in (None: the whole frame)."""
        return None if self.roi is None else self.roi.value

    def need_calibration(self, message: str) -> Choice[Calibration]:
        """The calibration; :class:`ConfigError` with ``message`` when there is none."""
        if self.calibration is None:
            raise ConfigError(message)
        return self.calibration

    def need_threshold(self, message: str) -> Choice[int]:
        """The threshold; :class:`ConfigError` with ``message`` when there is none."""
        if self.threshold_p is None:
            raise ConfigError(message)
        return self.threshold_p


def _first(*choices: Choice[_T] | None) -> Choice[_T] | None:
    return next((c for c in choices if c is not None), None)


def choose_imaging(
    *,
    override: ImagingSource | None = None,
    config: ImagingSource | None = None,
    recorded: ImagingSource | None = None,
    scene: ImagingSource | None = None,
) -> Imaging:
    """Choose the calibration, threshold and ROI from the sources (module docstring).

    Parameters
    ----------
    override : ImagingSource, optional
        The command line (``--calibration``, ``--threshold``, ``--roi``).
    config : ImagingSource, optional
        The config's calibration file and ``imaging`` settings (:func:`settings_source`).
    recorded : ImagingSource, optional
        A stored session's manifest (:func:`recorded_source`).
    scene : ImagingSource, optional
        A simulated scene (:func:`scene_source`) or its ground truth (:func:`truth_source`).

    Returns
    -------
    Imaging
    """
    none = ImagingSource()
    o, c, r, s = (x if x is not None else none for x in (override, config, recorded, scene))
    calibration = _first(o.calibration, c.calibration, r.calibration, s.calibration)
    own = ImagingSource()
    if calibration is not None:
        cal, name = calibration.value, f"calibration ({calibration.source})"
        own = ImagingSource(
            threshold_p=None if cal.threshold_p is None else Choice(int(cal.threshold_p), name),
            roi=None if cal.roi is None else Choice(cal.roi, name),
        )
    return Imaging(
        calibration=calibration,
        threshold_p=_first(
            o.threshold_p, c.threshold_p, r.threshold_p, own.threshold_p, s.threshold_p
        ),
        roi=_first(o.roi, c.roi, r.roi, own.roi, s.roi),
        truth=next((x.truth for x in (o, c, r, s) if x.truth is not None), None),
    )


# --------------------------------------------------------------------------------------------
# Sources
# --------------------------------------------------------------------------------------------


def settings_source(imaging: ImagingSettings, calibration_path: Path | None) -> ImagingSource:
    """A config's source: its calibration file (loaded) and ``imaging`` settings."""
    return ImagingSource(
        calibration=None
        if calibration_path is None
        else Choice(load_calibration(calibration_path), str(calibration_path)),
        threshold_p=None
        if imaging.threshold_p is None
        else Choice(int(imaging.threshold_p), "config imaging.threshold_p"),
        roi=None if imaging.roi is None else Choice(imaging.roi, "config imaging.roi"),
    )


def scene_source(scene_path: str | Path, seed: int | None) -> ImagingSource:
    """A simulated scene's source, read through the registry (``"scene:imaging"``)."""
    calibration, threshold_p, roi, truth = registry.load("scene:imaging")(scene_path, seed)
    return ImagingSource(
        calibration=Choice(calibration, SIMULATED_SCENE),
        threshold_p=Choice(int(threshold_p), SIMULATED_SCENE),
        roi=Choice(roi, SIMULATED_SCENE),
        truth=truth,
    )


def roi_from_truth(truth: Mapping[str, Any] | None) -> CircleROI | None:
    """The waveguide disc a ground truth records (``roi``: ``cx_px``, ``cy_px``,
    ``radius_px``), or None when it has none readable."""
    r = None if truth is None else truth.get("roi")
    if not isinstance(r, dict):
        return None
    try:
        return CircleROI(
            kind="circle", cx_px=r["cx_px"], cy_px=r["cy_px"], radius_px=r["radius_px"]
        )
    except (KeyError, ValidationError):
        return None


def truth_source(truth: dict[str, Any], where: str, name: str) -> ImagingSource:
    """A simulator ground truth's source: its calibration, threshold and waveguide disc.

    Parameters
    ----------
    truth : dict
        The ground truth document.
    where : str
        Where it came from (prefix of calibration errors).
    name : str
        Source name of its calibration and threshold.
    """
    cal = truth.get("calibration")
    frame = truth.get("frame")
    p = frame.get("threshold_p") if isinstance(frame, dict) else None
    roi = roi_from_truth(truth)
    return ImagingSource(
        calibration=None
        if not isinstance(cal, dict)
        else Choice(calibration_from_mapping(cal, where), name),
        threshold_p=None if p is None else Choice(int(p), name),
        roi=None if roi is None else Choice(roi, "simulator ground truth"),
        truth=truth,
    )


def recorded_source(calibration: Mapping[str, Any], where: str) -> ImagingSource:
    """A stored session's source: the manifest's calibration record.

    The calibration is rebuilt with every field the analysis reads (valid ranges
    included, :func:`calibration_record`); its ``threshold_p`` and ``roi`` are the
    threshold and ROI the live run counted S_k with (a record without ``roi``, from
    before it was kept, says nothing about the ROI).
    """
    p = calibration.get("threshold_p")
    cal = calibration_from_mapping(calibration, where)
    return ImagingSource(
        calibration=Choice(cal, SESSION_MANIFEST),
        threshold_p=None if p is None else Choice(int(p), "session manifest calibration"),
        roi=Choice(cal.roi, "session manifest calibration") if "roi" in calibration else None,
    )


def calibration_record(
    calibration: Calibration,
    threshold_p: int,
    roi: CircleROI | RectROI | None,
    source: str,
    frame_size_px: tuple[int, int] | None = None,
) -> dict[str, Any]:
    """The manifest's calibration record of a live run.

    It holds every field :func:`recorded_source` reads back, the valid ranges included:
    the analysis flags results outside them ``calibration_extrapolated``, and
    ``analyze SESSION`` must flag what the live run flagged. Its ``frame_size_px`` is the
    size of the frames the session's S_k were counted in, as the camera reports it (None
    when it does not: never the calibration's own, which nothing then checked), so that
    ``analyze SESSION --calibration`` and ``calibrate`` from the session check it.

    Parameters
    ----------
    calibration : Calibration
        The calibration used.
    threshold_p : int
        The threshold S_k was counted with [8-bit intensity].
    roi : CircleROI or RectROI or None
        The ROI S_k was counted in [px] (None: the whole frame).
    source : str
        Where the calibration came from (a file or ``simulated scene``).
    frame_size_px : tuple of int, optional
        ``(width, height)`` of the camera's frames [px], when it says.
    """
    return {
        "alpha1_mm_per_px2": calibration.alpha1_mm_per_px2,
        "alpha2_mm_per_px": calibration.alpha2_mm_per_px,
        "c1_px": calibration.c1_px,
        "c2_px_per_n": calibration.c2_px_per_n,
        "indenter_length_mm": calibration.indenter_length_mm,
        "threshold_p": threshold_p,
        "s0_valid_range_px": _pair(calibration.s0_valid_range_px),
        "force_valid_range_n": _pair(calibration.force_valid_range_n),
        "roi": None if roi is None else roi.model_dump(),
        "frame_size_px": None if frame_size_px is None else [int(v) for v in frame_size_px],
        "source": source,
    }


def _pair(rng: tuple[float, float] | None) -> list[float] | None:
    return None if rng is None else [float(rng[0]), float(rng[1])]


# --------------------------------------------------------------------------------------------
# The ROI against the frame
# --------------------------------------------------------------------------------------------

#: Largest ROI bounding box measured pixel by pixel [px]; larger ones are judged by geometry.
_MAX_EXACT_ROI_PX = 16_000_000


def roi_placement(roi: CircleROI | RectROI, width_px: int, height_px: int) -> str:
    """``inside``, ``partly`` or ``outside`` the ``width_px`` x ``height_px`` frame."""
    if isinstance(roi, CircleROI):
        # Distance from the centre to the nearest pixel centre of the frame [px].
        dx = max(0.0 - roi.cx_px, 0.0, roi.cx_px - (width_px - 1))
        dy = max(0.0 - roi.cy_px, 0.0, roi.cy_px - (height_px - 1))
        if math.hypot(dx, dy) > roi.radius_px:
            return "outside"
        if (2.0 * roi.radius_px + 3.0) ** 2 > _MAX_EXACT_ROI_PX:
            # Wider than any frame measured exactly: it cannot lie within the frame.
            return "partly"
    else:
        x1, y1 = roi.x_px + roi.width_px, roi.y_px + roi.height_px
        if x1 <= 0 or y1 <= 0 or roi.x_px >= width_px or roi.y_px >= height_px:
            return "outside"
        inside = roi.x_px >= 0 and roi.y_px >= 0 and x1 <= width_px and y1 <= height_px
        return "inside" if inside else "partly"
    blank = np.zeros((height_px, width_px), dtype=np.uint8)
    flags = FrameProcessor((height_px, width_px), 128, roi).measure(blank).flags
    if Flag.EMPTY_ROI in flags:
        return "outside"
    return "partly" if Flag.ROI_CLIPPED in flags else "inside"


def roi_fit_problem(
    roi: CircleROI | RectROI | None, width_px: int, height_px: int, field: str
) -> str | None:
    """Why ``roi`` does not fit a ``width_px`` x ``height_px`` frame, or None when it does.

    Parameters
    ----------
    roi : CircleROI or RectROI or None
        The ROI [px] (None: the whole frame, which always fits).
    width_px, height_px : int
        The camera's frame size [px].
    field : str
        What set the ROI, for the message (``"field 'imaging.roi'"``, ``"--roi"``).

    Returns
    -------
    str or None
        One line, e.g. ``"field 'imaging.roi': circle centre (900, 100) r 200 px lies
        outside the 640x480 frame"``.
    """
    if roi is None:
        return None
    placement = roi_placement(roi, width_px, height_px)
    if placement == "inside":
        return None
    where = "outside" if placement == "outside" else "partly outside"
    why = (
        "every S_k would be 0"
        if placement == "outside"
        else "pixels beyond the border are not counted, so S_k and D_p would read low"
    )
    return (
        f"{field}: {describe_roi(roi)} lies {where} the {width_px}x{height_px} frame "
        f"({why}; the ROI must lie within the frame)"
    )


def check_roi_fits(
    roi: CircleROI | RectROI | None, width_px: int, height_px: int, field: str
) -> None:
    """Raise :class:`ConfigError` when ``roi`` does not fit the frame (:func:`roi_fit_problem`)."""
    problem = roi_fit_problem(roi, width_px, height_px, field)
    if problem is not None:
        raise ConfigError(problem)


# --------------------------------------------------------------------------------------------
# The daemon
# --------------------------------------------------------------------------------------------


def roi_field(config: DaemonConfig, calibration: Calibration) -> str:
    """What the daemon's ROI comes from, for messages: the config's field, else the
    calibration file's own ROI, else the simulated scene's (:func:`choose_imaging`)."""
    if config.imaging.roi is not None:
        return "field 'imaging.roi'"
    if calibration.roi is not None and config.calibration is not None:
        return f"field 'roi' of the calibration ({config.calibration})"
    return "the scene's ROI"


def resolve_imaging(
    config: DaemonConfig,
) -> tuple[Calibration, int, CircleROI | RectROI | None, dict[str, Any] | None]:
    """Calibration, threshold p, ROI and (for simulated devices) the scene's ground truth.

    The config's calibration file and ``imaging`` settings win over a simulated camera's
    scene (:func:`choose_imaging`).

    Raises
    ------
    ConfigError
        No calibration (a real camera needs a calibration file), no threshold, or a
        threshold or ROI other than the one the calibration was made with.
    """
    scene_path = getattr(config.camera, "scene", None)
    imaging = choose_imaging(
        config=settings_source(config.imaging, config.calibration),
        scene=None
        if scene_path is None
        else scene_source(scene_path, getattr(config.camera, "seed", None)),
    )
    calibration = imaging.need_calibration(
        "field 'calibration': a calibration file is required with a real camera "
        "(run `stipi-daemon calibrate`)"
    )
    p = imaging.need_threshold(
        "field 'imaging.threshold_p': no threshold given and the calibration has none"
    )
    own = calibration.value.threshold_p
    if own is not None and p.value != own:
        raise ConfigError(
            f"field 'imaging.threshold_p': {p.value} differs from the threshold p {own} the "
            f"calibration ({calibration.source}) was made with: S_k counted with another p "
            "does not compare with its S values, so D_p and F_r (Eqs. 4-5) would be wrong; "
            f"leave imaging.threshold_p out to count with {own}, or calibrate with p {p.value}"
        )
    roi = imaging.roi_value
    problem = calibration.value.roi_problem(roi, roi_field(config, calibration.value))
    if problem is not None:
        raise ConfigError(
            f"{problem} ({calibration.source}); leave imaging.roi out to count in the "
            "calibration's ROI, or calibrate in this one"
        )
    return calibration.value, p.value, roi, imaging.truth
