"""The daemon's configuration file (``stipi-daemon --config FILE``), loaded once, typed.

This module owns the schema of the YAML file a lab edits: the probe (``probe.transport``:
serial, BLE or an emulated probe on a pty, plus rate and LED level), the camera (V4L2, a
video file or the simulator), imaging settings (threshold and ROI of Eqs. 1-2), the
calibration file, the state machine's thresholds (``measurement``), the analysis
settings, storage and the run speed. It validates everything with pydantic (unknown keys
are errors) and reports problems as one :class:`~stipi_daemon.errors.ConfigError` line
naming the file and the field path. Paths inside the file are resolved relative to the
file. It does not open devices or files other than the config itself. Each transport's
and camera's own options live in their modules (:mod:`stipi_daemon.probe.transports`,
:mod:`stipi_daemon.cameras`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from stipi_daemon.analysis.imaging import ROI
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.cameras import CameraConfig
from stipi_daemon.errors import ConfigError
from stipi_daemon.measurement.state_machine import MeasurementConfig
from stipi_daemon.probe.transports import TransportConfig

__all__ = [
    "CONFIG_FORMAT",
    "CONFIG_VERSION",
    "DaemonConfig",
    "ImagingSettings",
    "ProbeSettings",
    "RunSettings",
    "StorageSettings",
    "load_config",
]

CONFIG_FORMAT = "stipi-daemon-config"
CONFIG_VERSION = 1


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ProbeSettings(_Model):
    """The probe: its link and what to configure on it.

    Attributes
    ----------
    transport : TransportConfig
        ``serial``, ``ble`` or ``emulated`` (see :mod:`stipi_daemon.probe.transports`).
    rate_hz : int
        Load-cell sample rate to configure [Hz], 16..1000.
    led_level : int
        LED PWM duty to configure, 0..255 (kept constant for the run).
    heartbeat_timeout_s : float
        No frame for this long means the link is lost [s].
    reconnect_total_s : float
        Give up reconnecting after this long [s].
    zero_counts, span_un_per_count : int or None
        Load-cell calibration [counts], [uN/count] used when the probe has none stored.
    """

    transport: TransportConfig
    rate_hz: int = Field(100, ge=16, le=1000)
    led_level: int = Field(255, ge=0, le=255)
    heartbeat_timeout_s: float = Field(2.5, gt=0.0, allow_inf_nan=False)
    reconnect_total_s: float = Field(30.0, gt=0.0, allow_inf_nan=False)
    zero_counts: int | None = Field(None, ge=0, le=65535)
    span_un_per_count: int | None = None


class RunSettings(_Model):
    """How the run is paced.

    Attributes
    ----------
    speed : float
        Session seconds per wall second. 1 for real devices; simulated devices (emulated
        probe, simulator camera) may run faster (the demo uses 4). ``--realtime`` forces 1.
    max_lag_s : float
        Longest the daemon may fall behind the camera [s of session time]: the lag is the
        session time when a frame is measured minus its capture time. Frames measured more
        than half of it late are not measured but recorded as gaps (reason
        ``processing_behind``); a lag above it ends the run with a fault (one line: lower
        ``run.speed``). Samples and frames are fed to the measurement no further ahead
        than the camera, so the session never ends while frames of its window are queued.
    """

    speed: float = Field(1.0, gt=0.0, le=1000.0, allow_inf_nan=False)
    max_lag_s: float = Field(5.0, gt=0.0, le=60.0, allow_inf_nan=False)


class ImagingSettings(_Model):
    """Eqs. (1)-(2) settings.

    Attributes
    ----------
    threshold_p : int or None
        Threshold level p of Eq. (1), 0..255. ``None``: the calibration's ``threshold_p``
        or, for the simulator camera, the scene's.
    roi : ROI or None
        Region of interest; ``None``: for the simulator camera, the scene's waveguide
        disc, otherwise the whole frame.
    saturation_limit_fraction : float
        Fraction of ROI pixels at 255 above which a frame is flagged saturated [-].
    """

    threshold_p: int | None = Field(None, ge=0, le=255)
    roi: ROI | None = None
    saturation_limit_fraction: float = Field(0.01, ge=0.0, le=1.0)


class StorageSettings(_Model):
    """Where and how sessions are stored.

    Attributes
    ----------
    root : Path
        Directory holding one sub-directory per session (relative to the config file).
    commit_interval_s : float
        Longest time recorded rows wait before they are committed [s]; a crash loses at
        most this much.
    min_free_mb : float
        Free space required on ``root``'s file system before a session starts [MB].
    video : {"passthrough", "lossless", "off"}
        The session video (``video.mkv``, docs/storage.md): ``passthrough`` stores an MJPG
        camera's JPEGs as received and records sources without encoded frames losslessly;
        ``lossless`` stores the decoded frames S_k is counted on (FFV1); ``off`` none.
    video_roi_only : bool
        Lossless video: store only the bounding box of the ROI, in gray (the rectangle S_k
        is counted in), not the whole frame.
    """

    root: Path = Path("sessions")
    commit_interval_s: float = Field(0.2, gt=0.0, le=0.25)
    min_free_mb: float = Field(100.0, ge=0.0)
    video: Literal["passthrough", "lossless", "off"] = "passthrough"
    video_roi_only: bool = False


class DaemonConfig(_Model):
    """The whole configuration file."""

    format: Literal["stipi-daemon-config"] = "stipi-daemon-config"
    version: Literal[1] = 1
    probe: ProbeSettings
    camera: CameraConfig
    calibration: Path | None = None
    imaging: ImagingSettings = ImagingSettings()
    measurement: MeasurementConfig = MeasurementConfig()
    analysis: AnalysisSettings = Field(AnalysisSettings(), validate_default=True)
    storage: StorageSettings = StorageSettings()
    run: RunSettings = RunSettings()

    @field_validator("analysis")
    @classmethod
    def _settling_matches_analysis(
        cls, analysis: AnalysisSettings, info: ValidationInfo
    ) -> AnalysisSettings:
        # The state machine ends a recovery early only when the analysis' T_s of Eq. (6)
        # cannot change; both must read it at the same fraction of S_max.
        measurement = info.data.get("measurement")
        if isinstance(measurement, MeasurementConfig) and (
            measurement.settle_fraction != analysis.settle_fraction
        ):
            raise ValueError(
                f"analysis.settle_fraction ({analysis.settle_fraction}) must equal "
                f"measurement.settle_fraction ({measurement.settle_fraction}): the recovery "
                "stops early by the analysis' settling rule (Eq. (6))"
            )
        return analysis

    def resolved(self, base: Path) -> DaemonConfig:
        """The same config with relative paths made absolute against ``base``."""

        def fix(p: Path) -> Path:
            return p if p.is_absolute() else (base / p).resolve()

        def fix_paths(model: BaseModel) -> Any:
            # ``scene`` and ``path`` fields, also in nested models (e.g. a BLE transport's
            # ``emulate`` section).
            update: dict[str, Any] = {}
            for name in type(model).model_fields:
                value = getattr(model, name)
                if name in ("scene", "path") and isinstance(value, Path):
                    update[name] = fix(value)
                elif isinstance(value, BaseModel):
                    fixed = fix_paths(value)
                    if fixed is not value:
                        update[name] = fixed
            return model.model_copy(update=update) if update else model

        probe = self.probe.model_copy(update={"transport": fix_paths(self.probe.transport)})
        storage = self.storage.model_copy(update={"root": fix(self.storage.root)})
        cal = None if self.calibration is None else fix(self.calibration)
        return self.model_copy(
            update={
                "probe": probe,
                "camera": fix_paths(self.camera),
                "storage": storage,
                "calibration": cal,
            }
        )


def _loc(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + part
    return out or "(top level)"


def parse_config(data: Any, source: str) -> DaemonConfig:
    """Validate a parsed YAML mapping; errors name ``source`` and the field path."""
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the config must be a mapping, got {type(data).__name__}")
    try:
        return DaemonConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        # Drop the discriminator tags pydantic inserts into union locations.
        tags = {"serial", "ble", "emulated", "v4l2", "file", "simulator", "rect", "circle"}
        loc = tuple(p for p in err["loc"] if p not in tags)
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        raise ConfigError(f"{source}: field '{_loc(loc)}': {msg}{more}") from None


def load_config(path: str | Path) -> DaemonConfig:
    """Load, validate and resolve a daemon config file.

    Raises
    ------
    ConfigError
        The file is missing, unreadable, not YAML, or fails validation; the message names
        the file and the field.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config file: {exc.strerror or exc}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{p}: not valid YAML{where}: {problem}") from None
    return parse_config(data, str(p)).resolved(p.resolve().parent)
