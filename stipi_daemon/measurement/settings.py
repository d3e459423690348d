"""Settings of one STIP-I measurement: the thresholds and durations of Section IV.B.

This module owns :class:`MeasurementConfig`, the immutable, validated settings the pit/release
state machine (:mod:`~stipi_daemon.measurement.state_machine`) reads: the pitting force band,
the pitting and recovery durations, the release detection, the settling stop and the
watchdog limits. It does not own how they are applied (the machine's policies, described in
its module docstring) nor where they come from (the daemon's configuration file).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = ["MeasurementConfig"]


class MeasurementConfig(BaseModel):
    """Thresholds and durations of one measurement (Section IV.B); immutable.

    Parameters
    ----------
    target_force_n : float
        Pitting force to hold [N] (paper: 16 N).
    force_tolerance_n : float
        Half-width of the accepted force band [N] (paper: 1.5 N).
    contact_force_n : float
        Force above which the probe counts as touching the tissue [N].
    pitting_duration_s : float
        Pitting time from the first in-band sample [s] (paper: 15 s).
    out_of_band_grace_s : float
        Longest *continuous* excursion outside the band that is tolerated [s].
    out_of_band_limit_s : float
        Largest *cumulative* out-of-band time during pitting that is tolerated [s].
    release_force_n : float
        Force below which the indenter counts as released [N].
    release_debounce_s : float
        Time the force must stay below ``release_force_n`` to detect release [s].
    release_overrun_warn_s : float
        Time in RELEASE after which an over-pitting advisory is issued once [s].
    recovery_max_s : float
        Longest recovery observed after T_0 [s] (paper: 105 s).
    recovery_end_slack_s : float
        A session whose sources end (a video file, a simulated scene) at most this long
        before the recovery window's end has watched the window: it is analysed over what
        was recorded instead of aborted [s]. A recording of "15 s, release, 105 s" ends
        within a frame or a force sample of T_0 + 105 s, on either side.
    stop_when_settled : bool
        End the recovery once S_k has settled (see the state machine's module docstring),
        else always after ``recovery_max_s``.
    settle_fraction : float
        Relative band of the settling test, as in T_s at 98 % of S_max (Eq. (6)) [1]; must
        equal the analysis' ``settle_fraction`` (checked by the daemon's config).
    settle_hold_s : float
        Shortest time S_k must stay inside the settling band before the recovery may end
        early [s].
    settle_bias_fraction : float
        Largest relative bias of T_r (Eq. (6)) an early end may cause on a Kelvin-Voigt
        recovery, in (0, 0.1] [1]; sets how long the recording continues after the plateau
        starts (about 0.7 time constants more per halving).
    link_loss_limit_s : float
        Time the force link may be down before the phase's policy applies [s].
    camera_stall_limit_s : float
        Time the camera may deliver no frame before the phase's policy applies [s].
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    target_force_n: float = Field(16.0, gt=0.0, allow_inf_nan=False)
    force_tolerance_n: float = Field(1.5, gt=0.0, allow_inf_nan=False)
    contact_force_n: float = Field(2.0, gt=0.0, allow_inf_nan=False)
    pitting_duration_s: float = Field(15.0, gt=0.0, allow_inf_nan=False)
    out_of_band_grace_s: float = Field(1.0, ge=0.0, allow_inf_nan=False)
    out_of_band_limit_s: float = Field(3.0, ge=0.0, allow_inf_nan=False)
    release_force_n: float = Field(8.0, gt=0.0, allow_inf_nan=False)
    release_debounce_s: float = Field(0.1, ge=0.0, allow_inf_nan=False)
    release_overrun_warn_s: float = Field(3.0, gt=0.0, allow_inf_nan=False)
    recovery_max_s: float = Field(105.0, gt=0.0, allow_inf_nan=False)
    recovery_end_slack_s: float = Field(1.0, ge=0.0, allow_inf_nan=False)
    stop_when_settled: bool = True
    settle_fraction: float = Field(0.98, gt=0.0, lt=1.0, allow_inf_nan=False)
    settle_hold_s: float = Field(10.0, gt=0.0, allow_inf_nan=False)
    settle_bias_fraction: float = Field(0.005, gt=0.0, le=0.1, allow_inf_nan=False)
    link_loss_limit_s: float = Field(2.0, gt=0.0, allow_inf_nan=False)
    camera_stall_limit_s: float = Field(1.0, gt=0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _check_consistency(self) -> MeasurementConfig:
        low = self.band_low_n
        if low <= 0.0:
            raise ValueError(
                f"force_tolerance_n ({self.force_tolerance_n} N) must be below "
                f"target_force_n ({self.target_force_n} N)"
            )
        if self.contact_force_n >= low:
            raise ValueError(
                f"contact_force_n ({self.contact_force_n} N) must be below the band's lower "
                f"edge target_force_n - force_tolerance_n ({low} N)"
            )
        if self.release_force_n >= low:
            raise ValueError(
                f"release_force_n ({self.release_force_n} N) must be below the band's lower "
                f"edge target_force_n - force_tolerance_n ({low} N)"
            )
        if self.settle_hold_s >= self.recovery_max_s:
            raise ValueError(
                f"settle_hold_s ({self.settle_hold_s} s) must be shorter than "
                f"recovery_max_s ({self.recovery_max_s} s)"
            )
        return self

    @property
    def band_low_n(self) -> float:
        """Lower edge of the force band [N]."""
        return self.target_force_n - self.force_tolerance_n

    @property
    def band_high_n(self) -> float:
        """Upper edge of the force band [N]."""
        return self.target_force_n + self.force_tolerance_n
