"""Ground truth of a scene: what a perfect analysis of the simulator's output must report.

This module owns :class:`GroundTruth` and :func:`ground_truth`, which evaluate the paper's
definitions (Eqs. 3-8) on the closed-form model of :mod:`.physics` - S_0 at T_0, S_max
over the recovery window, T_s where S first reaches 98 % of S_max, E from Eq. (7) on the
model's D_p - and the JSON form written next to the video, with units in every key. It
does not render, sample or analyse anything.

For every tissue model (:mod:`.tissue`) the paper's quantities are read off the true
curve: T_r by the 98 % rule (Eq. 6) on S(t) (closed form where the model has one, else
Brent's method on its monotone recovery function); the effective time constant
``time_constant_s``, the time at which 1 - 1/e of the recovery S_inf - S_0 is done (tau
itself for Kelvin-Voigt; :mod:`.tissue.base` says why this definition); eta = E T_r
(Eq. 8, ``viscosity_n_s_per_mm2``) and E tau (``viscosity_from_time_constant_...``).
``tissue_model`` records the model's name, parameters (units in the keys) and source.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from stipi_daemon.sim.loadcell import LoadCellModel
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.scene import Scene

__all__ = ["SETTLE_FRACTION", "WINDOW_S", "GroundTruth", "ground_truth"]

#: Fraction of S_max defining T_s (Eq. 6, paper: 98 %).
SETTLE_FRACTION = 0.98
#: Longest recovery window the paper monitors [s].
WINDOW_S = 105.0


@dataclass(frozen=True)
class GroundTruth:
    """Model values of one scene (units in the names).

    Attributes
    ----------
    t0_s : float
        Release time T_0 [s].
    applied_force_n : float
        Hold force F_a [N].
    depth_mm : float
        Pitting depth D_p at T_0 [mm].
    depth_change_mm : float
        d_s = l - D_p, Eq. (3) [mm].
    s0_px, s_max_px, s_inf_px : float
        S at T_0, its maximum over the recovery window and its asymptote [px].
    rebound_force_n : float
        F_r from Eq. (5) at S_max [N].
    rebound_force_inf_n : float
        Asymptotic rebound force [N].
    ts_s, recovery_time_s : float
        T_s and T_r = T_s - T_0, Eq. (6) [s] (0 when S_0 already exceeds 98 % of S_max).
    time_constant_s : float
        Time constant of the recovery of S, F and D [s]: tau_r for a Kelvin-Voigt tissue
        (what a Kelvin-Voigt fit of S finds), the effective time constant (1 - 1/e of the
        recovery done) for another tissue model.
    recovered_fraction : float
        (S_max - S_0) / (S_inf - S_0): how far the recovery got inside the window [-].
    window_s : float
        Recovery window length [s].
    elasticity_kpa : float
        Eq. (7) on F_a, D_p and R [kPa].
    viscosity_n_s_per_mm2 : float
        Eq. (8), E T_r [N s/mm^2].
    viscosity_from_time_constant_n_s_per_mm2 : float
        E tau_r [N s/mm^2].
    tissue_e_kpa, tissue_eta_n_s_per_mm2, tissue_tau_s : float
        The scene's tissue (E, eta, tau = eta / E); eta and tau are None when the scene
        names a tissue model (its parameters are in ``tissue_model``).
    tissue_model : dict
        ``name``, ``title``, ``parameters`` (units in the keys), ``units``, ``equation``,
        ``source`` of the recovery model, its ``effective_time_constant_s`` and the rules
        behind ``time_constant_s`` and ``recovery_time_s``.
    creep_fraction : float
        D_p k / F_a: how far the pit crept toward F_a / k during the hold [-]. Eq. (7)
        returns tissue_e_kpa / creep_fraction.
    stiffness_n_per_mm, tip_stiffness_n_per_mm : float
        Tissue stiffness pi^2 R E / 3 and the PDMS tip's stiffness [N/mm].
    indenter_radius_mm : float
        R [mm].
    calibration : dict
        Eqs. (4)-(5) coefficients in the rendered resolution's pixel units, the frame size
        and the ROI (the waveguide disc, with ``kind``) they hold for.
    roi : dict
        Circle ROI (cx_px, cy_px, radius_px) covering the lit waveguide.
    frame : dict
        width, height, fps, pixel_format, threshold_p.
    load_cell : dict
        zero_counts, newton_per_count, span_un_per_count, sample_rate_hz, adc_bits.
    """

    scene: str
    seed: int
    t0_s: float
    end_s: float
    applied_force_n: float
    depth_mm: float
    depth_change_mm: float
    s0_px: float
    s_max_px: float
    s_inf_px: float
    rebound_force_n: float
    rebound_force_inf_n: float
    ts_s: float
    recovery_time_s: float
    time_constant_s: float
    recovered_fraction: float
    window_s: float
    elasticity_kpa: float
    viscosity_n_s_per_mm2: float
    viscosity_from_time_constant_n_s_per_mm2: float
    tissue_e_kpa: float
    tissue_eta_n_s_per_mm2: float | None
    tissue_tau_s: float | None
    creep_fraction: float
    stiffness_n_per_mm: float
    tip_stiffness_n_per_mm: float
    indenter_radius_mm: float
    tissue_model: dict[str, Any]
    calibration: dict[str, Any]
    roi: dict[str, float]
    frame: dict[str, Any]
    load_cell: dict[str, Any]
    effects: list[dict[str, Any]]

    def parameters(self) -> dict[str, float]:
        """The reported parameters by the paper's symbols: ``D_p`` [mm], ``F_r`` [N], ``T_r``
        [s], ``tau`` [s], ``E`` [kPa], ``eta`` [N*s/mm^2] (eta = E T_r, Eq. (8))."""
        return {
            "D_p": self.depth_mm,
            "F_r": self.rebound_force_n,
            "T_r": self.recovery_time_s,
            "tau": self.time_constant_s,
            "E": self.elasticity_kpa,
            "eta": self.viscosity_n_s_per_mm2,
        }

    def to_json_dict(self) -> dict[str, Any]:
        """A JSON-ready mapping (every key names its unit)."""
        out = asdict(self)
        out["format"] = "stipi-sim-ground-truth/1"
        return out


def ground_truth(
    scene: Scene,
    seed: int | None = None,
    *,
    model: SceneModel | None = None,
    roi: dict[str, float] | None = None,
) -> GroundTruth:
    """Model values of ``scene`` (Eqs. 3-8 on the closed-form physics).

    Parameters
    ----------
    scene : Scene
        The scene.
    seed : int, optional
        Recorded in the result (default: the scene's seed); the truth does not depend on it.
    model : SceneModel, optional
        Its physics, if already built.
    roi : dict, optional
        The renderer's ROI to record (the renderer computes it; omitted -> computed here).
    """
    m = model if model is not None else SceneModel(scene)
    cal = m.calibration
    window = min(scene.force_profile.recovery_s, WINDOW_S)
    t_end = m.t0_s + window
    s0 = m.s0_px
    s_inf = cal.c1_px + cal.c2_px_per_n * m.f_inf_n
    s_max = float(m.occluded_area_px(np.asarray([t_end]))[0])
    level = SETTLE_FRACTION * s_max
    tau_r = m.recovery_tau_s
    if level <= s0:
        tr = 0.0
    else:
        tr = m.recovery.settling_time_s(s0, s_inf, level)
    f_r = (s_max - cal.c1_px) / cal.c2_px_per_n
    r_mm = m.indenter_radius_mm
    d_p = m.depth_at_release_mm
    e_kpa = 1e3 * 3.0 / (math.pi**2 * r_mm) * m.applied_force_n / d_p
    if roi is None:
        from stipi_daemon.sim.render import Renderer

        r = Renderer(scene, m).roi
        roi = {"cx_px": r.cx_px, "cy_px": r.cy_px, "radius_px": r.radius_px}
    lc = LoadCellModel(scene.load_cell)
    cam = scene.camera
    return GroundTruth(
        scene=scene.name,
        seed=scene.seed if seed is None else seed,
        t0_s=m.t0_s,
        end_s=m.end_s,
        applied_force_n=m.applied_force_n,
        depth_mm=d_p,
        depth_change_mm=scene.indenter.length_mm - d_p,
        s0_px=s0,
        s_max_px=s_max,
        s_inf_px=s_inf,
        rebound_force_n=f_r,
        rebound_force_inf_n=m.f_inf_n,
        ts_s=m.t0_s + tr,
        recovery_time_s=tr,
        time_constant_s=tau_r,
        recovered_fraction=(s_max - s0) / (s_inf - s0),
        window_s=window,
        elasticity_kpa=e_kpa,
        viscosity_n_s_per_mm2=e_kpa * 1e-3 * tr,
        viscosity_from_time_constant_n_s_per_mm2=e_kpa * 1e-3 * tau_r,
        tissue_e_kpa=scene.tissue.youngs_modulus_kpa,
        tissue_eta_n_s_per_mm2=(
            None
            if m.tissue_tau_s is None
            else scene.tissue.youngs_modulus_kpa * 1e-3 * m.tissue_tau_s
        ),
        tissue_tau_s=m.tissue_tau_s,
        creep_fraction=d_p * m.stiffness_n_per_mm / m.applied_force_n,
        stiffness_n_per_mm=m.stiffness_n_per_mm,
        tip_stiffness_n_per_mm=m.tip_stiffness_n_per_mm,
        indenter_radius_mm=r_mm,
        tissue_model=_tissue_model_record(m),
        calibration={
            "alpha1_mm_per_px2": cal.alpha1_mm_per_px2,
            "alpha2_mm_per_px": cal.alpha2_mm_per_px,
            "c1_px": cal.c1_px,
            "c2_px_per_n": cal.c2_px_per_n,
            "indenter_length_mm": cal.indenter_length_mm,
            "threshold_p": scene.probe.threshold,
            "area_scale": m.area_scale,
            "reference_resolution": list(scene.probe.calibration.reference_resolution),
            "frame_size_px": [cam.width, cam.height],
            "roi": {"kind": "circle", **roi},
        },
        roi=dict(roi),
        frame={
            "width_px": cam.width,
            "height_px": cam.height,
            "fps": cam.fps,
            "exposure_s": cam.exposure_s,
            "pixel_format": cam.pixel_format,
            "threshold_p": scene.probe.threshold,
        },
        load_cell={
            "zero_counts": lc.zero_counts,
            "newton_per_count": lc.newton_per_count,
            "span_un_per_count": lc.span_un_per_count,
            "sample_rate_hz": scene.load_cell.sample_rate_hz,
            "adc_bits": scene.load_cell.adc_bits,
            "range_n": scene.load_cell.range_n,
        },
        effects=[e.model_dump() for e in scene.effects],
    )


def _tissue_model_record(m: SceneModel) -> dict[str, Any]:
    rec = m.recovery
    return {
        "name": rec.NAME,
        "title": rec.TITLE,
        "parameters": dict(rec.parameters),
        "units": {p.name: p.unit for p in rec.PARAMETERS},
        "equation": rec.EQUATION,
        "source": rec.SOURCE,
        "from_scene": "tissue.model" if m.scene.tissue.model is not None else "tissue (tau)",
        "effective_time_constant_s": m.recovery_tau_s,
        "time_constant_rule": "time after T_0 at which 1 - 1/e of S_inf - S_0 is recovered",
        "recovery_time_rule": "T_s - T_0, S first reaches 98 % of S_max (Eq. 6)",
        "viscosity_rule": "eta = E T_r (Eq. 8)",
    }
