"""Live processing of one measurement: events in, phases, live parameters and results out.

:class:`MeasurementPipeline` is the pure heart of a recording. The shell (the daemon, the
demo, the offline ``analyze`` replay) feeds it force samples and frame S_k values on one
clock (host seconds). It keeps the series, drives the pit/release state machine
(:mod:`~stipi_daemon.measurement.state_machine`), computes live pitting parameters while
the tissue recovers and, when the machine asks for it, runs the whole-measurement
analysis (:func:`~stipi_daemon.analysis.results.analyze_recovery`). It does no I/O
and reads no clock: the same inputs give the same outputs, live or replayed.

T_0 (Eq. 6) comes from what was observed, never from a timer: the release the state
machine reports (the force's downward crossing of the release threshold, interpolated
between samples, or the operator's confirmation), read on the S_k series by
:func:`~stipi_daemon.measurement.release.observe_release`: S_0 is the frame that shows the
release (the image jump when it lies within a bound of the force drop), never a value
interpolated across it, and T_0 is that frame's time. A release whose frames were lost
leaves S_0 "not observed" (:attr:`MeasurementPipeline.release`), which the validity rules
turn into an invalid D_p. F_a (Eq. 7) averages the hold up to the last in-band force
sample before the force drop.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.image_quality import FrameLevels, FramePictures
from stipi_daemon.analysis.pitting import compute_pitting_parameters
from stipi_daemon.analysis.recovery_fit import fit_recovery
from stipi_daemon.analysis.results import (
    AnalysisSettings,
    MeasurementResult,
    analyze_recovery,
    applied_force_n_from_samples,
    force_at_rail_fraction,
)
from stipi_daemon.analysis.severity import SeverityReference
from stipi_daemon.analysis.vpr import elasticity_kpa, viscosity_n_s_per_mm2
from stipi_daemon.errors import AnalysisError
from stipi_daemon.measurement.events import (
    AnalysisDone,
    Arm,
    Event,
    ForceSample,
    FrameSample,
    Tick,
)
from stipi_daemon.measurement.outputs import Output, Phase, StartAnalysis
from stipi_daemon.measurement.release import ReleaseObservation, observe_release
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.measurement.state_machine import MachineState, close, initial_state, transition

__all__ = ["LiveInputs", "LiveParameters", "MeasurementPipeline", "compute_live"]

#: Minimum recovery observed before a live time-constant fit is attempted [s].
LIVE_FIT_MIN_S = 2.0


@dataclass(frozen=True)
class LiveParameters:
    """Parameters as known so far during the recovery (all may still change).

    Attributes
    ----------
    t_s : float
        Time of the newest frame used [s].
    elapsed_s : float
        Recovery observed so far, since T_0 [s].
    depth_mm, rebound_force_n : float
        D_p (Eq. 3) and F_r so far (Eq. 5, from the largest S_k so far).
    recovery_time_s : float or None
        T_r (Eq. 6); a lower bound while ``settled`` is False.
    settled : bool
        Whether S_k has reached 98 % of its maximum so far (and stayed).
    elasticity_kpa : float or None
        E (Eq. 7) from the measured hold force.
    tau_s, tau_se_s : float or None
        Fitted Kelvin-Voigt time constant and its standard error [s].
    viscosity_n_s_per_mm2 : float or None
        The paper's viscosity eta = E * T_r (Eq. 8) [N*s/mm^2]; a lower bound while
        ``settled`` is False (as T_r is).
    viscosity_from_time_constant_n_s_per_mm2 : float or None
        eta_tau = E * tau, from the fitted Kelvin-Voigt tau [N*s/mm^2] (another quantity
        than eta: a single exponential reaches 98 % at T_r = 3.9 tau).
    """

    t_s: float
    elapsed_s: float
    depth_mm: float
    rebound_force_n: float
    recovery_time_s: float | None
    settled: bool
    elasticity_kpa: float | None
    tau_s: float | None
    tau_se_s: float | None
    viscosity_n_s_per_mm2: float | None
    viscosity_from_time_constant_n_s_per_mm2: float | None = None

    def to_dict(self) -> dict[str, float | None]:
        """Flat numeric mapping with units in the keys, for storage (``settled``: 1 or 0)."""
        return {
            "elapsed_s": self.elapsed_s,
            "depth_mm": self.depth_mm,
            "rebound_force_n": self.rebound_force_n,
            "recovery_time_s": self.recovery_time_s,
            "settled": 1.0 if self.settled else 0.0,
            "elasticity_kpa": self.elasticity_kpa,
            "tau_s": self.tau_s,
            "tau_se_s": self.tau_se_s,
            "viscosity_n_s_per_mm2": self.viscosity_n_s_per_mm2,
            "viscosity_from_time_constant_n_s_per_mm2": (
                self.viscosity_from_time_constant_n_s_per_mm2
            ),
        }


@dataclass
class _Series:
    """A time series, appended in time order; :meth:`arrays` costs one copy of the points
    added since its previous call (the live parameters ask for it every second)."""

    t: list[float] = field(default_factory=list)
    v: list[float] = field(default_factory=list)
    _buf: np.ndarray = field(default_factory=lambda: np.empty((2, 0)), repr=False)
    _n: int = 0

    def append(self, t_s: float, value: float) -> None:
        self.t.append(t_s)
        self.v.append(value)

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Times and values as float64 arrays (read-only views, valid after more appends)."""
        n = len(self.t)
        if n > self._buf.shape[1]:
            grown = np.empty((2, max(n, 2 * self._buf.shape[1], 1024)), dtype=np.float64)
            grown[:, : self._n] = self._buf[:, : self._n]
            self._buf = grown
        if n > self._n:
            self._buf[0, self._n : n] = self.t[self._n : n]
            self._buf[1, self._n : n] = self.v[self._n : n]
            self._n = n
        t, v = self._buf[0, :n], self._buf[1, :n]
        t.flags.writeable = False
        v.flags.writeable = False
        return t, v


class MeasurementPipeline:
    """One measurement's live processing (pure; see the module docstring).

    Parameters
    ----------
    measurement : MeasurementConfig
        State-machine thresholds (force band, durations, limits).
    analysis : AnalysisSettings
        Analysis settings (indenter radius, window, F_a override).
    calibration : Calibration
        Eqs. (4)-(5) in the pixel units of the S_k values fed in.
    reference : SeverityReference
        Reference grades for the severity classification.
    t_start_s : float
        Time the pipeline starts [s] (host clock).
    t0_refine_s : float
        How far around the reported release the image jump is looked for [s]
        (:func:`~stipi_daemon.measurement.release.observe_release`; also the bound of an
        operator-confirmed release).
    """

    def __init__(
        self,
        *,
        measurement: MeasurementConfig,
        analysis: AnalysisSettings,
        calibration: Calibration,
        reference: SeverityReference,
        t_start_s: float = 0.0,
        t0_refine_s: float = 0.5,
    ) -> None:
        self.config = measurement
        self.analysis = analysis
        self.calibration = calibration
        self.reference = reference
        self.t0_refine_s = t0_refine_s
        self.state: MachineState = initial_state(t_start_s)
        self._force = _Series()
        self._frames = _Series()
        #: The state machine's request to analyse, once it came.
        self.start: StartAnalysis | None = None
        #: T_0 used by the analysis [s] (the frame that shows the release), once known.
        self.t0_s: float | None = None
        #: The final result, once analysed (None also when the analysis failed).
        self.result: MeasurementResult | None = None
        #: Why the analysis failed, if it did.
        self.analysis_error: str | None = None
        #: Notes about how the result was obtained.
        self.notes: list[str] = []
        #: How T_0 and S_0 were observed, once the analysis ran (facts for the validity).
        self.release: ReleaseObservation | None = None
        #: Frames whose S_k was not finite (fed as time only, see :meth:`frame`).
        self.unmeasurable_frames = 0
        #: The threshold p, the ROI's pixel count [px] and the saturation limit [-] of the
        #: frames' picture statistics (:meth:`picture`); None: the picture is not judged.
        self.picture_setup: tuple[int, int, float] | None = None
        #: The load cell's full scale and one count [N] (None: unknown, not judged).
        self.force_full_scale_n: tuple[float, float] | None = None
        self._levels: dict[float, FrameLevels] = {}
        self._live_t0: float | None = None
        #: Called with the latest session time [s] the measurement can still end at, each
        #: time that becomes known: the recovery window's end at the release
        #: (``recovery_max_s`` after it), then the end the analysis starts at, before it
        #: runs. The daemon stores no frame captured after it. None: nobody is told.
        self.on_end_known: Callable[[float], None] | None = None

    # ------------------------------------------------------------------ feeding

    @property
    def phase(self) -> Phase:
        """Current phase of the state machine."""
        return self.state.phase

    @property
    def finished(self) -> bool:
        """Whether the machine reached a terminal phase (DONE or a fault)."""
        return self.state.phase in (
            Phase.DONE,
            Phase.LINK_LOST,
            Phase.CAMERA_STALLED,
            Phase.FORCE_OUT_OF_BAND,
            Phase.ABORTED,
        )

    def feed(self, event: Event) -> list[Output]:
        """Apply one event; runs the analysis when the machine asks for it.

        Force samples and frames are recorded (in time order; older ones are dropped by
        the machine and not recorded) before the transition, so that the analysis sees
        every sample up to the event that ended the recovery.
        """
        if isinstance(event, ForceSample):
            if not self._force.t or event.t_s > self._force.t[-1]:
                self._force.append(event.t_s, event.force_n)
        elif isinstance(event, FrameSample):
            if not self._frames.t or event.t_s > self._frames.t[-1]:
                self._frames.append(event.t_s, event.s_k)
        released_s = self.state.t_release_s
        self.state, outputs = transition(self.state, event, self.config)
        t_rel = self.state.t_release_s
        if t_rel is not None and t_rel != released_s and self.on_end_known is not None:
            # the recovery window (RECOVERY's timer rule) ends recovery_max_s after it
            self.on_end_known(t_rel + self.config.recovery_max_s)
        return self._run_requested_analysis(outputs)

    def arm(self, t_s: float) -> list[Output]:
        """Arm the measurement (wait for contact)."""
        return self.feed(Arm(t_s))

    def force(self, t_s: float, force_n: float) -> list[Output]:
        """Feed one force sample [s, N]."""
        return self.feed(ForceSample(t_s, force_n))

    def frame(self, t_s: float, s_k: float) -> list[Output]:
        """Feed one frame's S_k [s, px]; an unmeasurable frame (S_k not finite) is counted
        in :attr:`unmeasurable_frames` and only brings the time forward: like a lost frame,
        it is no observation (S_0 is never interpolated across it)."""
        if not math.isfinite(s_k):
            self.unmeasurable_frames += 1
            return self.feed(Tick(t_s))
        return self.feed(FrameSample(t_s, s_k))

    def picture(self, t_s: float, levels: FrameLevels) -> None:
        """Record the picture statistics of the frame at ``t_s`` [s] (fed with
        :meth:`frame`; any subset of the frames, e.g. one in n); the analysis judges the
        image quality on them when :attr:`picture_setup` is set."""
        self._levels[t_s] = levels

    def _pictures(
        self, t: np.ndarray, t_pit_start_s: float, hold_end_s: float
    ) -> FramePictures | None:
        """The picture statistics of the analysed span of frames ``t`` [s], if any."""
        if self.picture_setup is None or t.size == 0:
            return None
        lo, hi = float(t[0]), float(t[-1])
        times = sorted(x for x in self._levels if lo <= x <= hi)
        if not times:
            return None
        p, roi_px, limit = self.picture_setup
        return FramePictures(
            times_s=tuple(times),
            levels=tuple(self._levels[x] for x in times),
            p=p,
            roi_pixel_count=roi_px,
            saturation_limit=limit,
            hold_s=(t_pit_start_s, hold_end_s),
        )

    def close(self, t_s: float) -> list[Output]:
        """Close the session at ``t_s`` [s]: any non-terminal phase ends.

        A recording that ends with the recovery window (at most ``recovery_end_slack_s``
        before its end, or after it) has watched what the protocol asks for: the window
        is completed first (the recovery is analysed and the measurement ends DONE), then
        ``state_machine.close`` ends whatever is left (a fault phase for an earlier end).
        """
        out: list[Output] = []
        t_rel = self.state.t_release_s
        if self.state.phase is Phase.RECOVERY and t_rel is not None:
            t_window_end = t_rel + self.config.recovery_max_s
            now = max(t_s, self.state.now_s)
            if t_window_end - now <= self.config.recovery_end_slack_s:
                if now < t_window_end:
                    self.notes.append(
                        f"the recording ended {t_window_end - now:.3f} s before the recovery "
                        f"window's end ({self.config.recovery_max_s:g} s after T_0): window "
                        "taken as complete"
                    )
                out += self.feed(Tick(max(now, t_window_end)))
        self.state, outputs = close(self.state, t_s, self.config)
        return out + self._run_requested_analysis(outputs)

    def _run_requested_analysis(self, outputs: list[Output]) -> list[Output]:
        """``outputs``, each :class:`StartAnalysis` followed by what the analysis emitted."""
        out = list(outputs)
        for o in outputs:
            if isinstance(o, StartAnalysis):
                if self.on_end_known is not None:
                    self.on_end_known(o.t_end_s)
                out.extend(self._analyse(o))
        return out

    # ------------------------------------------------------------------ results

    def _observe_release(self, t_release_s: float, *, note: bool = True) -> ReleaseObservation:
        """T_0 and the S_0 frame for the reported release (module docstring); notes it."""
        t, s = self._frames.arrays()
        ft, _ = self._force.arrays()
        source: Literal["force", "operator"] = (
            "operator" if self.state.release_by == "operator" else "force"
        )
        obs = observe_release(
            t, s, ft, t_release_s, source=source, search_s=max(self.t0_refine_s, 1e-9)
        )
        if note and obs.t0_s != t_release_s:
            self.notes.append(
                f"T_0 at the frame that shows the release, {obs.t0_s:.3f} s "
                f"({obs.t0_s - t_release_s:+.3f} s from the {source} release {t_release_s:.3f} s)"
            )
        if note and obs.reason is not None:
            self.notes.append(obs.reason)
        return obs

    def _hold_end_s(self, t_pit_start_s: float, t_pit_end_s: float | None, t0_s: float) -> float:
        """End of the pitting hold for F_a [s]: the last force sample in the band (at or
        above its lower edge) before the release, within the pitting interval; the
        rebound and the operator's letting go are not the applied force of Eq. (7)."""
        end = t0_s if t_pit_end_s is None else min(t_pit_end_s, t0_s)
        rel = self.state.t_release_s
        if rel is None or self.state.release_by != "force":
            return end
        ft, fv = self._force.arrays()
        held = np.flatnonzero((ft >= t_pit_start_s) & (ft <= rel) & (fv >= self.config.band_low_n))
        return min(end, float(ft[held[-1]])) if held.size else end

    def analyse_recording(
        self,
        t_release_s: float,
        t_pit_start_s: float,
        t_pit_end_s: float | None,
        t_end_s: float | None = None,
    ) -> tuple[MeasurementResult | None, str | None, float]:
        """Analyse the recorded recovery: T_0 and S_0 as observed, F_a, then every result.

        The step the machine's :class:`StartAnalysis` runs; also usable on a recovery the
        recording cut short (``t_end_s=None``: every frame recorded). Notes on T_0 go to
        :attr:`notes` and how it was observed to :attr:`release`; the pipeline's own
        result is not changed.

        Returns
        -------
        tuple
            The result (None when the analysis failed), why it failed, and T_0 [s].
        """
        self.release = self._observe_release(t_release_s)
        t0 = self.release.t0_s
        end = self._hold_end_s(t_pit_start_s, t_pit_end_s, min(t0, t_release_s))
        try:
            rail = 0.0
            if self.analysis.applied_force_n is not None:
                f_a = self.analysis.applied_force_n
            else:
                ft, fv = self._force.arrays()
                f_a = applied_force_n_from_samples(ft, fv, t_pit_start_s, end)
                if self.force_full_scale_n is not None:
                    rail = force_at_rail_fraction(
                        ft, fv, t_pit_start_s, end, *self.force_full_scale_n
                    )
            t, s = self._frames.arrays()
            if t_end_s is not None:
                sel = t <= t_end_s
                t, s = t[sel], s[sel]
            result = analyze_recovery(
                t,
                s,
                t0,
                self.calibration,
                f_a,
                self.analysis,
                self.reference,
                pictures=self._pictures(t, t_pit_start_s, end),
                force_rail_fraction=rail,
            )
        except AnalysisError as exc:
            return None, str(exc), t0
        return result, None, t0

    def _analyse(self, start: StartAnalysis) -> list[Output]:
        self.start = start
        self.result, self.analysis_error, self.t0_s = self.analyse_recording(
            start.t0_s, start.t_pit_start_s, start.t_pit_end_s, start.t_end_s
        )
        self.state, outputs = transition(self.state, AnalysisDone(self.state.now_s), self.config)
        return list(outputs)

    def force_series(self) -> tuple[np.ndarray, np.ndarray]:
        """Recorded force samples: times [s] and forces [N]."""
        return self._force.arrays()

    def frame_series(self) -> tuple[np.ndarray, np.ndarray]:
        """Recorded frames: times [s] and S_k [px]."""
        return self._frames.arrays()

    def live(self) -> LiveParameters | None:
        """Live parameters during (and after) the recovery; None before the release.

        Costs one pass over the recovery series (and one fit once at least
        :data:`LIVE_FIT_MIN_S` of recovery is recorded): call it at display rate, not per
        frame. Equal to ``compute_live(self.live_inputs())``.
        """
        inputs = self.live_inputs()
        return None if inputs is None else compute_live(inputs)

    def live_inputs(self) -> LiveInputs | None:
        """What :func:`compute_live` needs, taken now (cheap: views of the series, no copy);
        None before the release or before a frame after it.

        The snapshot stays valid while more samples and frames are fed, so that the
        computation can run on another thread (the daemon's live fit, off its event loop).
        """
        t_rel = self.state.t_release_s
        if t_rel is None:
            return None
        t, s = self._frames.arrays()
        if t.size < 2 or t[-1] <= t_rel:
            return None
        if self.t0_s is None and self._live_t0 is None and t[-1] > t_rel + self.t0_refine_s:
            self._live_t0 = self._observe_release(t_rel, note=False).t0_s
        t0 = self.t0_s if self.t0_s is not None else (self._live_t0 or t_rel)
        ft, fv = self._force.arrays()
        pit_start, pit_end = self.state.t_pit_start_s, self.state.t_pit_end_s
        hold_end = None
        if pit_start is not None and pit_end is not None:
            hold_end = self._hold_end_s(pit_start, pit_end, t_rel)
        return LiveInputs(t, s, t0, self.calibration, self.analysis, ft, fv, pit_start, hold_end)


@dataclass(frozen=True)
class LiveInputs:
    """A snapshot of what the live parameters are computed from
    (:meth:`MeasurementPipeline.live_inputs`): read-only arrays that later samples do not
    change."""

    t: np.ndarray  #: frame times [s]
    s: np.ndarray  #: frame S_k [px]
    t0_s: float  #: T_0 used so far [s]
    calibration: Calibration
    analysis: AnalysisSettings
    force_t: np.ndarray  #: force sample times [s]
    force_n: np.ndarray  #: forces [N]
    pit_start_s: float | None  #: start of the pitting hold [s], once known
    hold_end_s: float | None  #: end of the hold for F_a [s], once the pitting ended


def compute_live(inputs: LiveInputs) -> LiveParameters | None:
    """Live parameters from a snapshot (pure; numpy and scipy do the work, so that it can
    run on a worker thread beside the event loop); None while they cannot be computed."""
    t, s, t0 = inputs.t, inputs.s, inputs.t0_s
    analysis = inputs.analysis
    elapsed = float(t[-1] - t0)
    try:
        params = compute_pitting_parameters(
            t,
            s,
            t0,
            inputs.calibration,
            settle_fraction=analysis.settle_fraction,
            window_s=max(elapsed, 1e-9),
            persist_frames=analysis.persist_frames,
            end_slope_fraction=0.0,
        )
    except AnalysisError:
        return None
    e_kpa: float | None = None
    pit_start, hold_end = inputs.pit_start_s, inputs.hold_end_s
    if pit_start is not None and hold_end is not None and params.depth_mm > 0.0:
        try:
            f_a = analysis.applied_force_n or applied_force_n_from_samples(
                inputs.force_t, inputs.force_n, pit_start, hold_end
            )
            e_kpa = elasticity_kpa(f_a, params.depth_mm, analysis.indenter_radius_mm)
        except AnalysisError:
            e_kpa = None
    tau = tau_se = eta_tau = eta = None
    if e_kpa is not None and params.recovery_time_s is not None:
        try:
            eta = viscosity_n_s_per_mm2(e_kpa, params.recovery_time_s)
        except AnalysisError:
            eta = None
    if elapsed >= LIVE_FIT_MIN_S:
        fit = fit_recovery(t, s, t0, elapsed)
        tau, tau_se = fit.tau_s, fit.tau_se_s
        if tau is not None and e_kpa is not None and math.isfinite(tau):
            try:
                eta_tau = fit.viscosity_n_s_per_mm2(e_kpa)
            except AnalysisError:
                eta_tau = None
    return LiveParameters(
        t_s=float(t[-1]),
        elapsed_s=elapsed,
        depth_mm=params.depth_mm,
        rebound_force_n=params.rebound_force_n,
        recovery_time_s=params.recovery_time_s,
        settled=Flag.NOT_SETTLED not in params.flags and Flag.NO_RECOVERY not in params.flags,
        elasticity_kpa=e_kpa,
        tau_s=tau,
        tau_se_s=tau_se,
        viscosity_n_s_per_mm2=eta,
        viscosity_from_time_constant_n_s_per_mm2=eta_tau,
    )
