"""The daemon's configuration file (``stipi-daemon --config FILE``), loaded once, typed.

This module owns the schema of the YAML file a lab edits: the probe (``probe.transport``:
serial, BLE or an emulated probe on a pty, plus rate and LED level), the camera (V4L2, a
video file or the simulator), imaging settings (threshold and ROI of Eqs. 1-2), the
calibration file, the state machine's thresholds (``measurement``), the analysis
settings, storage, the run speed and the session's metadata (``session``: subject, site,
operator, note). It validates everything with pydantic (unknown keys
are errors) and reports problems as one :class:`~stipi_daemon.errors.ConfigError` line
naming the file and the field path; a key given twice is refused with its line
(:mod:`stipi_daemon.yamlfile`). Paths inside the file are resolved relative to the file.
The command line may change a loaded file without copying it: ``--scene PATH`` (the scene
every simulated device plays) and ``--set KEY=VALUE`` (any field, by its dotted path),
validated by the same model; an error names the ``--set`` item. :func:`sessions_root` is
the one rule by which every command finds the sessions directory (``--root``, else the
``storage.root`` of ``--config``, else ``./sessions``). It does not open devices or files
other than the config itself. Each transport's
and camera's own options live in their modules (:mod:`stipi_daemon.probe.transports`,
:mod:`stipi_daemon.cameras`).
"""

from __future__ import annotations

import difflib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from stipi_daemon.analysis.imaging import ROI
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.cameras import CameraConfig
from stipi_daemon.errors import ConfigError, SessionError
from stipi_daemon.measurement.state_machine import MeasurementConfig
from stipi_daemon.probe.transports import TransportConfig
from stipi_daemon.storage.layout import DEFAULT_ROOT
from stipi_daemon.storage.metadata import metadata_problem
from stipi_daemon.yamlfile import load_yaml, read_utf8

__all__ = [
    "CONFIG_FORMAT",
    "CONFIG_VERSION",
    "DaemonConfig",
    "ImagingSettings",
    "Override",
    "ProbeSettings",
    "RunSettings",
    "SessionSettings",
    "StorageSettings",
    "ViewSettings",
    "find_session",
    "load_config",
    "parse_override",
    "sessions_root",
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
        Session seconds per wall second at most, >= 0. 1 for real devices; 0: as fast as
        the daemon goes (only where every device is simulated). A run whose every
        device is simulated in the daemon's process (the emulated probe and the simulator
        camera or a paced video file) runs on a clock that waits for the daemon
        (:class:`~stipi_daemon.clock.VirtualClock`): ``speed`` only caps how far ahead of
        real time it may run, and its rows and results are the same at any speed and on
        any machine. ``--realtime`` forces 1.
    clock : {"auto", "wall"}
        ``auto``: that waiting clock for such a run, wall time times ``speed`` otherwise;
        ``wall``: wall time times ``speed`` always (a simulated run then meets what the
        machine does as real devices do: lag, gaps, faults).
    max_lag_s : float
        Longest the daemon may fall behind the camera [s of session time]: the lag is the
        session time when a frame is measured minus its capture time. Frames measured more
        than half of it late are not measured but recorded as gaps (reason
        ``processing_behind``); a lag above it ends the run with a fault (one line: lower
        ``run.speed``). Samples and frames are fed to the measurement no further ahead
        than the camera, so the session never ends while frames of its window are queued.
    """

    speed: float = Field(1.0, ge=0.0, le=1000.0, allow_inf_nan=False)
    clock: Literal["auto", "wall"] = "auto"
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
        is counted in), not the whole frame. A passthrough of an MJPG source stores its
        JPEGs whole (the session gets a ``video_roi_only_ignored`` event and a warning);
        with ``video: off`` it is an error.
    """

    root: Path = Path("sessions")
    commit_interval_s: float = Field(0.2, gt=0.0, le=0.25)
    min_free_mb: float = Field(100.0, ge=0.0)
    video: Literal["passthrough", "lossless", "off"] = "passthrough"
    video_roi_only: bool = False

    @field_validator("video", mode="before")
    @classmethod
    def _yaml_off(cls, value: object) -> object:
        # YAML 1.1 (PyYAML) reads an unquoted `off` as false: `video: off` means "off"
        return "off" if value is False else value

    @model_validator(mode="after")
    def _roi_only_needs_video(self) -> StorageSettings:
        if self.video_roi_only and self.video == "off":
            raise ValueError(
                "storage.video_roi_only is true but storage.video is off: there is no "
                "video to store the ROI of (set storage.video: lossless, or drop "
                "storage.video_roi_only)"
            )
        return self


class SessionSettings(_Model):
    """Who and what a session is of: stored as the manifest's ``metadata``.

    The daemon's ``--subject``, ``--site``, ``--operator`` and ``--note`` replace these
    (:mod:`stipi_daemon.app.session_metadata`). Rules (:mod:`stipi_daemon.storage.metadata`):
    subject, site and operator are one line of at most 64 characters; the note is text
    of at most 2000 characters.

    Attributes
    ----------
    subject, site, operator, note : str or None
        Participant or specimen code, recording site, who held the probe, free note.
    """

    subject: str | None = None
    site: str | None = None
    operator: str | None = None
    note: str | None = None

    @field_validator("subject", "site", "operator", "note")
    @classmethod
    def _metadata_rules(cls, value: str | None, info: ValidationInfo) -> str | None:
        problem = metadata_problem(str(info.field_name), value)
        if problem is not None:
            raise ValueError(problem)
        return value


class ViewSettings(_Model):
    """The live view in the browser (:mod:`stipi_daemon.app.liveview`).

    Attributes
    ----------
    enabled : bool or None
        Serve the view while measuring. None (the default): when the console is a terminal
        and not ``--quiet`` (an interactive run); a script's or a service's run serves it
        only with ``true``.
    host : str
        Address to listen on. Loopback (the default) lets only this machine's browser
        connect; another address is an explicit choice and the daemon warns when it starts.
    port : int
        TCP port; 0 (the default): a free one the system chooses (the printed address has
        it, with the run's random token).
    """

    enabled: bool | None = None
    host: str = Field("127.0.0.1", min_length=1)
    port: int = Field(0, ge=0, le=65535)


def _simulated_world(probe: ProbeSettings, camera: CameraConfig) -> bool:
    """See :attr:`DaemonConfig.simulated_world`."""
    plays_scene = camera.kind == "simulator" or (camera.kind == "file" and camera.pace)
    return probe.transport.kind == "emulated" and plays_scene


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
    session: SessionSettings = SessionSettings()
    view: ViewSettings = ViewSettings()

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

    @field_validator("run")
    @classmethod
    def _unpaced_needs_a_simulated_world(
        cls, run: RunSettings, info: ValidationInfo
    ) -> RunSettings:
        probe, camera = info.data.get("probe"), info.data.get("camera")
        if run.speed == 0.0 and probe is not None and camera is not None:
            if run.clock == "wall" or not _simulated_world(probe, camera):
                raise ValueError(
                    "run.speed 0 (as fast as the daemon goes) needs every device simulated "
                    "in the daemon's process (probe.transport.kind emulated, camera.kind "
                    "simulator or a paced file) and run.clock auto; real devices run at 1"
                )
        return run

    @property
    def simulated_world(self) -> bool:
        """Whether every device of a run is simulated in the daemon's process: the emulated
        probe on a pty and a camera that plays the scene (the simulator, a paced video
        file). Such a run's clock waits for the daemon
        (:class:`~stipi_daemon.clock.VirtualClock`)."""
        return _simulated_world(self.probe, self.camera)

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


@dataclass(frozen=True)
class Override:
    """One ``--set KEY=VALUE`` of the command line, parsed.

    Attributes
    ----------
    key : str
        Dotted field path (``measurement.stop_when_settled``).
    value : Any
        The value, parsed as a YAML scalar (``true``, ``4``, ``0.5``, ``text``; empty:
        null).
    text : str
        As given (``KEY=VALUE``), for messages.
    """

    key: str
    value: Any
    text: str

    @property
    def parts(self) -> tuple[str, ...]:
        return tuple(self.key.split("."))

    def owns(self, loc: str) -> bool:
        """Whether a validation error at dotted ``loc`` concerns this override."""
        return loc == self.key or loc.startswith(self.key + ".") or self.key.startswith(loc + ".")


def parse_override(text: str) -> Override:
    """Parse one ``--set KEY=VALUE`` (``KEY`` dotted, ``VALUE`` a YAML scalar).

    Raises
    ------
    ConfigError
        No ``=``, an empty key or key part, or a value that is not a YAML scalar.
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    example = "e.g. --set measurement.stop_when_settled=true"
    if not sep or not key:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE ({example})")
    if any(not part.strip() or part != part.strip() for part in key.split(".")):
        raise ConfigError(f"--set {text!r}: empty or padded part in the dotted key ({example})")
    value = load_yaml(raw, f"--set {key}")
    if isinstance(value, dict | list):
        raise ConfigError(
            f"--set {text}: the value must be a single value (number, true/false, text), "
            "not a mapping or list; set each field with its own --set"
        )
    return Override(key, value, text)


def _apply_override(data: dict[str, Any], ov: Override) -> None:
    node = data
    parts = ov.parts
    for i, part in enumerate(parts[:-1]):
        child = node.get(part)
        if child is None:
            child = node[part] = {}
        elif not isinstance(child, dict):
            section = ".".join(parts[: i + 1])
            raise ConfigError(f"--set {ov.text}: '{section}' is a value, not a section")
        node = child
    node[parts[-1]] = ov.value


def _apply_scene(data: dict[str, Any], scene: Path, source: str) -> None:
    """Point every simulated device of the raw config at ``scene`` (absolute path)."""
    targets: list[dict[str, Any]] = []
    probe = data.get("probe")
    transport = probe.get("transport") if isinstance(probe, dict) else None
    if isinstance(transport, dict):
        if transport.get("kind") == "emulated":
            targets.append(transport)
        elif transport.get("kind") == "ble" and isinstance(transport.get("emulate"), dict):
            targets.append(transport["emulate"])
    camera = data.get("camera")
    if isinstance(camera, dict) and camera.get("kind") == "simulator":
        targets.append(camera)
    if not targets:
        kinds = (
            f"probe.transport.kind {transport.get('kind') if isinstance(transport, dict) else None}"
            f", camera.kind {camera.get('kind') if isinstance(camera, dict) else None}"
        )
        raise ConfigError(
            f"--scene: {source} has no simulated device ({kinds}); a scene drives an "
            "emulated probe (kind emulated, or ble with emulate) or the simulator camera"
        )
    for target in targets:
        target["scene"] = str(scene)


def _field_value(model: Any, parts: tuple[str, ...]) -> Any:
    for part in parts:
        if not isinstance(model, BaseModel) or part not in type(model).model_fields:
            return None
        model = getattr(model, part)
    return model


def _did_you_mean(loc: str) -> str:
    """`` (did you mean 'x'?)`` for an unknown dotted key of a plain section, else ``""``."""
    *section, name = loc.split(".")
    model: type[BaseModel] = DaemonConfig
    for part in section:
        field = model.model_fields.get(part)
        annotation = None if field is None else field.annotation
        if not (isinstance(annotation, type) and issubclass(annotation, BaseModel)):
            return ""
        model = annotation
    close = difflib.get_close_matches(name, list(model.model_fields), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def parse_config(data: Any, source: str, overrides: Sequence[Override] = ()) -> DaemonConfig:
    """Validate a parsed YAML mapping; errors name ``source`` and the field path.

    An error in a field an override set names that ``--set KEY=VALUE`` instead of the
    file; any other error names the file (and that overrides were applied).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the config must be a mapping, got {type(data).__name__}")
    try:
        return DaemonConfig.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        # Drop the discriminator tags pydantic inserts into union locations.
        tags = {"serial", "ble", "emulated", "v4l2", "file", "simulator", "rect", "circle"}
        loc = _loc(tuple(p for p in err["loc"] if p not in tags))
        more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        owner = next((ov for ov in reversed(overrides) if ov.owns(loc)), None)
        if owner is not None:
            field = "" if loc == owner.key else f"field '{loc}': "
            if msg == "unknown key":
                msg += _did_you_mean(loc)
            raise ConfigError(f"--set {owner.text}: {field}{msg}{more}") from None
        if overrides:
            source += " (with " + ", ".join(f"--set {ov.key}" for ov in overrides) + ")"
        raise ConfigError(f"{source}: field '{loc}': {msg}{more}") from None


def read_config_data(path: Path) -> Any:
    """The parsed YAML of a config file (duplicate keys refused, naming the line)."""
    return load_yaml(read_utf8(path, "config file"), str(path))


def load_config(
    path: str | Path, *, scene: Path | None = None, overrides: Sequence[str] = ()
) -> DaemonConfig:
    """Load, validate and resolve a daemon config file, with command-line overrides.

    Parameters
    ----------
    path : str or Path
        The YAML file. Its relative paths are resolved against its directory.
    scene : Path, optional
        ``--scene``: the scene file every simulated device of the config plays (the
        emulated probe and the simulator camera); relative to the working directory.
    overrides : sequence of str
        ``--set KEY=VALUE`` items, applied in order after ``scene``; each value is a YAML
        scalar validated by the same model as the file. A relative path given this way is
        relative to the working directory.

    Raises
    ------
    ConfigError
        The file is missing, unreadable, not YAML, has a duplicate key, or fails
        validation (the message names the file and the field, or the ``--set`` item);
        ``scene`` is missing or the config has no simulated device.
    """
    p = Path(path)
    parsed = [parse_override(text) for text in overrides]
    data = read_config_data(p)
    if (scene is not None or parsed) and isinstance(data, dict):
        if scene is not None:
            if not scene.is_file():
                raise ConfigError(f"--scene {scene}: no such scene file")
            _apply_scene(data, scene.resolve(), str(p))
        for ov in parsed:
            _apply_override(data, ov)
    config = parse_config(data, str(p), parsed)
    # A path set on the command line is relative to the working directory, not the file.
    relative = [
        ov
        for ov in parsed
        if isinstance(value := _field_value(config, ov.parts), Path) and not value.is_absolute()
    ]
    if relative:
        for ov in relative:
            _apply_override(data, Override(ov.key, str(Path.cwd() / str(ov.value)), ov.text))
        config = parse_config(data, str(p), parsed)
    return config.resolved(p.resolve().parent)


def sessions_root(root: Path | None, config: Path | None) -> Path:
    """The sessions directory a command reads: every command finds it by this one rule.

    ``--root`` when given; else the ``storage.root`` of ``--config`` (resolved against
    the config file's directory, as the daemon records there); else ``./sessions``.
    """
    if root is not None:
        return root
    if config is not None:
        return load_config(config).storage.root
    return DEFAULT_ROOT


def find_session(root: Path, text: str) -> Path:
    """The session directory a command's ``SESSION``/``ID`` argument names, by one rule for
    every command (``sessions show``/``export``, ``analyze``, ``report``).

    A path (it contains ``/``, or is ``.`` or ``..``) is taken as it is; a name is the
    session of that id under ``root`` (:func:`sessions_root`), else a directory of that
    name in the current directory.

    Raises
    ------
    SessionError
        A name that is neither: one line naming both places looked in.
    """
    if "/" in text or text in (".", ".."):
        return Path(text)
    directory = root / text
    if text and directory.is_dir():
        return directory
    here = Path(text)
    if text and here.is_dir():
        return here
    raise SessionError(
        f"{text}: no such session: neither a session id in the sessions directory "
        f"({directory}) nor a directory in the current one ({Path.cwd() / text}) "
        "(list them: stipi-daemon sessions list)"
    )
