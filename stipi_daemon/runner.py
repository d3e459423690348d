"""Run one measurement from a config: source → live pipeline → session on disk → results.

This is the shell around :class:`~stipi_daemon.measurement.pipeline.MeasurementPipeline`:
it pulls frames and force samples from the configured source in time order, measures S_k
on every frame (Eqs. 1-2), feeds the pipeline, streams everything into the session
(:mod:`stipi_daemon.storage`), tells the operator what to do next, and at the end writes
``summary.json`` and prints the parameters and the severity.

Time: with a simulated source the scene's clock is the session clock. By default the
run is accelerated (no waiting); ``realtime=True`` paces it to the wall clock, as a probe
would. The simulated probe is in process here: its samples carry the MCU timestamps the
simulator gives them, mapped onto the session clock one to one.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from stipi_daemon import __version__
from stipi_daemon.analysis.calibration import Calibration, load_calibration
from stipi_daemon.analysis.imaging import CircleROI, FrameProcessor
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.config import DaemonConfig
from stipi_daemon.errors import StipiError
from stipi_daemon.measurement.pipeline import MeasurementPipeline
from stipi_daemon.measurement.state_machine import (
    Advisory,
    Fault,
    OperatorPrompt,
    Output,
    Phase,
    PhaseChanged,
)
from stipi_daemon.storage.writer import SessionWriter, StorageOptions

__all__ = ["RunOutcome", "run_measurement"]

#: Interval between stored live-parameter rows and console updates, in session time [s].
LIVE_INTERVAL_S = 1.0
#: Rows buffered in memory before they are handed to the writer [-].
_BATCH_ROWS = 256


@dataclass(frozen=True)
class RunOutcome:
    """How a run ended.

    Attributes
    ----------
    session_dir : Path
        The session directory.
    phase : Phase
        Terminal phase (``DONE`` or a fault).
    summary : dict
        What ``summary.json`` holds.
    """

    session_dir: Path
    phase: Phase
    summary: dict[str, Any]

    @property
    def exit_code(self) -> int:
        """0 for a completed measurement with results, 1 otherwise."""
        return 0 if self.phase == Phase.DONE and self.summary.get("results") else 1


def _merged(
    frames: Iterator[tuple[int, float, np.ndarray]], force: Iterator[tuple[int, int, float, float]]
) -> Iterator[tuple[str, tuple[Any, ...]]]:
    """Frames and force samples in time order (force first at equal times)."""
    f = next(force, None)
    for fr in frames:
        while f is not None and f[2] <= fr[1]:
            yield "force", f
            f = next(force, None)
        yield "frame", fr
    while f is not None:
        yield "force", f
        f = next(force, None)


class _Console:
    """Plain-text operator console: phase changes, faults, and prompts at most once per
    5 s unless what they ask for changes (the text before the first ':')."""

    def __init__(self, out: TextIO, quiet: bool) -> None:
        self.out = out
        self.quiet = quiet
        self._prompt_key = ""
        self._prompt_t = -math.inf
        self.now_s = 0.0

    def line(self, text: str) -> None:
        if not self.quiet:
            print(text, file=self.out, flush=True)

    def outputs(self, outputs: list[Output]) -> None:
        for o in outputs:
            if isinstance(o, PhaseChanged):
                self.line(f"[{o.t_s:7.2f} s] {o.old} -> {o.new}: {o.reason}")
            elif isinstance(o, OperatorPrompt):
                key = o.text.split(":", 1)[0]
                if key != self._prompt_key or self.now_s - self._prompt_t >= 5.0:
                    self._prompt_key, self._prompt_t = key, self.now_s
                    self.line(f"           >> {o.text}")
            elif isinstance(o, Advisory):
                self.line(f"[{o.t_s:7.2f} s] note: {o.kind}: {o.detail}")
            elif isinstance(o, Fault):
                self.line(f"[{o.t_s:7.2f} s] FAULT {o.kind}: {o.reason}")


def _fmt(v: float | None, unit: str, digits: int = 3) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}g} {unit}"


def run_measurement(
    config: DaemonConfig,
    *,
    realtime: bool = False,
    out: TextIO | None = None,
    quiet: bool = False,
    clock: Callable[[], float] = time.monotonic,
) -> RunOutcome:
    """Record and analyse one measurement as ``config`` says.

    Raises
    ------
    StipiError
        The source, calibration or storage cannot be opened (one-line message).
    """
    # Imported here: the simulator is only needed for a simulated source.
    from stipi_daemon.sim.physics import scaled_calibration
    from stipi_daemon.sim.pipeline import Pipeline
    from stipi_daemon.sim.scene import load_scene
    from stipi_daemon.sim.truth import ground_truth

    console = _Console(out if out is not None else sys.stdout, quiet)
    src = config.source
    scene = load_scene(src.scene)
    seed = scene.seed if src.seed is None else src.seed
    sim = Pipeline(scene, seed)
    truth = ground_truth(scene, seed)

    calibration: Calibration
    if config.calibration is not None:
        calibration = load_calibration(config.calibration)
    else:
        calibration, _ = scaled_calibration(scene)
    threshold = config.imaging.threshold_p
    if threshold is None:
        threshold = calibration.threshold_p
    if threshold is None:
        threshold = int(truth.frame["threshold_p"])
    roi = config.imaging.roi or CircleROI(kind="circle", **truth.roi)
    reference = load_reference()

    first = next(iter(sim.frames(0.0, 0.0)), None)
    if first is None:
        raise StipiError(f"{src.scene}: the scene renders no frame")
    processor = FrameProcessor(
        first.image.shape,
        threshold,
        roi,
        saturation_limit_fraction=config.imaging.saturation_limit_fraction,
    )

    storage = config.storage
    writer = SessionWriter.create(
        storage.root,
        config.model_dump(mode="json"),
        {
            "alpha1_mm_per_px2": calibration.alpha1_mm_per_px2,
            "alpha2_mm_per_px": calibration.alpha2_mm_per_px,
            "c1_px": calibration.c1_px,
            "c2_px_per_n": calibration.c2_px_per_n,
            "indenter_length_mm": calibration.indenter_length_mm,
            "threshold_p": threshold,
            "source": "config file" if config.calibration else f"scene {scene.name}",
        },
        {"kind": "simulator", "scene": scene.name, "seed": seed, "software": __version__},
        options=StorageOptions(
            commit_interval_s=storage.commit_interval_s,
            min_free_bytes=int(storage.min_free_mb * 1e6),
        ),
    )
    console.line(f"session {writer.session_id} in {storage.root}")
    console.line(
        f"source: simulated scene '{scene.name}' ({scene.camera.width}x{scene.camera.height}"
        f" @ {scene.camera.fps:g} fps, load cell {scene.load_cell.sample_rate_hz:g} Hz),"
        f" seed {seed}"
    )

    pipeline = MeasurementPipeline(
        measurement=config.measurement,
        analysis=config.analysis,
        calibration=calibration,
        reference=reference,
    )
    batch = sim.force_batch()
    force_iter = zip(
        batch.index.tolist(),
        batch.adc_counts.tolist(),
        batch.t_true_s.tolist(),
        batch.force_n.tolist(),
        strict=True,
    )
    mcu_us = dict(zip(batch.index.tolist(), batch.t_mcu_us.tolist(), strict=True))
    frame_iter = ((f.index, f.t_s, f.image) for f in sim.frames())

    force_rows: list[tuple[Any, ...]] = []
    frame_rows: list[tuple[Any, ...]] = []
    wall0 = clock()
    next_live = 0.0
    last_index: int | None = None
    status = "fault"

    def record(outputs: list[Output]) -> None:
        console.now_s = pipeline.state.now_s
        console.outputs(outputs)
        for o in outputs:
            if isinstance(o, PhaseChanged):
                writer.add_transition(o.t_s, str(o.old), str(o.new), o.reason)
            elif isinstance(o, Advisory):
                writer.add_event(o.t_s, f"advisory:{o.kind}", {"detail": o.detail})
            elif isinstance(o, Fault):
                writer.add_event(o.t_s, f"fault:{o.kind}", {"reason": o.reason})
            elif isinstance(o, OperatorPrompt):
                writer.add_event(pipeline.state.now_s, "prompt", {"text": o.text})

    try:
        record(pipeline.arm(0.0))
        for kind, item in _merged(frame_iter, force_iter):
            if kind == "force":
                index, counts, t_s, force_n = item
                if last_index is not None and index != last_index + 1:
                    writer.add_gap("force", last_index + 1, index - last_index - 1, t_s, "link")
                last_index = index
                raw = mcu_us[index]
                force_rows.append((index, counts, raw % (1 << 32), raw, t_s, force_n))
                outputs = pipeline.force(t_s, force_n)
            else:
                seq, t_s, image = item
                m = processor.measure(image)
                frame_rows.append((seq, t_s, t_s, m.s_k_px, sorted(m.flags)))
                outputs = pipeline.frame(t_s, float(m.s_k_px))
            if outputs:
                record(outputs)
            if len(force_rows) >= _BATCH_ROWS:
                writer.add_force_samples(force_rows)
                force_rows.clear()
            if len(frame_rows) >= _BATCH_ROWS:
                writer.add_frames(frame_rows)
                frame_rows.clear()
            now = pipeline.state.now_s
            if now >= next_live:
                next_live = now + LIVE_INTERVAL_S
                live = pipeline.live()
                if live is not None:
                    writer.add_live_parameters(now, live.to_dict())
                    if int(live.elapsed_s) % 5 == 0:
                        console.line(
                            f"[{now:7.2f} s] recovery {live.elapsed_s:5.1f} s:"
                            f" D_p {_fmt(live.depth_mm, 'mm')},"
                            f" F_r {_fmt(live.rebound_force_n, 'N')},"
                            f" T_r {'>=' if not live.settled else ''}"
                            f"{_fmt(live.recovery_time_s, 's')},"
                            f" E {_fmt(live.elasticity_kpa, 'kPa')}, tau {_fmt(live.tau_s, 's')}"
                        )
            if realtime:
                lag = now - (clock() - wall0)
                if lag > 0:
                    time.sleep(lag)
            if pipeline.finished:
                break
        if not pipeline.finished:
            record(pipeline.close(pipeline.state.now_s))
        writer.add_force_samples(force_rows)
        writer.add_frames(frame_rows)

        summary = _summary(pipeline, truth.to_json_dict())
        phase = pipeline.phase
        status = "complete" if phase == Phase.DONE else "fault"
        writer.finish(status, summary)
    except BaseException:
        writer.add_force_samples(force_rows)
        writer.add_frames(frame_rows)
        writer.finish("aborted", {"status": "aborted", "phase": str(pipeline.phase)})
        raise
    finally:
        writer.close()
    _print_results(console, summary)
    console.line(f"session written to {writer.db_path.parent}")
    return RunOutcome(writer.db_path.parent, phase, summary)


def _summary(pipeline: MeasurementPipeline, truth: dict[str, Any] | None) -> dict[str, Any]:
    start = pipeline.start
    out: dict[str, Any] = {
        "status": "complete" if pipeline.phase == Phase.DONE else "fault",
        "phase": str(pipeline.phase),
        "end_reason": pipeline.state.end_reason,
        "measurement": None if start is None else asdict(start) | {"t0_refined_s": pipeline.t0_s},
        "measurement_flags": sorted(pipeline.state.flags),
        "results": None if pipeline.result is None else pipeline.result.to_dict(),
        "analysis_error": pipeline.analysis_error,
        "notes": list(pipeline.notes),
    }
    if truth is not None:
        out["ground_truth"] = truth
    return out


def _print_results(console: _Console, summary: dict[str, Any]) -> None:
    res = summary.get("results")
    if not res:
        console.line(f"no results: {summary.get('analysis_error') or summary.get('end_reason')}")
        return
    p = res["pitting"]
    paper = res["paper_estimator"] or {}
    fit = res["fitted_recovery"]
    fm = fit["model"] or {}
    console.line("")
    console.line("results")
    console.line(f"  pitting depth      D_p = {_fmt(p['depth_mm'], 'mm', 4)}      (Eq. 3)")
    console.line(f"  rebound force      F_r = {_fmt(p['rebound_force_n'], 'N', 4)}       (Eq. 5)")
    console.line(f"  recovery time      T_r = {_fmt(p['recovery_time_s'], 's', 4)}       (Eq. 6)")
    console.line(f"  applied force      F_a = {_fmt(res['applied_force_n'], 'N', 4)}")
    console.line(
        f"  elasticity         E   = {_fmt(paper.get('elasticity_kpa'), 'kPa', 4)}  (Eq. 7)"
    )
    console.line(
        f"  viscosity (paper)  eta = {_fmt(paper.get('viscosity_n_s_per_mm2'), 'N*s/mm^2', 4)}"
        " (Eq. 8, E*T_r)"
    )
    tau_se = fit.get("tau_se_s")
    console.line(
        f"  time constant      tau = {_fmt(fit['tau_s'], 's', 4)}"
        + (f" +- {tau_se:.2g} s" if tau_se is not None else "")
        + "  (fitted Kelvin-Voigt recovery)"
    )
    console.line(
        f"  viscosity (fit)    eta = {_fmt(fm.get('viscosity_n_s_per_mm2'), 'N*s/mm^2', 4)} (E*tau)"
    )
    for name, sev in res["severity"].items():
        if sev is None:
            continue
        console.line(
            f"  severity ({name.replace('_', ' ')}): {sev['severity'].upper()},"
            f" nearest grade {sev['nearest_grade']}, recovered {sev['recovered_percent']:.1f} %"
            f" in {sev['window_s'][0]:g}-{sev['window_s'][1]:g} s"
            f" (threshold {sev['threshold_recovered_percent']:.1f} %)"
        )
    if res["flags"]:
        console.line(f"  flags: {', '.join(res['flags'])}")
