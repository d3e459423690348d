"""Offline analysis: replay a recorded measurement through a fresh live pipeline.

This module owns the pure part of ``stipi-daemon analyze``: a :class:`Recording` (frame
times and S_k, force samples, the arm time) is fed in time order through a new
:class:`~stipi_daemon.measurement.pipeline.MeasurementPipeline`, exactly as the live shell
feeds it (force before frame at equal times, stop as soon as the machine reaches a
terminal phase, close the session otherwise), so the same inputs give the same numbers as
the live run. A recording that ends during the recovery (an interrupted session) can be
analysed over the recovery that was kept (:func:`replay` with ``partial_recovery=True``,
flagged and noted). The outcome gives its results in the layout of the live
``summary.json`` (:meth:`ReplayOutcome.summary`); :func:`calibration_from_mapping` rebuilds
the calibration a manifest or a ground truth records. It does no I/O: reading sessions,
CSV files and videos is :mod:`stipi_daemon.app.offline_io`'s job; comparing with a stored
summary or a simulator's ground truth is :mod:`stipi_daemon.analysis.summary_diff`'s and
:mod:`stipi_daemon.analysis.truth_comparison`'s; the orchestration, the output document
and writing it are :mod:`stipi_daemon.app.analyze`'s.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, RectROI, roi_from_record
from stipi_daemon.analysis.results import AnalysisSettings, MeasurementResult
from stipi_daemon.analysis.severity import SeverityReference
from stipi_daemon.analysis.validity import assess_validity
from stipi_daemon.errors import AnalysisError, CalibrationError
from stipi_daemon.measurement.pipeline import LiveParameters, MeasurementPipeline
from stipi_daemon.measurement.release import ReleaseObservation
from stipi_daemon.measurement.state_machine import (
    Arm,
    CameraRecovered,
    CameraStalled,
    Event,
    ForceSample,
    FrameSample,
    LinkLost,
    LinkRestored,
    MachineState,
    MeasurementConfig,
    Phase,
    PhaseChanged,
    StartAnalysis,
    Tick,
)

__all__ = [
    "Recording",
    "ReplayOutcome",
    "ReplaySetup",
    "calibration_from_mapping",
    "replay",
]

FloatArray = npt.NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------------------------


def _series(name: str, values: npt.ArrayLike) -> FloatArray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1:
        raise AnalysisError(f"{name} must be one-dimensional, got shape {arr.shape}")
    return arr


@dataclass(frozen=True)
class Recording:
    """The raw inputs of one measurement, on one clock (host or session seconds).

    Attributes
    ----------
    frame_times_s : numpy.ndarray
        Frame times [s], finite.
    s_k_px : numpy.ndarray
        S_k of those frames, Eq. (2) [px].
    force_times_s : numpy.ndarray
        Force sample times [s], finite.
    force_n : numpy.ndarray
        Forces [N]; non-finite samples (lost or invalid readings) are not fed.
    t_arm_s : float or None
        When the measurement was armed [s]; None arms at the first sample.
    link_events : tuple of Event
        Watchdog events the live shell fed (:class:`LinkLost`, :class:`LinkRestored`,
        :class:`CameraStalled`, :class:`CameraRecovered`), merged by time (after force
        samples, before frames at equal times).

    Raises
    ------
    AnalysisError
        Mismatched lengths, non-finite times, no frame at all.
    """

    frame_times_s: FloatArray
    s_k_px: FloatArray
    force_times_s: FloatArray
    force_n: FloatArray
    t_arm_s: float | None = None
    link_events: tuple[Event, ...] = ()

    def __post_init__(self) -> None:
        ft = _series("frame_times_s", self.frame_times_s)
        sk = _series("s_k_px", self.s_k_px)
        gt = _series("force_times_s", self.force_times_s)
        gf = _series("force_n", self.force_n)
        if ft.shape != sk.shape:
            raise AnalysisError(f"{ft.size} frame times but {sk.size} S_k values")
        if gt.shape != gf.shape:
            raise AnalysisError(f"{gt.size} force sample times but {gf.size} forces")
        if ft.size == 0:
            raise AnalysisError("the recording holds no frame: nothing to analyse")
        for name, t in (("frame", ft), ("force sample", gt)):
            bad = np.flatnonzero(~np.isfinite(t))
            if bad.size:
                raise AnalysisError(f"{name} {int(bad[0])} has a non-finite time {t[bad[0]]}")
        if self.t_arm_s is not None and not math.isfinite(self.t_arm_s):
            raise AnalysisError(f"arm time must be finite, got {self.t_arm_s}")
        for ev in self.link_events:
            if not isinstance(ev, LinkLost | LinkRestored | CameraStalled | CameraRecovered):
                raise AnalysisError(f"not a watchdog event: {ev!r}")
        object.__setattr__(self, "frame_times_s", ft)
        object.__setattr__(self, "s_k_px", sk)
        object.__setattr__(self, "force_times_s", gt)
        object.__setattr__(self, "force_n", gf)

    @property
    def first_time_s(self) -> float:
        """Earliest sample time [s]."""
        first = float(self.frame_times_s.min())
        if self.force_times_s.size:
            first = min(first, float(self.force_times_s.min()))
        return first

    @property
    def arm_time_s(self) -> float:
        """The arm time used: :attr:`t_arm_s`, or the first sample's time [s]."""
        return self.first_time_s if self.t_arm_s is None else float(self.t_arm_s)


@dataclass(frozen=True)
class ReplaySetup:
    """Everything besides the samples that decides the results.

    Attributes
    ----------
    measurement : MeasurementConfig
        State-machine thresholds.
    analysis : AnalysisSettings
        Analysis settings (radius, window, F_a override).
    calibration : Calibration
        Eqs. (4)-(5) in the pixel units of the S_k values.
    reference : SeverityReference
        Severity reference curves (Section IV.C).
    t0_refine_s : float
        How far around the release the pipeline looks for the image jump [s].
    live_interval_s : float or None
        Interval of the live-parameter updates after the release [s of recording time], as
        the live shell asks for them; None asks for none.
    force_full_scale_n : tuple of float or None
        The load cell's full scale and one count [N] (the probe's ADC, as the session
        recorded it; :func:`~stipi_daemon.analysis.results.force_full_scale_n`): hold
        samples there make F_a invalid. None: not judged.
    """

    measurement: MeasurementConfig
    analysis: AnalysisSettings
    calibration: Calibration
    reference: SeverityReference
    t0_refine_s: float = 0.5
    live_interval_s: float | None = 1.0
    force_full_scale_n: tuple[float, float] | None = None


def calibration_from_mapping(data: Mapping[str, Any], where: str) -> Calibration:
    """Rebuild the :class:`Calibration` a session's manifest or a ground truth records.

    Reads the coefficient keys of the calibration file (``alpha1_mm_per_px2``,
    ``alpha2_mm_per_px``, ``c1_px``, ``c2_px_per_n``, optional ``indenter_length_mm``,
    ``threshold_p``, ``s0_valid_range_px``, ``force_valid_range_n``, ``probe_id``,
    ``frame_size_px``, ``roi``); other keys (``source``, ``area_scale``...) are ignored. A
    manifest's ``roi`` is the ROI the live run counted S_k in, which the daemon refuses to
    differ from its calibration's (:meth:`Calibration.roi_problem`): read back as the
    calibration's ROI, S_k counted again in another ROI is flagged.

    Raises
    ------
    CalibrationError
        A coefficient is missing or invalid; the message starts with ``where``.
    """
    keys = ("alpha1_mm_per_px2", "alpha2_mm_per_px", "c1_px", "c2_px_per_n")
    missing = [k for k in keys if k not in data]
    if missing:
        raise CalibrationError(f"{where}: calibration lacks {', '.join(missing)}")

    def rng(key: str) -> tuple[float, float] | None:
        v = data.get(key)
        if v is None:
            return None
        if not isinstance(v, Sequence) or len(v) != 2:
            raise CalibrationError(f"{where}: field '{key}' must be a [low, high] pair, got {v!r}")
        return (float(v[0]), float(v[1]))

    try:
        return Calibration(
            alpha1_mm_per_px2=data["alpha1_mm_per_px2"],
            alpha2_mm_per_px=data["alpha2_mm_per_px"],
            c1_px=data["c1_px"],
            c2_px_per_n=data["c2_px_per_n"],
            indenter_length_mm=data.get("indenter_length_mm", 12.0),
            threshold_p=data.get("threshold_p"),
            s0_valid_range_px=rng("s0_valid_range_px"),
            force_valid_range_n=rng("force_valid_range_n"),
            probe_id=data.get("probe_id"),
            frame_size_px=_size(data.get("frame_size_px")),
            roi=_roi(data.get("roi")),
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{where}: {exc}") from None


def _size(value: Any) -> tuple[int, int] | None:
    """A recorded ``[width, height]`` as a tuple (the calibration checks its values)."""
    if value is None:
        return None
    if not isinstance(value, Sequence) or isinstance(value, str) or len(value) != 2:
        raise CalibrationError(f"field 'frame_size_px' must be [width, height], got {value!r}")
    return (value[0], value[1])


def _roi(value: Any) -> CircleROI | RectROI | None:
    """A recorded ROI (``{"kind": "circle", ...}``, as the config's ``imaging.roi``)."""
    try:
        return roi_from_record(value)
    except ValueError as exc:
        raise CalibrationError(f"field 'roi': {exc}") from None


# --------------------------------------------------------------------------------------------
# Replay
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReplayOutcome:
    """What a replay produced.

    Attributes
    ----------
    phase : Phase
        The state machine's final phase.
    end_reason : str or None
        Why the machine ended.
    start : StartAnalysis or None
        The analysis request (None when the machine never asked for one).
    t0_s : float or None
        T_0 used by the analysis [s] (the frame that shows the release).
    result : MeasurementResult or None
        The results (None when the analysis failed or never ran).
    analysis_error : str or None
        Why the analysis failed.
    pipeline_notes : tuple of str
        The pipeline's notes (how T_0 and S_0 were observed...).
    measurement_flags : tuple of str
        The state machine's flags, sorted.
    transitions : tuple of PhaseChanged
        Every phase change, in order.
    partial : bool
        True when the results come from a recovery cut short (the recording ended during
        the recovery and ``partial_recovery`` was asked for).
    notes : tuple of str
        How the replay went (samples skipped, samples after the end, partial recovery).
    frames_fed, force_samples_fed : int
        Samples fed to the pipeline.
    live : tuple of LiveParameters
        The live parameters as the live shell would have shown them.
    release : ReleaseObservation or None
        How T_0 and S_0 were observed (None when the analysis never ran).
    """

    phase: Phase
    end_reason: str | None
    start: StartAnalysis | None
    t0_s: float | None
    result: MeasurementResult | None
    analysis_error: str | None
    pipeline_notes: tuple[str, ...]
    measurement_flags: tuple[str, ...]
    transitions: tuple[PhaseChanged, ...]
    partial: bool
    notes: tuple[str, ...]
    frames_fed: int
    force_samples_fed: int
    live: tuple[LiveParameters, ...] = ()
    release: ReleaseObservation | None = None

    def summary(self) -> dict[str, Any]:
        """The results in the layout of the live ``summary.json`` (without ground truth).

        ``status`` is ``complete`` when the machine finished (DONE), ``partial`` for a
        partial-recovery analysis, ``fault`` otherwise.
        """
        start, rel = self.start, self.release
        if self.partial:
            status = "partial"
        else:
            status = "complete" if self.phase == Phase.DONE else "fault"
        return {
            "status": status,
            "phase": str(self.phase),
            "end_reason": self.end_reason,
            "measurement": None if start is None else asdict(start) | {"t0_refined_s": self.t0_s},
            "measurement_flags": list(self.measurement_flags),
            "results": None if self.result is None else self.result.to_dict(),
            "analysis_error": self.analysis_error,
            "notes": list(self.pipeline_notes),
            "release": None if self.release is None else self.release.to_dict(),
            **assess_validity(
                self.result,
                ended_done=self.phase == Phase.DONE and not self.partial,
                end_reason="partial recovery" if self.partial else self.end_reason,
                analysis_error=self.analysis_error,
                invalid_reasons=None if rel is None else rel.invalid_reasons(),
                caveats=None if rel is None else rel.caveats(),
                extra_flags=() if rel is None else rel.flags,
            ),
        }


@dataclass
class _Feed:
    events: list[Event] = field(default_factory=list)
    skipped_force: int = 0
    skipped_frames: int = 0


def _events(rec: Recording) -> _Feed:
    """Every input event in the order the live shell feeds them.

    Frames and force samples are merged by time, force first at equal times (the live
    shell drains every force sample at or before a frame's time before the frame). The
    arm event comes before every sample at or after the arm time. Non-finite forces are
    left out (counted); a frame whose S_k is not finite (unmeasurable) is fed as a
    :class:`Tick` at its time (counted).
    """
    feed = _Feed()
    ok = np.isfinite(rec.force_n)
    feed.skipped_force = int(np.count_nonzero(~ok))
    ft, fv = rec.force_times_s[ok], rec.force_n[ok]
    et = np.asarray([e.t_s for e in rec.link_events], dtype=np.float64)
    times = np.concatenate([ft, et, rec.frame_times_s])
    kinds = np.concatenate(
        [
            np.zeros(ft.size, np.int8),
            np.ones(et.size, np.int8),
            np.full(rec.frame_times_s.size, 2, np.int8),
        ]
    )
    index = np.concatenate(
        [np.arange(ft.size), np.arange(et.size), np.arange(rec.frame_times_s.size)]
    )
    # Sort by time, then kind (force, watchdog, frame), then original order (stable).
    order = np.lexsort((index, kinds, times))
    t_arm = rec.arm_time_s
    armed = False
    ft_l, fv_l = ft.tolist(), fv.tolist()
    st_l, sv_l = rec.frame_times_s.tolist(), rec.s_k_px.tolist()
    for k in order.tolist():
        t = float(times[k])
        if not armed and t >= t_arm:
            feed.events.append(Arm(t_arm))
            armed = True
        i = int(index[k])
        if kinds[k] == 0:
            feed.events.append(ForceSample(ft_l[i], fv_l[i]))
        elif kinds[k] == 1:
            feed.events.append(rec.link_events[i])
        elif math.isfinite(sv_l[i]):
            feed.events.append(FrameSample(st_l[i], sv_l[i]))
        else:
            # an unmeasurable frame is no observation: only its time is fed (as the live
            # shell's ticks); S_0 is never interpolated across it
            feed.events.append(Tick(st_l[i]))
            feed.skipped_frames += 1
    if not armed:
        feed.events.append(Arm(t_arm))
    return feed


def _partial_result(
    pipeline: MeasurementPipeline, state: MachineState
) -> tuple[MeasurementResult | None, str | None, float | None]:
    """Analyse a recovery that the recording cut short (the pipeline's own analysis step)."""
    t_rel, pit_start = state.t_release_s, state.t_pit_start_s
    if t_rel is None or pit_start is None:
        return None, f"the recording ends in phase {state.phase}: no recovery to analyse", None
    return pipeline.analyse_recording(t_rel, pit_start, state.t_pit_end_s)


def replay(rec: Recording, setup: ReplaySetup, *, partial_recovery: bool = False) -> ReplayOutcome:
    """Feed a recording through a fresh pipeline, as the live shell fed it.

    Parameters
    ----------
    rec : Recording
        The samples.
    setup : ReplaySetup
        Configuration, calibration and reference.
    partial_recovery : bool
        When the recording ends during the recovery (an interrupted session), analyse the
        recovery that was kept instead of reporting the session closed without results.
        Such results carry the flag ``not_settled`` when S_k had not settled, and
        :attr:`ReplayOutcome.partial` is True.

    Returns
    -------
    ReplayOutcome
    """
    pipeline = MeasurementPipeline(
        measurement=setup.measurement,
        analysis=setup.analysis,
        calibration=setup.calibration,
        reference=setup.reference,
        t_start_s=min(rec.arm_time_s, rec.first_time_s),
        t0_refine_s=setup.t0_refine_s,
    )
    pipeline.force_full_scale_n = setup.force_full_scale_n
    feed = _events(rec)
    notes: list[str] = []
    if feed.skipped_force:
        notes.append(f"{feed.skipped_force} force sample(s) without a finite value not fed")
    if feed.skipped_frames:
        notes.append(f"{feed.skipped_frames} frame(s) without a finite S_k fed as time only")
    transitions: list[PhaseChanged] = []
    frames_fed = force_fed = 0
    n_events = len(feed.events)
    used = 0
    live: list[LiveParameters] = []
    next_live = -math.inf
    for event in feed.events:
        used += 1
        if isinstance(event, FrameSample):
            frames_fed += 1
        elif isinstance(event, ForceSample):
            force_fed += 1
        transitions.extend(o for o in pipeline.feed(event) if isinstance(o, PhaseChanged))
        if pipeline.finished:
            break
        now = pipeline.state.now_s
        interval = setup.live_interval_s
        if interval is not None and now >= next_live and pipeline.state.t_release_s is not None:
            next_live = now + interval
            params = pipeline.live()
            if params is not None:
                live.append(params)
    if used < n_events:
        notes.append(
            f"the measurement ended at {pipeline.state.now_s:.3f} s; "
            f"{n_events - used} later sample(s) not used"
        )
    partial = False
    result, error, t0 = pipeline.result, pipeline.analysis_error, pipeline.t0_s
    pipeline_notes = list(pipeline.notes)
    if not pipeline.finished:
        before = pipeline.state
        transitions.extend(
            o for o in pipeline.close(pipeline.state.now_s) if isinstance(o, PhaseChanged)
        )
        result, error, t0 = pipeline.result, pipeline.analysis_error, pipeline.t0_s
        pipeline_notes = list(pipeline.notes)
        if pipeline.start is None and partial_recovery:
            if before.phase == Phase.RECOVERY:
                result, error, t0 = _partial_result(pipeline, before)
                pipeline_notes = list(pipeline.notes)
                partial = True
                kept = before.now_s - (t0 if t0 is not None else before.now_s)
                notes.append(
                    f"the recording ends {kept:.2f} s into the recovery (phase recovery): "
                    "analysed the recovery that was kept; the recovery window is incomplete"
                )
                if result is not None and Flag.NOT_SETTLED in result.flags:
                    notes.append("S_k had not settled when the recording ends: T_r is not final")
            else:
                notes.append(
                    f"the recording ends in phase {before.phase}, before any recovery: "
                    "nothing to analyse"
                )
                error = error or f"no recovery recorded (recording ends in phase {before.phase})"
    return ReplayOutcome(
        phase=pipeline.phase,
        end_reason=pipeline.state.end_reason,
        start=pipeline.start,
        t0_s=t0,
        result=result,
        analysis_error=error,
        pipeline_notes=tuple(pipeline_notes),
        measurement_flags=tuple(sorted(pipeline.state.flags)),
        transitions=tuple(transitions),
        partial=partial,
        notes=tuple(notes),
        frames_fed=frames_fed,
        force_samples_fed=force_fed,
        live=tuple(live),
        release=pipeline.release,
    )
