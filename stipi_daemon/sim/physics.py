"""Physics of a simulated measurement: pure functions of time for one scene.

This module owns the mechanical model behind a scene: the Kelvin-Voigt tissue under the
operator's force profile (pit creation), its recovery after the release pushing the
indenter into the PDMS tip (a spring in series, giving the rebound force) with the shape
of the scene's tissue model (:mod:`.tissue`; Kelvin-Voigt unless the scene names one), and the
probe's occluded area S(t) through the calibration of Eqs. (4)-(5), evaluated with
:class:`~stipi_daemon.analysis.calibration.Calibration` rather than re-implemented. Every
quantity is in closed form; nothing here draws random numbers, renders or does I/O.
Rendering is :mod:`.render`'s job, the ground-truth record :mod:`.truth`'s.

Model (docs/simulator.md has the derivation):

* Tissue stiffness from Eq. (7) inverted, k = pi^2 R E / 3 [N/mm], damping c = k tau.
* Before the release the applied force F_a(t) is piecewise linear (idle, ramp, hold) and
  the depth solves c_l D' + k D = F_a(t) exactly on each segment, c_l = k tau_load
  (tau_load = tau unless the scene sets a faster loading time constant).
* At T_0 the indenter is unlocked. S_0 encodes d_s = l - D_p through Eq. (4); the tip
  then carries the force F_0 = (S_0 - C1)/C2 (Eq. 5 at T_0, so S is continuous). The
  tissue pushes the indenter into the tip (stiffness k_p): c D' + k D = F, F = F_0 +
  k_p (D_p - D). Both D and F relax exponentially with tau_r = tau k / (k + k_p) and
  F(t) = F_inf - (F_inf - F_0) exp(-(t - T_0)/tau_r), F_inf = F_0 + k_p (k D_p - F_0)/(k + k_p).
* A scene with ``tissue.model`` keeps the pitting phase, F_0, F_inf and D_inf (they follow
  from E, k_p and the calibration) and replaces exp(-(t - T_0)/tau_r) by the model's
  recovery function remaining(t - T_0): F(t) = F_inf - (F_inf - F_0) remaining(t - T_0),
  and D likewise (:mod:`.tissue.base` says what a model describes).
* S(t) = C1 + C2 F(t) (Eq. 5) during the recovery; during the pitting phase either the
  tip carries the applied force (S = C1 + C2 F_a, ``applied_force``) or the locked
  indenter leaves the waveguide clear (S = 0, ``none``; the paper's Fig. 4 (a)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.scene import Scene
from stipi_daemon.sim.tissue.base import RecoveryModel
from stipi_daemon.sim.tissue.kelvin_voigt import KelvinVoigt, recovery_time_constant_s

__all__ = ["SceneModel", "scaled_calibration"]

FloatArray = NDArray[np.float64]


def scaled_calibration(scene: Scene) -> tuple[Calibration, float]:
    """The scene's calibration in the rendered resolution's pixel units.

    The waveguide image scales with the frame height; areas scale with r = (H / H_ref)^2:
    alpha1' = alpha1 / r^2, alpha2' = alpha2 / r, C1' = r C1, C2' = r C2. Its
    ``frame_size_px`` is the scene camera's frame size.

    Returns
    -------
    (Calibration, float)
        The scaled calibration and the area factor r [-].
    """
    cal = scene.probe.calibration
    r = (scene.camera.height / cal.reference_resolution[1]) ** 2
    return (
        Calibration(
            alpha1_mm_per_px2=cal.alpha1_mm_per_px2 / r**2,
            alpha2_mm_per_px=cal.alpha2_mm_per_px / r,
            c1_px=cal.c1_px * r,
            c2_px_per_n=cal.c2_px_per_n * r,
            indenter_length_mm=scene.indenter.length_mm,
            threshold_p=scene.probe.threshold,
            frame_size_px=(scene.camera.width, scene.camera.height),
        ),
        r,
    )


@dataclass(frozen=True)
class _Segment:
    t_start_s: float
    force_start_n: float
    slope_n_per_s: float
    depth_start_mm: float


class SceneModel:
    """Closed-form mechanics of one scene at its camera resolution.

    Parameters
    ----------
    scene : Scene
        The scene; its tissue, indenter, force profile, probe and camera are used.

    Raises
    ------
    ConfigError
        The scene is inconsistent: the pit is deeper than the indenter, Eq. (4) cannot
        encode the depth change, or S_0 lies below C1 (negative tip force at T_0).
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        fp = scene.force_profile
        e_n_per_mm2 = scene.tissue.youngs_modulus_kpa * 1e-3
        self.indenter_radius_mm = scene.indenter.diameter_mm / 2.0
        #: Tissue stiffness k = pi^2 R E / 3, Eq. (7) inverted [N/mm].
        self.stiffness_n_per_mm = math.pi**2 * self.indenter_radius_mm * e_n_per_mm2 / 3.0
        tissue = scene.tissue
        #: Kelvin-Voigt tissue time constant tau = eta / E [s]; None when the scene names a
        #: tissue model (its parameters then set the recovery).
        self.tissue_tau_s: float | None = tissue.time_constant_s if tissue.model is None else None
        #: Time constant of the creep under load [s] (the damper of an edematous tissue
        #: expels fluid under the indenter faster than it refills; docs/simulator.md).
        self.loading_tau_s = scene.tissue.loading_time_constant_s
        self.tip_stiffness_n_per_mm = scene.probe.tip_stiffness_n_per_mm
        self.applied_force_n = fp.hold_force_n
        self.t0_s = fp.release_s
        self.end_s = fp.duration_s
        self.calibration, self.area_scale = scaled_calibration(scene)

        k = self.stiffness_n_per_mm
        # Pitting phase: idle (F = 0), linear approach, hold at F_a.
        segs: list[tuple[float, float, float]] = [(0.0, 0.0, 0.0)]
        if fp.approach_s > 0.0:
            segs.append((fp.pre_s, 0.0, fp.hold_force_n / fp.approach_s))
        segs.append((fp.pre_s + fp.approach_s, fp.hold_force_n, 0.0))
        built: list[_Segment] = []
        depth = 0.0
        for i, (t_start, f_start, slope) in enumerate(segs):
            if i > 0:
                prev = built[-1]
                depth = self._kv(prev, t_start)
            built.append(_Segment(t_start, f_start, slope, depth))
        self._segments = tuple(built)
        #: Pitting depth at the release D_p [mm].
        self.depth_at_release_mm = self._kv(built[-1], self.t0_s)
        length = scene.indenter.length_mm
        if not 0.0 < self.depth_at_release_mm < length:
            raise ConfigError(
                f"{scene.name}: pit depth at release {self.depth_at_release_mm:.3f} mm is "
                f"outside (0, {length}) mm (indenter length)"
            )
        d_s = length - self.depth_at_release_mm
        if d_s > self.calibration.max_depth_change_mm:
            raise ConfigError(
                f"{scene.name}: probe.calibration: depth change {d_s:.3f} mm exceeds the "
                f"largest Eq. (4) can encode ({self.calibration.max_depth_change_mm:.3f} mm)"
            )
        #: S_0, occluded area at T_0 from Eq. (4) inverted [px].
        self.s0_px = self.calibration.s0_for_depth_change(d_s)
        #: Tip force at T_0 from Eq. (5) [N].
        self.f0_n = (self.s0_px - self.calibration.c1_px) / self.calibration.c2_px_per_n
        kp = self.tip_stiffness_n_per_mm
        restoring = k * self.depth_at_release_mm
        if self.f0_n < 0.0 or self.f0_n >= restoring:
            raise ConfigError(
                f"{scene.name}: probe.calibration: the tip force at release F_0 = "
                f"{self.f0_n:.3f} N (S_0 = {self.s0_px:.1f} px) must lie in [0, "
                f"{restoring:.3f}) N, the tissue's restoring force k D_p"
            )
        #: The recovery function after T_0 (the scene's tissue model).
        self.recovery: RecoveryModel
        try:
            if self.tissue_tau_s is not None:
                tau_r = recovery_time_constant_s(self.tissue_tau_s, k, kp)
                self.recovery = KelvinVoigt(tau_s=tau_r)
            else:
                assert tissue.model is not None
                self.recovery = tissue.model.build()
        except ConfigError as exc:
            raise ConfigError(f"{scene.name}: tissue: {exc}") from exc
        #: Time constant of the recovery of D, F and S [s]: tau k / (k + k_p) for a
        #: Kelvin-Voigt tissue, the model's effective time constant (1 - 1/e of the
        #: recovery done, :mod:`.tissue.base`) otherwise.
        self.recovery_tau_s = self.recovery.effective_time_constant_s()
        #: Asymptotic rebound force F_inf [N].
        self.f_inf_n = self.f0_n + kp * (restoring - self.f0_n) / (k + kp)
        #: Asymptotic depth under the tip D_inf [mm].
        self.depth_inf_mm = self.depth_at_release_mm - (self.f_inf_n - self.f0_n) / kp

    def _kv(self, seg: _Segment, t_s: float) -> float:
        return float(self._kv_array(seg, np.asarray(t_s, dtype=np.float64)))

    def _kv_array(self, seg: _Segment, t_s: FloatArray) -> FloatArray:
        k, tau = self.stiffness_n_per_mm, self.loading_tau_s
        dt = t_s - seg.t_start_s
        force = seg.force_start_n + seg.slope_n_per_s * dt
        particular = (force - seg.slope_n_per_s * tau) / k
        a = seg.depth_start_mm - (seg.force_start_n - seg.slope_n_per_s * tau) / k
        result: FloatArray = particular + a * np.exp(-dt / tau)
        return result

    def _recovery_decay(self, t_s: FloatArray) -> FloatArray:
        return self.recovery.remaining(np.maximum(t_s - self.t0_s, 0.0))

    def applied_force_profile_n(self, t_s: ArrayLike) -> FloatArray:
        """Operator's force on the locked indenter before T_0, 0 after [N]."""
        t = np.asarray(t_s, dtype=np.float64)
        out = np.zeros_like(t)
        for i, seg in enumerate(self._segments):
            end = self._segments[i + 1].t_start_s if i + 1 < len(self._segments) else self.t0_s
            m = (t >= seg.t_start_s) & (t < end)
            out[m] = seg.force_start_n + seg.slope_n_per_s * (t[m] - seg.t_start_s)
        return out

    def depth_mm(self, t_s: ArrayLike) -> FloatArray:
        """Pit depth D(t) [mm]: Kelvin-Voigt creep before T_0, the tissue model's recovery after."""
        t = np.asarray(t_s, dtype=np.float64)
        out = np.zeros_like(t)
        for i, seg in enumerate(self._segments):
            end = self._segments[i + 1].t_start_s if i + 1 < len(self._segments) else self.t0_s
            m = (t >= seg.t_start_s) & (t < end)
            out[m] = self._kv_array(seg, t[m])
        rec = t >= self.t0_s
        out[rec] = self.depth_inf_mm + (
            self.depth_at_release_mm - self.depth_inf_mm
        ) * self._recovery_decay(t[rec])
        return out

    def tip_force_n(self, t_s: ArrayLike) -> FloatArray:
        """Force through the PDMS tip after T_0 (the rebound force F(t)), 0 before [N]."""
        t = np.asarray(t_s, dtype=np.float64)
        f = self.f_inf_n - (self.f_inf_n - self.f0_n) * self._recovery_decay(t)
        return np.where(t >= self.t0_s, f, 0.0)

    def force_n(self, t_s: ArrayLike) -> FloatArray:
        """Force the load cell sees [N]: applied force before T_0, rebound force after."""
        t = np.asarray(t_s, dtype=np.float64)
        return np.where(t >= self.t0_s, self.tip_force_n(t), self.applied_force_profile_n(t))

    def occluded_area_px(self, t_s: ArrayLike) -> FloatArray:
        """Occluded area S(t) at the rendered resolution [px] (Eq. 5 for the tip force)."""
        t = np.asarray(t_s, dtype=np.float64)
        cal = self.calibration
        if self.scene.probe.pitting_phase_occlusion == "applied_force":
            fa = self.applied_force_profile_n(t)
            before = np.where(fa > 0.0, cal.c1_px + cal.c2_px_per_n * fa, 0.0)
        else:
            before = np.zeros_like(t)
        after = cal.c1_px + cal.c2_px_per_n * self.tip_force_n(t)
        return np.where(t >= self.t0_s, after, before)

    @property
    def max_occluded_area_px(self) -> float:
        """Largest S(t) over the scene [px]."""
        cal = self.calibration
        peak_force = max(self.f_inf_n, self.f0_n)
        if self.scene.probe.pitting_phase_occlusion == "applied_force":
            peak_force = max(peak_force, self.applied_force_n)
        return cal.c1_px + cal.c2_px_per_n * peak_force
