"""Runs the real analysis core on simulator output (shared by the simulator's tests)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.analysis.pitting import compute_pitting_parameters
from stipi_daemon.analysis.recovery_fit import fit_recovery
from stipi_daemon.analysis.vpr import elasticity_kpa
from stipi_daemon.protocol.clocksync import ClockSync
from stipi_daemon.sim.pipeline import ForceBatch, SimFrame
from stipi_daemon.sim.truth import GroundTruth


@dataclass(frozen=True)
class Analysed:
    times_s: np.ndarray
    s_k: np.ndarray
    depth_mm: float
    rebound_force_n: float
    recovery_time_s: float | None
    tau_s: float | None
    applied_force_n: float
    e_kpa: float
    flags: frozenset[Flag]
    saturated_frames: int


def calibration_of(truth: GroundTruth) -> Calibration:
    c = truth.calibration
    return Calibration(
        alpha1_mm_per_px2=c["alpha1_mm_per_px2"],
        alpha2_mm_per_px=c["alpha2_mm_per_px"],
        c1_px=c["c1_px"],
        c2_px_per_n=c["c2_px_per_n"],
        indenter_length_mm=c["indenter_length_mm"],
        threshold_p=c["threshold_p"],
    )


def count_frames(
    frames: Iterable[SimFrame], truth: GroundTruth
) -> tuple[np.ndarray, np.ndarray, int]:
    roi = CircleROI(**truth.roi)
    proc: FrameProcessor | None = None
    times, counts, saturated = [], [], 0
    for f in frames:
        if proc is None:
            proc = FrameProcessor(f.image.shape, truth.frame["threshold_p"], roi)
        m = proc.measure(f.image)
        if Flag.SATURATED_FRAME in m.flags:
            saturated += 1
        times.append(f.t_s)
        counts.append(m.s_k_px)
    return np.asarray(times), np.asarray(counts, dtype=np.float64), saturated


def applied_force(batch: ForceBatch, truth: GroundTruth, hold_start_s: float) -> float:
    m = (batch.t_true_s >= hold_start_s + 0.5) & (batch.t_true_s < truth.t0_s - 0.05)
    return float(np.mean(batch.force_n[m]))


def analyse(
    frames: Iterable[SimFrame],
    batch: ForceBatch,
    truth: GroundTruth,
    hold_start_s: float,
    t0_s: float | None = None,
) -> Analysed:
    t, s, saturated = count_frames(frames, truth)
    cal = calibration_of(truth)
    t0 = truth.t0_s if t0_s is None else t0_s
    pp = compute_pitting_parameters(t, s, t0, cal, window_s=truth.window_s)
    fit = fit_recovery(t, s, t0, window_s=truth.window_s)
    fa = applied_force(batch, truth, hold_start_s)
    e = elasticity_kpa(fa, pp.depth_mm, truth.indenter_radius_mm)
    return Analysed(
        times_s=t,
        s_k=s,
        depth_mm=pp.depth_mm,
        rebound_force_n=pp.rebound_force_n,
        recovery_time_s=pp.recovery_time_s,
        tau_s=fit.tau_s,
        applied_force_n=fa,
        e_kpa=e,
        flags=pp.flags | fit.flags,
        saturated_frames=saturated,
    )


def host_timed(batch: ForceBatch, batch_size: int = 10) -> tuple[ForceBatch, ClockSync]:
    """The batch with ``t_true_s`` replaced by the host's view of each sample's time.

    As the daemon does: one :class:`ClockSync` observation per received notification (the
    MCU time of its last sample, the host receive time ``t_host_s``), then every sample's
    ``t_mcu_us`` mapped through the final fit. Returns the copy and the fit.
    """
    idx = batch.index
    last = np.r_[idx[1:] // batch_size != idx[:-1] // batch_size, True]
    sync = ClockSync()
    for i in np.flatnonzero(last):
        sync.observe(int(batch.t_mcu_us[i]), float(batch.t_host_s[i]))
    mapped = np.asarray([sync.to_host(int(u)) for u in batch.t_mcu_us], dtype=np.float64)
    return dataclasses.replace(batch, t_true_s=mapped), sync
