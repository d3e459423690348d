"""The fault matrix's literature-law group (issue 37): tissues and camera faults the
project's own models do not make, through the real daemon.

Each :class:`LawCase` is one measurement whose recovery follows a law of
:mod:`tests.faults.laws` (power-law, poroelastic, stretched-exponential, a standard linear
solid that springs back inside the release frame, Kelvin-Voigt as the control), with the
camera and sensor faults the issue names: LED flicker, pixel noise, vignetting, saturated
frames, a load cell pinned at its rail, a long frame gap in the recovery, a run stopped
(Ctrl-C) in the recovery and analysed afterwards with ``analyze``.

How it runs: the daemon of ``tests/faults/matrix.py`` (``run_daemon``, emulated Feather on
a pty, the simulator camera, the session clock that waits for the daemon) on a grade-III
scene file whose devices are fed by this module while the run lasts
(:func:`law_world`): the camera's frames come from :class:`~tests.faults.laws.FrameRenderer`
with S(t) from the law, and the load cell's force from :func:`LawWorld.force_n` (the
hold, then Eq. 5 inverted on the law's S, through the scene's load cell and ADC). The
scene's own tissue model makes neither. Every primary quantity is classified as in the
matrix (:func:`tests.faults.matrix.classify`) against :func:`law_truth`.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

import stipi_daemon.sim as sim_package
import stipi_daemon.sim.camera as sim_camera
from stipi_daemon.analysis.severity import classify_decay_rate, load_reference
from stipi_daemon.app.analyze import AnalyzeRequest, analyze
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import DaemonHandles, run_daemon
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.pipeline import Pipeline, SimFrame
from stipi_daemon.sim.render import Renderer
from stipi_daemon.sim.scene import Scene, parse_scene
from stipi_daemon.storage import SessionWriter

from .laws import (
    SETTLE_FRACTION,
    FloatArray,
    FrameRenderer,
    Optics,
    Tissue,
    crossing_s,
    frame_times,
)
from .matrix import (
    BAND_LOW_N,
    LAG_ERROR,
    MARGIN_S,
    PAPER_WINDOW_S,
    PITTING_S,
    SCENES,
    T_R_FRAMES,
    TOLERANCES,
    CaseResult,
    camera_kept_up,
    classify,
    recorded,
)

#: Indenter radius R of Eq. (7) the matrix's daemon config sets [mm].
RADIUS_MM = 7.5
#: Approach to the hold force [s] (the matrix's scenes).
APPROACH_S = 1.0


@dataclass(frozen=True)
class LawCase:
    """One run of the law group; times marked ``rel`` are relative to the true T_0 [s].

    Attributes
    ----------
    name : str
        Unique name.
    tissue : Tissue
        The recovery law and its pit.
    window_s : float
        Recovery the daemon may watch (``measurement.recovery_max_s``) and over which the
        truth is taken [s].
    stop_when_settled : bool
        ``measurement.stop_when_settled`` (the early-stop rule; its default is true).
    optics : Optics
        Picture and camera effects.
    hold_force_n : float
        True applied force of the hold [N].
    load_cell_range_n : float, optional
        The scene load cell's rated range [N]; the cell's output is pinned there (its
        bridge at full scale) when the force exceeds it, while the tissue feels the force.
    frame_gap_rel_s : tuple of float, optional
        Span without frames, [a, b) after T_0 [s] (the camera delivers none).
    stall_rel_s : tuple of float, optional
        Span [a, b) after T_0 whose frames the daemon does not process in time (the
        scene's ``processing_stall``: they are handed over at b; ``run.max_lag_s`` is
        its largest, 60 s, so the run goes on past them).
    stop_rel_s : float, optional
        Ctrl-C this long after T_0 [s]; the session is then analysed with ``analyze``.
    release_lead_s : float
        Release this long before the daemon's pitting timer ends [s] (the matrix's).
    seed : int
        Scene seed (the noise's seed is the optics').
    """

    name: str
    tissue: Tissue
    window_s: float = PAPER_WINDOW_S
    stop_when_settled: bool = True
    optics: Optics = field(default_factory=Optics)
    hold_force_n: float = 16.0
    load_cell_range_n: float | None = None
    frame_gap_rel_s: tuple[float, float] | None = None
    stall_rel_s: tuple[float, float] | None = None
    stop_rel_s: float | None = None
    release_lead_s: float = -0.6
    seed: int = 0

    @property
    def hold_s(self) -> float:
        """Hold after the approach that releases ``release_lead_s`` before the timer [s]."""
        band_entry_s = APPROACH_S * BAND_LOW_N / self.hold_force_n
        return band_entry_s + PITTING_S - self.release_lead_s - APPROACH_S

    @property
    def t0_s(self) -> float:
        """True release time T_0 [s]."""
        return APPROACH_S + self.hold_s

    def scene_doc(self) -> dict[str, Any]:
        """The scene: the grade III file with this case's force profile, a 320x240 gray
        camera and no effects (the faults are this module's)."""
        doc: dict[str, Any] = yaml.safe_load((SCENES / "grade3.yaml").read_text())
        doc["name"] = self.name
        doc["seed"] = self.seed
        doc["force_profile"].update(
            pre_s=0.0,
            approach_s=APPROACH_S,
            hold_force_n=self.hold_force_n,
            hold_s=round(self.hold_s, 6),
            recovery_s=self.window_s + MARGIN_S,
        )
        doc["probe"]["pitting_phase_occlusion"] = "applied_force"
        doc["camera"].update(
            width=self.optics.width, height=self.optics.height, pixel_format="gray8"
        )
        if self.load_cell_range_n is not None:
            doc["load_cell"]["range_n"] = self.load_cell_range_n
        doc["effects"] = []
        if self.stall_rel_s is not None:
            a, b = self.stall_rel_s
            doc["effects"].append(
                {"name": "processing_stall", "t_start_s": self.t0_s + a, "t_end_s": self.t0_s + b}
            )
        return doc


# ------------------------------------------------------------------------------ the world


@dataclass(frozen=True)
class LawWorld:
    """Force and S(t) of a case on the scene's clock (t = 0 the scene's start)."""

    case: LawCase
    c1_px: float
    c2_px_per_n: float

    def applied_n(self, t: FloatArray) -> FloatArray:
        """Force during the approach and hold: a ramp to the hold force, held [N]."""
        out: FloatArray = self.case.hold_force_n * np.clip(t / APPROACH_S, 0.0, 1.0)
        return out

    def area_px(self, t_s: ArrayLike) -> FloatArray:
        """S(t): C1 + C2 F under the applied force (the tip carries it, Eq. 5), then the
        law after T_0 [px]."""
        t = np.asarray(t_s, dtype=np.float64)
        f = self.applied_n(t)
        before = np.where(f > 0.0, self.c1_px + self.c2_px_per_n * f, 0.0)
        after = self.case.tissue.area_px(t - self.case.t0_s)
        out: FloatArray = np.where(t >= self.case.t0_s, after, before)
        return out

    def force_n(self, t_s: ArrayLike) -> FloatArray:
        """Force on the load cell: the hold, then the tip's force, Eq. (5) inverted on the
        law's S [N]."""
        t = np.asarray(t_s, dtype=np.float64)
        after = np.maximum((self.area_px(t) - self.c1_px) / self.c2_px_per_n, 0.0)
        out: FloatArray = np.where(t >= self.case.t0_s, after, self.applied_n(t))
        return out


def world_of(case: LawCase, scene: Scene) -> LawWorld:
    """The case's world with the scene's calibration (Eq. 5's C1, C2 at its frame size)."""
    cal = SceneModel(scene).calibration
    return LawWorld(case, cal.c1_px, cal.c2_px_per_n)


class _LawModel(SceneModel):
    """The scene's model with the law's force (the load cell reads this)."""

    def __init__(self, scene: Scene, world: LawWorld) -> None:
        super().__init__(scene)
        self._world = world

    def force_n(self, t_s: ArrayLike) -> FloatArray:
        rail = self._world.case.load_cell_range_n
        force = self._world.force_n(t_s)
        return force if rail is None else np.minimum(force, rail)

    def occluded_area_px(self, t_s: ArrayLike) -> FloatArray:
        return self._world.area_px(t_s)


def _law_pipeline(world: LawWorld) -> type[Pipeline]:
    """A :class:`~stipi_daemon.sim.pipeline.Pipeline` whose frames are this module's and
    whose force is the law's."""
    case = world.case
    renderer = FrameRenderer(case.optics)
    gap = case.frame_gap_rel_s
    gaps = () if gap is None else ((case.t0_s + gap[0], case.t0_s + gap[1]),)

    class LawPipeline(Pipeline):
        def __init__(
            self,
            scene: Scene,
            seed: int | None = None,
            renderer: Renderer | None = None,
            *,
            gray_decode: bool = False,
        ) -> None:
            super().__init__(scene, seed, renderer, gray_decode=gray_decode)
            self.model = _LawModel(scene, world)

        def frames(self, start_s: float = 0.0, end_s: float | None = None) -> Iterator[SimFrame]:
            fps = float(self.scene.camera.fps)
            last = self.scene.force_profile.duration_s if end_s is None else end_s
            for k, t in frame_times(fps, last, gaps):
                if t >= start_s - 1e-9:
                    s = float(world.area_px(np.asarray([t]))[0])
                    yield SimFrame(k, t, _frozen(renderer.frame(k, t, s)), s)

    return LawPipeline


def _frozen(image: np.ndarray[Any, Any]) -> Any:
    image.flags.writeable = False
    return image


@contextlib.contextmanager
def law_world(world: LawWorld) -> Iterator[None]:
    """While inside: the simulated devices (camera and emulated probe) build their scene
    pipeline as :func:`_law_pipeline`, i.e. play ``world``. Both look the class up when
    they open (``stipi_daemon.sim.camera.Pipeline``, ``stipi_daemon.sim.Pipeline``)."""
    cls = _law_pipeline(world)
    name = "Pipeline"
    modules = (sim_camera, sim_package)
    saved = [getattr(m, name) for m in modules]  # AttributeError if either is renamed
    for m in modules:
        setattr(m, name, cls)
    try:
        yield
    finally:
        for m, original in zip(modules, saved, strict=True):
            setattr(m, name, original)


# ------------------------------------------------------------------------------ truth


def law_truth(case: LawCase, scene: Scene) -> dict[str, dict[str, Any]]:
    """Truth of each primary quantity from the law (the matrix's layout, :func:`~.matrix.truth`).

    * S_0 is the hold's pit (the law at T_0, before any spring-back); D_p's and E's ranges
      are its values +- the tolerance, without the matrix's allowance of one frame of
      recovery (:func:`~.matrix.truth`): these laws recover 10-50 % of the pit within the
      frame period after the release (a power law's rate is infinite at T_0, the SLS
      jumps), which is the depth the frames cannot show, not the depth the hold made; the
      analysis has to say so (issue 37, "S_0 agrees with the hold");
    * S_max is the law's level at the end of the window (every law here rises
      monotonically), T_s its first crossing of 98 % of S_max (Eq. 6, to 1 us);
    * D_p = l - d_s with d_s = -alpha1 S_0^2 + alpha2 S_0 (Eqs. 3-4), F_r = (S_max - C1) / C2
      (Eq. 5), E = 3 F_a / (pi^2 R D_p) (Eq. 7, F_a the true hold force), eta = E T_r (Eq. 8);
    * the class is the paper's (Section IV.C) for T_r over its 105 s window.

    Tolerances and ranges as the matrix's (:data:`~.matrix.TOLERANCES`).
    """
    cal = SceneModel(scene).calibration
    tis = case.tissue
    frame_s = 1.0 / float(scene.camera.fps)

    def depth_mm(s0_px: float) -> float:
        return cal.indenter_length_mm - (
            -cal.alpha1_mm_per_px2 * s0_px**2 + cal.alpha2_mm_per_px * s0_px
        )

    def t_r(window_s: float) -> tuple[float, float]:
        s_max = float(tis.area_px(np.asarray([window_s]))[0])
        return crossing_s(tis.area_px, SETTLE_FRACTION * s_max, window_s), s_max

    tr, s_max = t_r(case.window_s)
    d_p = depth_mm(tis.s0_px)
    e_kpa = 1e3 * 3.0 / (math.pi**2 * RADIUS_MM) * case.hold_force_n / d_p

    def band(quantity: str, *values: float) -> dict[str, Any]:
        kind, tol = TOLERANCES[quantity]
        lo, hi = min(values), max(values)
        margin = (tol * lo, tol * hi)
        if kind == "rel_or_frames":
            margin = (max(margin[0], T_R_FRAMES * frame_s), max(margin[1], T_R_FRAMES * frame_s))
        return {"value": values[0], "low": lo - margin[0], "high": hi + margin[1]}

    tr_paper = t_r(PAPER_WINDOW_S)[0]
    severity = classify_decay_rate(1.0 / tr_paper, load_reference()).severity
    return {
        "depth_mm": band("depth_mm", d_p),
        "rebound_force_n": band("rebound_force_n", (s_max - cal.c1_px) / cal.c2_px_per_n),
        "recovery_time_s": band("recovery_time_s", tr),
        "elasticity_kpa": band("elasticity_kpa", e_kpa),
        "viscosity_n_s_per_mm2": band("viscosity_n_s_per_mm2", 1e-3 * e_kpa * tr),
        "severity": {"value": severity, "low": None, "high": None},
    }


# ------------------------------------------------------------------------------ running


def write_law_case(case: LawCase, directory: Path, speed: float) -> tuple[Path, Scene]:
    """Scene file and daemon config of ``case`` in ``directory``; returns (config, scene).
    The config is the matrix's (emulated probe, simulator camera), with the case's window
    and early-stop rule, the largest ``run.max_lag_s`` (60 s: a processing stall is lived
    through) and no session video (nothing here reads it)."""
    directory.mkdir(parents=True, exist_ok=True)
    doc = case.scene_doc()
    scene_path = directory / f"{case.name}.yaml"
    scene_path.write_text(yaml.safe_dump(doc, sort_keys=False))
    scene = parse_scene(doc, scene_path.name)
    config = {
        "format": "stipi-daemon-config",
        "version": 1,
        "probe": {"transport": {"kind": "emulated", "scene": str(scene_path)}},
        "camera": {"kind": "simulator", "scene": str(scene_path)},
        "measurement": {
            "recovery_max_s": case.window_s,
            "stop_when_settled": case.stop_when_settled,
        },
        "analysis": {"indenter_radius_mm": RADIUS_MM},
        "storage": {"root": str(directory / "sessions"), "min_free_mb": 0, "video": "off"},
        "run": {"speed": speed, "max_lag_s": 60.0},
    }
    config_path = directory / "config.yaml"
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    return config_path, scene


async def _daemon(case: LawCase, config_path: Path) -> tuple[dict[str, Any], str, Path]:
    """Run the daemon; returns (summary, phase, session directory). A case with
    ``stop_rel_s`` is cancelled then (the daemon's Ctrl-C) and its session analysed by
    ``analyze``, whose summary is returned."""
    sessions: list[Path] = []

    def on_session(writer: SessionWriter) -> None:
        sessions.append(Path(writer.directory))

    task: asyncio.Task[Any] | None = None

    async def stop(h: DaemonHandles) -> None:
        while h.camera.camera.t0_s is None:
            await asyncio.sleep(0.01)
        assert case.stop_rel_s is not None
        await h.clock.sleep_until(float(h.camera.camera.t0_s) + case.t0_s + case.stop_rel_s)
        assert task is not None
        task.cancel()

    on_running = stop if case.stop_rel_s is not None else None
    task = asyncio.ensure_future(
        run_daemon(
            load_config(config_path), quiet=True, on_session=on_session, on_running=on_running
        )
    )
    try:
        outcome = await task
    except asyncio.CancelledError:
        if case.stop_rel_s is None or not sessions:
            raise
        run = analyze(AnalyzeRequest(session_dir=sessions[0], out=config_path.parent / "a.json"))
        return dict(run.document["summary"]), f"aborted/analyze: {run.outcome.phase}", sessions[0]
    return outcome.summary, str(outcome.phase), outcome.session_dir


async def run_law_case(
    case: LawCase, directory: Path, speed: float = 20.0, *, min_speed: float = 1.0
) -> CaseResult:
    """Run ``case`` on the real daemon in ``directory`` and classify its results (halving
    the speed when the camera fell behind, as :func:`~.matrix.run_case`)."""
    while True:
        result = await _run_once(case, directory / f"x{speed:g}", speed)
        if result.error is None or not result.error.startswith(LAG_ERROR) or speed / 2 < min_speed:
            return result
        speed /= 2


async def _run_once(case: LawCase, directory: Path, speed: float) -> CaseResult:
    config_path, scene = write_law_case(case, directory, speed)
    result = CaseResult(case, speed=speed)
    t = time.monotonic()
    try:
        with law_world(world_of(case, scene)):
            summary, phase, session = await _daemon(case, config_path)
    except Exception as exc:  # a crash is reported as such, never as a result
        result.error = f"{type(exc).__name__}: {exc}"
        result.quantities = {q: {"outcome": "error"} for q in TOLERANCES}
        return result
    finally:
        result.wall_s = time.monotonic() - t
    result.phase = phase
    result.recorded = recorded(session)
    if case.stop_rel_s is None:
        result.error = camera_kept_up(result.recorded, summary)
    verdict = summary.get("verdict")
    result.verdict = (
        str(verdict.get("status")) if isinstance(verdict, dict) else f"{summary.get('status')}"
    )
    result.quantities = classify(summary, law_truth(case, scene))
    return result


def run_law_cases(
    cases: Sequence[LawCase], directory: Path, speed: float, *, echo: bool = False
) -> list[CaseResult]:
    """Run ``cases`` one after the other (each in its own subdirectory)."""
    from .matrix import row

    out = []
    for case in cases:
        r = asyncio.run(run_law_case(case, directory / case.name, speed))
        if echo:
            print(row(r), flush=True)
        out.append(r)
    return out


# ------------------------------------------------------------------------------ the grid

#: Grade-III-like pit at 320x240: S_0 of the grade III scene, S_inf for its F_inf 6.54 N
#: (C1 375 px + C2 625 px/N x 6.54 N) [px].
PIT = {"s0_px": 1215.0, "s_inf_px": 4462.5}
#: Kelvin-Voigt tau whose T_r is grade III's 27.5 s [s] (T_r = tau ln(S_inf / (0.02 S_inf ...))).
KV_GRADE3_TAU_S = 7.66
#: Fast Kelvin-Voigt tissue of the camera cases (T_r 7.2 s) and their window [s].
CAMERA_TAU_S, CAMERA_WINDOW_S = 2.0, 20.0


def law_cases() -> list[LawCase]:
    """The law group: tissues from the literature (early-stop rule on, the default), the
    camera and sensor faults on a fast Kelvin-Voigt tissue (the whole window watched), 47 s
    of recovery whose frames are not processed in time (and, as a camera fault, not
    delivered) and a run stopped 16 s into a grade-III-like recovery."""
    hold = LawCase("x", Tissue("kv")).hold_s
    cam = Tissue("kv", tau_s=CAMERA_TAU_S, **PIT)

    def camera(name: str, **kw: Any) -> LawCase:
        return LawCase(name, cam, window_s=CAMERA_WINDOW_S, stop_when_settled=False, **kw)

    return [
        LawCase("law-kv-control", Tissue("kv", tau_s=KV_GRADE3_TAU_S, **PIT)),
        LawCase("law-findley-n0.3", Tissue("findley", shape=0.3, hold_s=hold, **PIT)),
        LawCase("law-findley-n0.2", Tissue("findley", shape=0.2, hold_s=hold, **PIT)),
        LawCase("law-terzaghi-tau25s", Tissue("terzaghi", tau_s=25.0, **PIT)),
        LawCase("law-terzaghi-tau12s", Tissue("terzaghi", tau_s=12.0, **PIT)),
        LawCase("law-kww-tau6s-b0.5", Tissue("kww", tau_s=6.0, shape=0.5, **PIT)),
        LawCase("law-kww-tau3s-b0.6", Tissue("kww", tau_s=3.0, shape=0.6, **PIT)),
        LawCase("law-sls-springback-0.5", Tissue("sls", tau_s=8.0, shape=0.5, **PIT)),
        LawCase("law-sls-springback-0.25", Tissue("sls", tau_s=8.0, shape=0.25, **PIT)),
        camera("cam-led-flicker-40pct", optics=Optics(flicker_depth=0.4)),
        camera("cam-noise-20-levels", optics=Optics(noise_sigma=20.0, seed=1)),
        camera("cam-noise-10-levels-control", optics=Optics(noise_sigma=10.0, seed=1)),
        camera("cam-vignetting-strong", optics=Optics(vignetting=0.6)),
        camera("cam-every-frame-saturated", optics=Optics(gain=4.0)),
        camera("sensor-load-cell-pinned", hold_force_n=18.0, load_cell_range_n=15.74),
        LawCase(
            "stall-47s-in-recovery",
            Tissue("kv", tau_s=KV_GRADE3_TAU_S, **PIT),
            stop_when_settled=False,
            stall_rel_s=(15.0, 62.0),
        ),
        LawCase(
            "camera-gap-47s-in-recovery",
            Tissue("kv", tau_s=KV_GRADE3_TAU_S, **PIT),
            stop_when_settled=False,
            frame_gap_rel_s=(5.0, 52.0),
        ),
        LawCase(
            "stopped-16s-into-recovery",
            Tissue("kv", tau_s=KV_GRADE3_TAU_S, **PIT),
            stop_when_settled=False,
            stop_rel_s=16.0,
        ),
    ]
