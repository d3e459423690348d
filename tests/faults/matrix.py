"""Fault-injection matrix: the real daemon on simulated devices, every result against truth.

Each :class:`Case` is one simulated measurement (a grade scene of ``configs/scenes``, or a
tissue with a given time constant tau) with one timing or imaging fault: a camera gap, a
dark or bright outlier frame, a corrupt (unmeasurable) frame, a force dropout, a release
before the daemon's 15 s pitting timer, either pitting-phase occlusion mode. :func:`run_case`
runs the real daemon (:func:`stipi_daemon.app.daemon.run_daemon`: emulated Feather on a
pty, simulator camera, accelerated clock) on it and :func:`classify` holds every primary
quantity of ``summary.json`` to the scene's ground truth (:func:`stipi_daemon.sim.ground_truth`
over the window the daemon watched):

* ``ok``: reported valid and within its tolerance (:data:`TOLERANCES`);
* ``flagged`` / ``invalid``: the summary says so (its ``validity`` mapping; a summary
  without one is read the old way: a reported value is ``flagged`` when a flag concerns
  it, else valid; a missing value is ``invalid``);
* ``SILENT MISS``: reported valid and outside its tolerance, the outcome that must never
  happen (issue 14).

The fast subset runs in the test suite (``tests/faults/test_matrix.py``); the long form
is ``python -m tests.faults.matrix --long --out docs/fault_matrix.json`` (docs/reliability.md,
"Fault-injection matrix"). ``--laws`` runs the group of recoveries from literature laws and
camera faults rendered by the test (``tests/faults/law_matrix.py``, issue 37).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import yaml

from stipi_daemon.analysis.severity import classify_decay_rate, load_reference
from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import DaemonHandles, run_daemon
from stipi_daemon.sim import ground_truth
from stipi_daemon.sim.physics import SceneModel
from stipi_daemon.sim.scene import GRADE_PRESETS, Scene, parse_scene
from stipi_daemon.storage import SessionReader

if TYPE_CHECKING:
    from .law_matrix import LawCase

REPO_ROOT = Path(__file__).resolve().parents[2]
SCENES = REPO_ROOT / "configs" / "scenes"

#: Primary quantities (summary ``validity`` keys) -> (tolerance kind, value) and symbol.
#: "rel": relative error; "rel_or_frames": relative error or a number of frame periods,
#: whichever is larger; "equal": the class must match.
TOLERANCES: dict[str, tuple[Literal["rel", "rel_or_frames", "equal"], float]] = {
    "depth_mm": ("rel", 0.05),
    "rebound_force_n": ("rel", 0.05),
    "recovery_time_s": ("rel_or_frames", 0.05),
    "elasticity_kpa": ("rel", 0.05),
    "viscosity_n_s_per_mm2": ("rel", 0.10),
    "severity": ("equal", 0.0),
}
#: Frame periods T_r may be off by (its resolution is one frame, on each end) [-].
T_R_FRAMES = 2.0
SYMBOLS = {
    "depth_mm": "D_p",
    "rebound_force_n": "F_r",
    "recovery_time_s": "T_r",
    "elasticity_kpa": "E",
    "viscosity_n_s_per_mm2": "eta",
    "severity": "class",
}
OUTCOMES = ("ok", "flagged", "invalid", "SILENT MISS", "error")

#: Force band the daemon's pitting timer starts in (MeasurementConfig defaults) [N].
BAND_LOW_N = 16.0 - 1.5
#: The daemon's pitting time, counted from the first in-band sample [s].
PITTING_S = 15.0
#: Scene time recorded after the daemon's recovery window ends [s].
MARGIN_S = 4.0
#: Frame size of the matrix's scenes [px] (60 fps kept; a smaller frame costs less CPU).
FRAME_SIZE = (320, 240)
#: Largest shortfall of the last recorded frame before the window's end [s].
MAX_FRAME_LAG_S = 0.5
#: How :func:`camera_kept_up` starts its answer.
LAG_ERROR = "the simulated camera fell behind"
#: The paper's recovery window, over which the severity truth is taken [s].
PAPER_WINDOW_S = 105.0


@dataclass(frozen=True)
class Case:
    """One run of the matrix; every time marked ``rel`` is relative to the true T_0 [s].

    Attributes
    ----------
    name : str
        Unique name.
    grade : str
        Phantom grade ("I".."IV"): its scene file ``configs/scenes/grade{n}.yaml``.
    tau_s : float, optional
        Recovery time constant of the tissue [s] (E stays the grade's); default the grade's.
    occlusion : "applied_force" or "none"
        The scene's ``probe.pitting_phase_occlusion``.
    release_lead_s : float
        How long before the daemon's pitting timer ends the operator releases [s]
        (negative: after it; -0.6 is an operator reacting to the release prompt).
    window_s : float
        Recovery the daemon watches (``measurement.recovery_max_s``) [s].
    pre_s : float
        Idle time before the approach [s].
    frame_gap_rel_s : tuple of float, optional
        Span without frames (``frame_gap``), relative to T_0 [s].
    dark_rel_s, bright_rel_s, corrupt_rel_s : tuple of float
        Times of single dark, bright and corrupt frames relative to T_0 [s].
    force_dropout_rel_s : tuple of float, optional
        Span without force samples (``force_dropout``), relative to T_0 [s].
    seed : int
        Scene seed.
    """

    name: str
    grade: str = "I"
    tau_s: float | None = None
    occlusion: Literal["applied_force", "none"] = "applied_force"
    release_lead_s: float = -0.6
    window_s: float = 10.0
    pre_s: float = 0.0
    frame_gap_rel_s: tuple[float, float] | None = None
    dark_rel_s: tuple[float, ...] = ()
    bright_rel_s: tuple[float, ...] = ()
    corrupt_rel_s: tuple[float, ...] = ()
    force_dropout_rel_s: tuple[float, float] | None = None
    seed: int = 0

    @property
    def approach_s(self) -> float:
        """Linear approach to 16 N [s] (the shipped scenes')."""
        return 1.0

    @property
    def hold_s(self) -> float:
        """Hold after the approach that releases ``release_lead_s`` before the timer [s]."""
        band_entry_s = self.approach_s * BAND_LOW_N / 16.0
        return band_entry_s + PITTING_S - self.release_lead_s - self.approach_s

    @property
    def t0_s(self) -> float:
        """True release time T_0 [s]."""
        return self.pre_s + self.approach_s + self.hold_s

    def effects(self) -> list[dict[str, Any]]:
        """The scene's fault effects, at absolute scene times."""
        t0 = self.t0_s
        out: list[dict[str, Any]] = []
        if self.frame_gap_rel_s is not None:
            a, b = self.frame_gap_rel_s
            out.append({"name": "frame_gap", "t_start_s": t0 + a, "t_end_s": t0 + b})
        if self.dark_rel_s or self.bright_rel_s:
            out.append(
                {
                    "name": "outlier_frames",
                    "dark_times_s": [t0 + t for t in self.dark_rel_s],
                    "bright_times_s": [t0 + t for t in self.bright_rel_s],
                }
            )
        if self.corrupt_rel_s:
            out.append({"name": "corrupt_frames", "times_s": [t0 + t for t in self.corrupt_rel_s]})
        if self.force_dropout_rel_s is not None:
            a, b = self.force_dropout_rel_s
            out.append({"name": "force_dropout", "t_start_s": t0 + a, "t_end_s": t0 + b})
        return out

    def scene_doc(self) -> dict[str, Any]:
        """The scene as a YAML mapping: the grade's file with this case's changes."""
        doc: dict[str, Any] = yaml.safe_load(
            (SCENES / f"grade{_arabic(self.grade)}.yaml").read_text()
        )
        doc["name"] = self.name
        doc["seed"] = self.seed
        if self.tau_s is not None:
            doc["tissue"] = {
                "e_kpa": GRADE_PRESETS[self.grade][0],
                "tau_s": self.tau_s,
                "loading_tau_s": GRADE_PRESETS[self.grade][2],
            }
        doc["force_profile"].update(
            pre_s=self.pre_s,
            approach_s=self.approach_s,
            hold_s=round(self.hold_s, 6),
            recovery_s=self.window_s + MARGIN_S,
        )
        doc["probe"]["pitting_phase_occlusion"] = self.occlusion
        doc["camera"].update(width=FRAME_SIZE[0], height=FRAME_SIZE[1])
        doc["effects"] = self.effects()
        return doc


def _arabic(grade: str) -> int:
    return {"I": 1, "II": 2, "III": 3, "IV": 4}[grade]


# ------------------------------------------------------------------------------ truth


def truth(case: Case, scene: Scene) -> dict[str, dict[str, Any]]:
    """Ground truth of each primary quantity (:data:`TOLERANCES` keys) for ``case``.

    Each entry holds ``value`` (the paper's definition on the scene's model over the
    window the daemon watches, ``window_s``) and the accepted range ``low``..``high``:

    * D_p, E, eta: S_0 is observed on the first frame at or after T_0, up to one frame
      period late, so the range spans the model's values at T_0 and one frame later
      (eta = E T_r with the true T_r), widened by the relative tolerance;
    * F_r: the relative tolerance; T_r: the relative tolerance or :data:`T_R_FRAMES`
      frame periods, whichever is larger;
    * the severity class is that of the tissue, from T_r over the paper's 105 s window (a
      recovery too slow to settle in a short window is still the tissue it is); it must
      be equal.
    """

    def over(window_s: float) -> Any:
        fp = scene.force_profile.model_copy(update={"recovery_s": window_s})
        return ground_truth(scene.model_copy(update={"force_profile": fp}))

    gt = over(case.window_s)
    paper = over(PAPER_WINDOW_S)
    frame_s = 1.0 / scene.camera.fps
    model = SceneModel(scene)
    s_late = float(model.occluded_area_px([gt.t0_s + frame_s])[0])
    d_late = scene.indenter.length_mm - model.calibration.depth_change_mm(s_late)
    e_late = gt.elasticity_kpa * gt.depth_mm / d_late

    def band(quantity: str, *values: float) -> dict[str, Any]:
        kind, tol = TOLERANCES[quantity]
        lo, hi = min(values), max(values)
        margin = (tol * lo, tol * hi)
        if kind == "rel_or_frames":
            margin = (max(margin[0], T_R_FRAMES * frame_s), max(margin[1], T_R_FRAMES * frame_s))
        return {"value": values[0], "low": lo - margin[0], "high": hi + margin[1]}

    severity: str | None = None
    if paper.recovery_time_s > 0.0:
        severity = classify_decay_rate(1.0 / paper.recovery_time_s, load_reference()).severity
    return {
        "depth_mm": band("depth_mm", gt.depth_mm, d_late),
        "rebound_force_n": band("rebound_force_n", gt.rebound_force_n),
        "recovery_time_s": band("recovery_time_s", gt.recovery_time_s),
        "elasticity_kpa": band("elasticity_kpa", gt.elasticity_kpa, e_late),
        "viscosity_n_s_per_mm2": band(
            "viscosity_n_s_per_mm2",
            gt.viscosity_n_s_per_mm2,
            e_late * 1e-3 * gt.recovery_time_s,
        ),
        "severity": {"value": severity, "low": None, "high": None},
    }


# ------------------------------------------------------------------------------ reading


def reported(summary: dict[str, Any]) -> dict[str, Any]:
    """The value of each primary quantity in ``summary`` (None where absent)."""
    res = summary.get("results") or {}
    pit = res.get("pitting") or {}
    paper = res.get("paper_estimator") or {}
    sev = ((res.get("severity") or {}).get("paper_estimator")) or {}
    return {
        "depth_mm": pit.get("depth_mm"),
        "rebound_force_n": pit.get("rebound_force_n"),
        "recovery_time_s": pit.get("recovery_time_s"),
        "elasticity_kpa": paper.get("elasticity_kpa"),
        "viscosity_n_s_per_mm2": paper.get("viscosity_n_s_per_mm2"),
        "severity": sev.get("severity"),
    }


def validity(summary: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """``summary["validity"]`` restricted to the primary quantities.

    A summary written before the validity schema is read the old way: a missing value is
    ``invalid``; a reported one is ``flagged`` when a flag concerns it (the pitting
    parameters' flags for D_p, F_r, T_r and E, eta which derive from them; for the class
    also the paper estimator's severity flags), else ``valid``. The results' overall
    ``flags`` are not used: they merge every estimator's (a fitted-recovery or severity
    flag would mark D_p flagged).
    """
    if isinstance(summary.get("validity"), dict):
        v = summary["validity"]
        return {
            q: v.get(q) or {"status": "invalid", "flags": [], "reason": "missing from validity"}
            for q in TOLERANCES
        }
    res = summary.get("results") or {}
    common = list((res.get("pitting") or {}).get("flags") or [])
    sev = ((res.get("severity") or {}).get("paper_estimator")) or {}
    values = reported(summary)
    out: dict[str, dict[str, Any]] = {}
    for q in TOLERANCES:
        flags = common + (list(sev.get("flags") or []) if q == "severity" else [])
        if values[q] is None:
            out[q] = {"status": "invalid", "flags": flags, "reason": "not reported"}
        elif flags:
            out[q] = {"status": "flagged", "flags": flags, "reason": "flags (old summary)"}
        else:
            out[q] = {"status": "valid", "flags": [], "reason": None}
    return out


def within(quantity: str, value: Any, true: dict[str, Any]) -> tuple[bool, float | None]:
    """Whether ``value`` lies in the accepted range of ``true`` (:func:`truth`), and its
    error relative to the true value."""
    if TOLERANCES[quantity][0] == "equal":
        return value == true["value"], None
    if value is None or not math.isfinite(float(value)):
        return False, None
    v, t = float(value), float(true["value"])
    rel = (v - t) / t if t != 0.0 else math.inf
    return bool(true["low"] <= v <= true["high"]), rel


def classify(summary: dict[str, Any], true: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Outcome of each primary quantity: ``ok``, ``flagged``, ``invalid`` or ``SILENT MISS``."""
    values = reported(summary)
    valid = validity(summary)
    out: dict[str, dict[str, Any]] = {}
    for q in TOLERANCES:
        good, rel = within(q, values[q], true[q])
        status = valid[q]["status"]
        if status in ("flagged", "invalid"):
            outcome = status
        elif values[q] is None:
            outcome = "invalid"  # not reported: nothing wrong is shown as right
        elif true[q]["value"] is None:
            outcome = "ok"  # nothing to hold it to (a truth without recovery)
        else:
            outcome = "ok" if good else "SILENT MISS"
        out[q] = {
            "outcome": outcome,
            "status": status,
            "value": values[q],
            "truth": true[q]["value"],
            "accepted": [true[q]["low"], true[q]["high"]],
            "rel_error": rel,
            "within_tolerance": good,
            "flags": list(valid[q].get("flags") or []),
            "reason": valid[q].get("reason"),
        }
    return out


# ------------------------------------------------------------------------------ running


@dataclass
class CaseResult:
    """One case's run: how the daemon ended and the outcome of every primary quantity."""

    case: Case | LawCase
    phase: str = ""
    verdict: str = ""
    quantities: dict[str, dict[str, Any]] = field(default_factory=dict)
    error: str | None = None
    wall_s: float = 0.0
    speed: float = 0.0
    recorded: dict[str, float] = field(default_factory=dict)

    @property
    def silent_misses(self) -> list[str]:
        """Quantities reported valid and outside their tolerance."""
        return [q for q, r in self.quantities.items() if r["outcome"] == "SILENT MISS"]

    def to_json(self) -> dict[str, Any]:
        return {
            "case": asdict(self.case),
            "phase": self.phase,
            "verdict": self.verdict,
            "quantities": self.quantities,
            "error": self.error,
            "wall_s": self.wall_s,
            "speed": self.speed,
            "recorded": self.recorded,
        }


def write_case(case: Case, directory: Path, speed: float) -> tuple[Path, Scene]:
    """Scene file and daemon config of ``case`` in ``directory``; returns (config, scene).

    The daemon runs as configs/demo.yaml (emulated probe on a pty, simulator camera), with
    the case's recovery window watched whole (``stop_when_settled: false``) so that it is
    the window the truth is taken over.
    """
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
            "stop_when_settled": False,
            "settle_hold_s": min(10.0, case.window_s / 2.0),
        },
        "analysis": {"indenter_radius_mm": 7.5},
        "storage": {"root": str(directory / "sessions"), "min_free_mb": 0},
        "run": {"speed": speed},
    }
    config_path = directory / "config.yaml"
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    return config_path, scene


def recorded(session: Path) -> dict[str, float]:
    """What the session holds of the injected faults: the last frame's capture time
    ``last_frame_s`` [s], and the frames and force samples recorded as lost
    (``frames_lost``, ``samples_lost``) [-]."""
    with SessionReader(session) as reader:
        t = reader.frames()["t_capture_host_s"]
        gaps = reader.gaps()
    return {
        "last_frame_s": float(t.max()) if len(t) else -math.inf,
        "frames_lost": float(gaps["count"][gaps["stream"] == "frames"].sum()),
        "samples_lost": float(gaps["count"][gaps["stream"] == "force"].sum()),
    }


def camera_kept_up(facts: dict[str, float], summary: dict[str, Any]) -> str | None:
    """None when the recorded frames reach the end of the recovery window, else why not.

    The simulated camera renders a scene with frame effects frame by frame; when the
    machine cannot render at ``fps * speed`` its frames fall behind the session clock
    and those not yet delivered when the session ends are missing without a gap record.
    The run then does not measure what the case claims, and is reported as an error (run
    at a lower speed). ``facts`` is :func:`recorded`.
    """
    end = (summary.get("measurement") or {}).get("t_end_s")
    last = facts["last_frame_s"]
    if end is not None and last < float(end) - MAX_FRAME_LAG_S:
        return (
            f"{LAG_ERROR}: frames end at {last:.2f} s, the recovery "
            f"window at {float(end):.2f} s (run at a lower speed)"
        )
    return None


def _injector(case: Case) -> Any:
    """``on_running`` callback producing the case's force dropout on the emulated link.

    The serial emulator's firmware samples every tick (the scene's lost samples are read
    from the model), so the dropout is made where a real one happens: nothing crosses the
    link from T_0 + a to T_0 + b (``EmulatedFeather.silence``); the firmware's ring
    overflows and the host sees the samples missing.
    """
    span = case.force_dropout_rel_s
    if span is None:
        return None

    async def inject(h: DaemonHandles) -> None:
        while h.camera.camera.t0_s is None:
            await asyncio.sleep(0.01)
        origin = float(h.camera.camera.t0_s)
        await h.clock.sleep_until(origin + case.t0_s + span[0])
        h.probe.transport.feather.silence(span[1] - span[0])

    return inject


async def run_case(
    case: Case, directory: Path, speed: float = 6.0, *, min_speed: float = 1.0
) -> CaseResult:
    """Run the real daemon on ``case`` in ``directory`` and classify its results.

    When the simulated camera falls behind the clock (:func:`camera_kept_up`, a loaded
    machine) the case is run again at half the speed, down to ``min_speed``, so that the
    result measures the fault and not the CPU's spare capacity.
    """
    while True:
        result = await _run_once(case, directory / f"x{speed:g}", speed)
        if result.error is None or not result.error.startswith(LAG_ERROR) or speed / 2 < min_speed:
            return result
        speed /= 2


async def _run_once(case: Case, directory: Path, speed: float) -> CaseResult:
    config_path, scene = write_case(case, directory, speed)
    result = CaseResult(case, speed=speed)
    t = time.monotonic()
    try:
        outcome = await run_daemon(load_config(config_path), quiet=True, on_running=_injector(case))
    except Exception as exc:  # a crash is reported as such, never as a result
        result.error = f"{type(exc).__name__}: {exc}"
        result.quantities = {q: {"outcome": "error"} for q in TOLERANCES}
        return result
    finally:
        result.wall_s = time.monotonic() - t
    summary = outcome.summary
    result.phase = str(outcome.phase)
    result.recorded = recorded(outcome.session_dir)
    result.error = camera_kept_up(result.recorded, summary)
    verdict = summary.get("verdict")
    result.verdict = (
        str(verdict.get("status"))
        if isinstance(verdict, dict)
        else (f"{summary.get('status')} (no verdict)")
    )
    result.quantities = classify(summary, truth(case, scene))
    return result


def run_cases(
    cases: Sequence[Case], directory: Path, speed: float, *, echo: bool = False
) -> list[CaseResult]:
    """Run ``cases`` one after the other (each in its own subdirectory)."""
    out = []
    for case in cases:
        r = asyncio.run(run_case(case, directory / case.name, speed))
        if echo:
            print(row(r), flush=True)
        out.append(r)
    return out


# ------------------------------------------------------------------------------ grids

#: hold_s 14.0 after a 1 s approach, as the shipped grade scenes held until they were given
#: an operator's 1.1 s past the prompt (16 s): the release comes this long before the
#: daemon's timer, which starts at 14.5 N, 0.906 s into the approach, within its 1 s grace [s].
EARLY_14S_HOLD_LEAD_S = BAND_LOW_N / 16.0


def fast_cases() -> list[Case]:
    """The test suite's subset: each fault kind once, and the cases issue 14 found."""
    return [
        Case("release-0.9s-early-occlusion-none", "II", occlusion="none",
             release_lead_s=0.9, window_s=15.0),
        Case("release-at-timer", "I", release_lead_s=0.0),
        Case("gap-18.8-20.0-release-19.5", "I", pre_s=4.5, release_lead_s=EARLY_14S_HOLD_LEAD_S,
             frame_gap_rel_s=(-0.7, 0.5)),
        Case("gap-0.5s-at-T0+1s", "II", window_s=15.0, frame_gap_rel_s=(1.0, 1.5)),
        Case("dark-frame-mid-recovery", "II", window_s=15.0, dark_rel_s=(5.0,)),
        Case("bright-frame-after-T0", "I", bright_rel_s=(0.01,)),
        Case("corrupt-frame-after-T0", "I", corrupt_rel_s=(0.01,)),
        Case("force-dropout-over-release", "I", force_dropout_rel_s=(-0.5, 0.5)),
        Case("tau-1e4s-window-10s", "IV", tau_s=1e4, window_s=10.0),
        Case("tau-1s-occlusion-none", "I", tau_s=1.0, occlusion="none"),
    ]  # fmt: skip


#: Recovery window of the long form per grade: about 3 T_r, at most the paper's 105 s [s].
LONG_WINDOW_S = {"I": 15.0, "II": 30.0, "III": 90.0, "IV": 105.0}


def long_cases() -> list[Case]:
    """The documented grid (docs/reliability.md, "Fault-injection matrix")."""
    out: list[Case] = []
    occl: tuple[Literal["applied_force", "none"], ...] = ("applied_force", "none")
    for g in ("I", "II", "III", "IV"):
        for o in occl:
            for lead in (-0.6, 0.0, 0.25, 0.5, 0.9, 1.0):
                out.append(
                    Case(
                        f"release-{g}-{o}-lead{lead:+.2f}s",
                        g,
                        occlusion=o,
                        release_lead_s=lead,
                        window_s=LONG_WINDOW_S[g],
                    )
                )
    for g, o in (("I", "applied_force"), ("II", "applied_force"), ("II", "none")):
        for d in (0.1, 0.5, 1.0, 2.0):
            for a in (-1.0, -0.5, -0.05, 0.0, 0.5, 1.0, 2.0):
                out.append(
                    Case(
                        f"gap-{g}-{o}-{d:g}s-at{a:+g}s",
                        g,
                        occlusion=o,
                        window_s=LONG_WINDOW_S[g],
                        frame_gap_rel_s=(a, a + d),
                    )
                )
    for g in ("I", "II", "IV"):
        w = LONG_WINDOW_S[g]
        for kind in ("dark", "bright"):
            for t in (0.01, 0.5, 1.0, 2.0, 5.0, w / 2, w - 1.0):
                times: dict[str, Any] = {f"{kind}_rel_s": (t,)}
                out.append(Case(f"{kind}-{g}-at{t:+g}s", g, window_s=w, **times))
    for g in ("I", "IV"):
        for t in (-1 / 60, 0.01, 0.03, 0.5, 2.0):
            out.append(
                Case(f"corrupt-{g}-at{t:+.3f}s", g, window_s=LONG_WINDOW_S[g], corrupt_rel_s=(t,))
            )
    for g in ("I", "II"):
        for a, b in ((-3.0, -2.0), (-1.0, 0.0), (-0.5, 0.5), (-0.2, 0.3), (0.0, 1.0), (1.0, 3.0)):
            out.append(
                Case(
                    f"force-dropout-{g}-{a:+g}..{b:+g}s",
                    g,
                    window_s=LONG_WINDOW_S[g],
                    force_dropout_rel_s=(a, b),
                )
            )
    for o in occl:
        for tau in (1.0, 3.0, 10.0, 30.0, 100.0, 1e3, 1e4):
            out.append(Case(f"tau-{tau:g}s-{o}", "IV", tau_s=tau, occlusion=o, window_s=105.0))
    return out  # fmt: skip


# ------------------------------------------------------------------------------ report

_SHORT = {"ok": "ok", "flagged": "flag", "invalid": "inv", "SILENT MISS": "MISS", "error": "ERR"}


def row(r: CaseResult) -> str:
    """One line of the table: case, how it ended, each quantity's outcome (and error)."""
    cells = []
    for q, v in r.quantities.items():
        rel = v.get("rel_error")
        err = f"{100 * rel:+.1f}%" if isinstance(rel, float) and math.isfinite(rel) else ""
        cells.append(f"{SYMBOLS[q]}={_SHORT[v['outcome']]}{'(' + err + ')' if err else ''}")
    end = r.error or f"{r.phase}/{r.verdict}"
    return f"{r.case.name:42s} {end:28s} " + " ".join(cells)


def totals(results: Sequence[CaseResult]) -> dict[str, int]:
    """How many quantities ended in each outcome."""
    out = dict.fromkeys(OUTCOMES, 0)
    for r in results:
        for v in r.quantities.values():
            out[v["outcome"]] += 1
    return out


def report_json(results: Sequence[CaseResult], speed: float, grid: str) -> dict[str, Any]:
    """The figures docs/reliability.md quotes, with every case's details."""
    return {
        "format": "stipi-fault-matrix/1",
        "grid": grid,
        "speed": speed,
        "frame_size_px": list(FRAME_SIZE),
        "tolerances": {q: {"kind": k, "value": v} for q, (k, v) in TOLERANCES.items()},
        "t_r_frames": T_R_FRAMES,
        "cases_run": len(results),
        "totals": totals(results),
        "silent_misses": [f"{r.case.name}: {SYMBOLS[q]}" for r in results for q in r.silent_misses],
        "errors": [f"{r.case.name}: {r.error}" for r in results if r.error],
        "cases": [r.to_json() for r in results],
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Run a grid, print the table and the totals, optionally write the JSON figures."""
    ap = argparse.ArgumentParser(prog="python -m tests.faults.matrix", description=__doc__)
    ap.add_argument("--long", action="store_true", help="the full grid (default: fast subset)")
    ap.add_argument(
        "--laws",
        action="store_true",
        help="the literature-law and camera-fault group (tests/faults/law_matrix.py)",
    )
    ap.add_argument("--every", type=int, default=1, help="run every N-th case of the grid")
    ap.add_argument("--match", default="", help="run only cases whose name contains this")
    ap.add_argument("--speed", type=float, default=6.0, help="session clock speed [-]")
    ap.add_argument("--out", type=Path, help="write the figures as JSON here")
    ap.add_argument("--workdir", type=Path, help="keep the sessions here (default: temporary)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="stipi-faults-") as tmp:
        work = args.workdir or Path(tmp)
        if args.laws:
            from .law_matrix import law_cases, run_law_cases

            laws = [c for c in law_cases()[:: max(1, args.every)] if args.match in c.name]
            results = run_law_cases(laws, work, args.speed, echo=True)
        else:
            grid = long_cases() if args.long else fast_cases()
            cases = [c for c in grid[:: max(1, args.every)] if args.match in c.name]
            results = run_cases(cases, work, args.speed, echo=True)
    doc = report_json(
        results,
        args.speed,
        ("laws" if args.laws else "long" if args.long else "fast")
        + (f" every {args.every}" if args.every > 1 else "")
        + (f" matching {args.match!r}" if args.match else ""),
    )
    print(json.dumps(doc["totals"]))
    for line in doc["silent_misses"] + doc["errors"]:
        print(line)
    if args.out:
        args.out.write_text(json.dumps(doc, indent=1, default=float) + "\n")
    return 1 if doc["silent_misses"] or doc["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())
