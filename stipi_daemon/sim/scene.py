"""Scene files: the typed description of one simulated measurement.

This module owns the pydantic models of a scene (tissue, indenter, force profile, probe,
camera, load cell, effects), their validation (``extra="forbid"`` everywhere, effects
dispatched on ``name`` through the lazy registry) and :func:`load_scene`, which turns a
YAML file into a :class:`Scene` or raises :class:`~stipi_daemon.errors.ConfigError` naming
the file and the field path. It does not own the physics (:mod:`.physics`), rendering or
outputs; it reads files but computes nothing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.effects import effect_module, known_effects
from stipi_daemon.sim.effects.base import EffectParams
from stipi_daemon.sim.tissue.spec import TissueModelSpec
from stipi_daemon.yamlfile import load_yaml, read_utf8

__all__ = [
    "DEFAULT_JPEG_QUALITY",
    "GRADE_PRESETS",
    "CalibrationSpec",
    "CameraSpec",
    "ForceProfileSpec",
    "IndenterSpec",
    "LedSpec",
    "LoadCellSpec",
    "ProbeSpec",
    "Scene",
    "TissueSpec",
    "load_scene",
    "parse_effects",
    "parse_scene",
]

#: Phantom grades: Young's modulus [kPa] measured with the Instron (paper, Section IV.A),
#: the recovery time constant tau = eta / E [s] chosen so that the shipped probe
#: reproduces the paper's STIP-I recovery times T_r (Table I: 2.19, 8.95, 27.5, 44.4 s),
#: and the loading (creep) time constant [s]; see docs/simulator.md.
GRADE_PRESETS: dict[str, tuple[float, float, float]] = {
    "I": (355.59, 0.86, 1.0),
    "II": (266.37, 3.69, 1.0),
    "III": (221.35, 11.85, 1.0),
    "IV": (185.91, 20.16, 1.0),
}


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TissueSpec(_Model):
    """The tissue: a phantom grade, or Young's modulus with viscosity or time constant.

    ``model`` names a tissue model of :mod:`stipi_daemon.sim.tissue` and its parameters
    (docs/simulator.md, "Tissue models"); then E comes from ``grade`` or ``e_kpa``, the
    loading time constant from ``grade`` or ``loading_tau_s``, and the recovery from the
    model alone. Without it the tissue is Kelvin-Voigt with tau (or eta), as before.
    """

    grade: Literal["I", "II", "III", "IV"] | None = None
    e_kpa: float | None = Field(default=None, gt=0.0)
    eta_n_s_per_mm2: float | None = Field(default=None, gt=0.0)
    tau_s: float | None = Field(default=None, gt=0.0)
    loading_tau_s: float | None = Field(default=None, gt=0.0)
    model: TissueModelSpec | None = None

    @model_validator(mode="after")
    def _one_definition(self) -> TissueSpec:
        if self.model is not None:
            if self.tau_s is not None or self.eta_n_s_per_mm2 is not None:
                raise ValueError(
                    "with 'model', give no 'tau_s'/'eta_n_s_per_mm2' (the model's "
                    "parameters set the recovery)"
                )
            if (self.grade is None) == (self.e_kpa is None):
                raise ValueError("with 'model', give exactly one of 'grade' and 'e_kpa'")
            if self.grade is None and self.loading_tau_s is None:
                raise ValueError("with 'model' and 'e_kpa', give 'loading_tau_s'")
            return self
        if self.grade is not None:
            if self.e_kpa is not None and (self.eta_n_s_per_mm2 or self.tau_s) is None:
                raise ValueError("with 'grade', give both e_kpa and eta/tau to override, or none")
            return self
        if self.e_kpa is None:
            raise ValueError("give 'grade', or 'e_kpa' with 'eta_n_s_per_mm2' or 'tau_s'")
        if (self.eta_n_s_per_mm2 is None) == (self.tau_s is None):
            raise ValueError("give exactly one of 'eta_n_s_per_mm2' and 'tau_s'")
        return self

    @property
    def youngs_modulus_kpa(self) -> float:
        """E [kPa]."""
        if self.e_kpa is not None:
            return self.e_kpa
        assert self.grade is not None
        return GRADE_PRESETS[self.grade][0]

    @property
    def time_constant_s(self) -> float:
        """Kelvin-Voigt retardation time tau = eta / E [s] (a tissue without ``model``)."""
        if self.model is not None:
            raise ValueError(f"tissue model {self.model.name!r} has no Kelvin-Voigt tau")
        if self.tau_s is not None:
            return self.tau_s
        if self.eta_n_s_per_mm2 is not None:
            # eta [N s/mm^2] / E [N/mm^2]; E [kPa] * 1e-3 = E [N/mm^2].
            return self.eta_n_s_per_mm2 / (self.youngs_modulus_kpa * 1e-3)
        assert self.grade is not None
        return GRADE_PRESETS[self.grade][1]

    @property
    def loading_time_constant_s(self) -> float:
        """Time constant of the creep under load [s] (default: tau, a plain Kelvin-Voigt)."""
        if self.loading_tau_s is not None:
            return self.loading_tau_s
        if self.grade is not None and self.e_kpa is None:
            return GRADE_PRESETS[self.grade][2]
        return self.time_constant_s


class IndenterSpec(_Model):
    """The indenter: a flat cylinder."""

    diameter_mm: float = Field(default=15.0, gt=0.0)
    length_mm: float = Field(default=12.0, gt=0.0)


class ForceProfileSpec(_Model):
    """The operator's force profile: idle, linear approach, hold, instant release, recovery."""

    pre_s: float = Field(default=0.0, ge=0.0)
    approach_s: float = Field(default=1.0, ge=0.0)
    hold_force_n: float = Field(default=16.0, gt=0.0)
    hold_s: float = Field(default=14.0, gt=0.0)
    recovery_s: float = Field(default=105.0, gt=0.0)

    @property
    def release_s(self) -> float:
        """T_0: time of the release, the start of the recovery [s]."""
        return self.pre_s + self.approach_s + self.hold_s

    @property
    def duration_s(self) -> float:
        """Whole scene length [s]."""
        return self.release_s + self.recovery_s


class CalibrationSpec(_Model):
    """Eqs. (4)-(5) coefficients, stated at ``reference_resolution`` (pixel units)."""

    reference_resolution: tuple[int, int] = (640, 480)
    alpha1_mm_per_px2: float = Field(gt=0.0)
    alpha2_mm_per_px: float = Field(gt=0.0)
    c1_px: float = Field(ge=0.0)
    c2_px_per_n: float = Field(gt=0.0)

    @field_validator("reference_resolution")
    @classmethod
    def _positive(cls, v: tuple[int, int]) -> tuple[int, int]:
        if v[0] <= 0 or v[1] <= 0:
            raise ValueError(f"resolution must be positive, got {v[0]}x{v[1]}")
        return v


class LedSpec(_Model):
    """The LEDs at the waveguide's edge, evenly spaced."""

    count: int = Field(default=6, ge=1, le=32)
    first_angle_deg: float = 30.0
    intensity: tuple[float, ...] | None = None
    highlight_level: float = Field(default=40.0, ge=0.0, le=255.0)
    highlight_width_fraction: float = Field(default=0.12, gt=0.0, le=1.0)

    @model_validator(mode="after")
    def _intensity_count(self) -> LedSpec:
        if self.intensity is not None:
            if len(self.intensity) != self.count:
                raise ValueError(
                    f"intensity has {len(self.intensity)} values for {self.count} LEDs"
                )
            if any(not 0.0 <= v <= 2.0 for v in self.intensity):
                raise ValueError("intensity values must be in [0, 2]")
        return self

    @property
    def intensities(self) -> tuple[float, ...]:
        """Relative intensity of every LED [-]."""
        return self.intensity if self.intensity is not None else (1.0,) * self.count


class ProbeSpec(_Model):
    """The sensing probe: calibration, tip, waveguide appearance and threshold p."""

    calibration: CalibrationSpec
    tip_stiffness_n_per_mm: float = Field(default=3.0, gt=0.0)
    pitting_phase_occlusion: Literal["applied_force", "none"] = "applied_force"
    waveguide_diameter_fraction: float = Field(default=0.9, gt=0.1, le=1.0)
    waveguide_diameter_mm: float = Field(default=50.0, gt=0.0)
    threshold: int = Field(default=128, ge=1, le=254)
    background_level: float = Field(default=200.0, gt=0.0, le=255.0)
    edge_falloff_level: float = Field(default=25.0, ge=0.0, le=255.0)
    outside_level: float = Field(default=12.0, ge=0.0, le=255.0)
    occluded_level: int = Field(default=70, ge=0, le=254)
    edge_width_px: float = Field(default=2.0, gt=0.0, le=20.0)
    leds: LedSpec = LedSpec()

    @model_validator(mode="after")
    def _levels(self) -> ProbeSpec:
        if self.occluded_level > self.threshold:
            raise ValueError(
                f"occluded_level {self.occluded_level} must be <= threshold {self.threshold}"
            )
        return self


#: JPEG quality [1..100] of an ``mjpg`` camera whose scene sets no ``jpeg_quality``.
DEFAULT_JPEG_QUALITY = 95


class CameraSpec(_Model):
    """The camera. ``pixel_format``: ``gray8`` or ``bgr8`` deliver raw frames (stored
    losslessly), ``mjpg`` a JPEG of the BGR picture per frame at ``jpeg_quality``
    (default :data:`DEFAULT_JPEG_QUALITY`; only with ``mjpg``); docs/simulator.md."""

    width: int = Field(default=640, ge=64, le=7680)
    height: int = Field(default=480, ge=48, le=4320)
    fps: float = Field(default=60.0, gt=0.0, le=1000.0)
    exposure_s: float = Field(default=0.008, gt=0.0)
    pixel_format: Literal["gray8", "bgr8", "mjpg"] = "bgr8"
    jpeg_quality: int | None = Field(default=None, ge=1, le=100)

    @model_validator(mode="after")
    def _exposure(self) -> CameraSpec:
        if self.exposure_s > 1.0 / self.fps:
            raise ValueError(
                f"exposure_s {self.exposure_s} is longer than the frame period {1 / self.fps}"
            )
        if self.jpeg_quality is not None and self.pixel_format != "mjpg":
            raise ValueError(
                f"jpeg_quality applies to pixel_format mjpg only (this camera is "
                f"{self.pixel_format}: raw frames)"
            )
        return self


class LoadCellSpec(_Model):
    """FC22-like ratiometric load cell read by the MCU's ADC through a divider."""

    range_n: float = Field(default=44.48, gt=0.0)
    adc_bits: int = Field(default=10, ge=8, le=16)
    sample_rate_hz: float = Field(default=100.0, gt=0.0, le=1000.0)
    supply_v: float = Field(default=5.0, gt=0.0)
    zero_fraction: float = Field(default=0.1, ge=0.0, lt=1.0)
    span_fraction: float = Field(default=0.8, gt=0.0, le=1.0)
    divider_ratio: float = Field(default=0.66, gt=0.0, le=1.0)
    adc_reference_v: float = Field(default=3.3, gt=0.0)
    mcu_boot_offset_us: int = Field(default=0, ge=0)

    @model_validator(mode="after")
    def _fraction_sum(self) -> LoadCellSpec:
        if self.zero_fraction + self.span_fraction > 1.0:
            raise ValueError("zero_fraction + span_fraction must be <= 1 (output within supply)")
        return self


class Scene(_Model):
    """One simulated measurement."""

    name: str = Field(min_length=1)
    description: str = ""
    seed: int = Field(default=0, ge=0)
    tissue: TissueSpec
    indenter: IndenterSpec = IndenterSpec()
    force_profile: ForceProfileSpec = ForceProfileSpec()
    probe: ProbeSpec
    camera: CameraSpec = CameraSpec()
    load_cell: LoadCellSpec = LoadCellSpec()
    effects: tuple[EffectParams, ...] = ()

    @field_validator("effects", mode="before")
    @classmethod
    def _effects(cls, v: Any) -> Any:
        if isinstance(v, list | tuple) and any(not isinstance(e, EffectParams) for e in v):
            parsed, errors = parse_effects(v)
            if errors:
                raise ValueError("; ".join(f"effects[{e}" for e in errors))
            return tuple(parsed)
        return v

    @model_validator(mode="after")
    def _one_jpeg_quality(self) -> Scene:
        named = [e for e in self.effects if e.name == "jpeg_compression"]
        if named and self.camera.jpeg_quality is not None:
            raise ValueError(
                "camera.jpeg_quality and the jpeg_compression effect's quality both set "
                "the JPEG quality: give one"
            )
        return self

    def with_camera(
        self, *, width: int | None = None, height: int | None = None, fps: float | None = None
    ) -> Scene:
        """A copy with another resolution or frame rate (exposure clipped to the period)."""
        cam = self.camera.model_dump()
        if width is not None:
            cam["width"] = width
        if height is not None:
            cam["height"] = height
        if fps is not None:
            cam["fps"] = fps
            cam["exposure_s"] = min(cam["exposure_s"], 1.0 / fps)
        return self.model_copy(update={"camera": CameraSpec.model_validate(cam)})

    def with_effects(self, effects: Sequence[Mapping[str, Any] | EffectParams]) -> Scene:
        """A copy with another effect list (validated like a scene file's)."""
        parsed, errors = parse_effects(list(effects))
        if errors:
            raise ConfigError("\n".join(f"{self.name}: effects[{e}" for e in errors))
        return self.model_copy(update={"effects": tuple(parsed)})


def _loc(loc: Sequence[int | str]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def parse_effects(raw: Sequence[Any]) -> tuple[list[EffectParams], list[str]]:
    """Validate a scene's effect list entry by entry.

    Returns the parsed parameters and error lines of the form ``"1].name: msg"`` relative
    to ``effects[`` (so that callers prefix their own path).
    """
    parsed: list[EffectParams] = []
    errors: list[str] = []
    for i, item in enumerate(raw):
        if isinstance(item, EffectParams):
            parsed.append(item)
            continue
        if not isinstance(item, Mapping):
            errors.append(f"{i}]: an effect must be a mapping with a 'name', got {item!r}")
            continue
        name = item.get("name")
        if not isinstance(name, str):
            errors.append(f"{i}].name: missing effect name (known: {', '.join(known_effects())})")
            continue
        try:
            module = effect_module(name)
        except ConfigError as exc:
            errors.append(f"{i}].name: {exc}")
            continue
        try:
            parsed.append(module.Params.model_validate(dict(item)))
        except ValidationError as exc:
            for err in exc.errors():
                errors.append(f"{i}].{_loc(err['loc'])}: {err['msg']}")
    return parsed, errors


def parse_scene(data: Any, source: str) -> Scene:
    """Validate a scene mapping; ``source`` (file name) prefixes every error.

    Raises
    ------
    ConfigError
        One line, every problem as ``field.path: message`` after ``source: `` and
        separated by ``; ``; a daemon config given as a scene is said to be one.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: a scene must be a mapping, got {type(data).__name__}")
    if data.get("format") == "stipi-daemon-config":
        raise ConfigError(
            f"{source}: is a daemon config (format stipi-daemon-config), not a scene; give it "
            "with --config, and a scene (e.g. configs/scenes/grade2.yaml) with --scene"
        )
    problems: list[str] = []
    raw = dict(data)
    raw_effects = raw.pop("effects", [])
    if raw_effects is None:
        raw_effects = []
    if not isinstance(raw_effects, list):
        problems.append(f"{source}: effects: must be a list")
        raw_effects = []
    effects, effect_errors = parse_effects(raw_effects)
    problems.extend(f"{source}: effects[{e}" for e in effect_errors)
    try:
        scene = Scene.model_validate({**raw, "effects": tuple(effects)})
    except ValidationError as exc:
        for err in exc.errors():
            msg = err["msg"].removeprefix("Value error, ")
            problems.append(f"{source}: {_loc(err['loc']) or '(scene)'}: {msg}")
        scene = None
    if problems or scene is None:
        rest = [p.removeprefix(f"{source}: ") for p in problems[1:]]
        raise ConfigError("; ".join([problems[0], *rest]))
    return scene


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene YAML file.

    Raises
    ------
    ConfigError
        The file cannot be read or parsed, or a field is missing, unknown or out of range;
        the message names the file and the field path.
    """
    p = Path(path)
    # a key given twice is an error naming its line; bytes not UTF-8 one naming its offset
    data = load_yaml(read_utf8(p, "scene file"), p.name)
    return parse_scene(data, p.name)
