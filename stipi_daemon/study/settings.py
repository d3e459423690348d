"""The settings of a study re-analysis (``study reanalyze --settings S.yaml``): schema, hash.

A settings file says what to change, for every session, relative to what each session
recorded (``configs/study-settings.example.yaml``)::

    format: stipi-study-settings      # optional
    version: 1                        # optional
    calibration: cal.json             # optional: this calibration instead of the recorded
    imaging:                          # Eqs. (1)-(2): used when S_k is counted again
      threshold_p: 110                #   threshold p [8-bit intensity, 0..255]
      roi: {kind: circle, cx_px: 80, cy_px: 60, radius_px: 45}   # null: the whole frame
      saturation_limit_fraction: 0.02 #   [-]
    measurement: {settle_fraction: 0.05}        # fields of the config's measurement section
    analysis: {bootstrap_replicates: 0}         # fields of the config's analysis section

``imaging.threshold_p`` and ``imaging.roi`` win over every other source, as ``analyze
--threshold`` and ``--roi`` do; they change S_k only, so they need ``--recompute-sk``.
The ``measurement`` and ``analysis`` fields are set over each session's recorded section
(the rest of it stays as recorded) and validated one by one with the config's own models
(:class:`~stipi_daemon.measurement.settings.MeasurementConfig`,
:class:`~stipi_daemon.analysis.results.AnalysisSettings`); rules that tie fields together
are checked per session, where a violation is that session's error. A relative
``calibration`` path is relative to the settings file. Unknown keys are errors; every
error is one line naming the file and the field.

The settings' **normalised** form (:meth:`StudySettings.normalised`) holds the fields
given, as the models parse them (``110.0`` becomes ``110``; a ROI gets its every field),
the calibration as the SHA-256 of its file (its path may differ between machines), and
whether S_k is counted again. :func:`settings_hash` is the SHA-256 of its canonical JSON
(:func:`stipi_daemon.study.hashing.settings_hash`): two files that say the same thing
hash the same, whatever their key order, comments or number spelling. The package version
is not part of it; each results row records it beside the hash.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError
from pydantic.fields import FieldInfo

from stipi_daemon.analysis.calibration import load_calibration
from stipi_daemon.analysis.imaging import ROI, CircleROI, RectROI
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.errors import ConfigError, StipiError
from stipi_daemon.measurement.settings import MeasurementConfig
from stipi_daemon.study import hashing
from stipi_daemon.yamlfile import load_yaml, read_utf8

__all__ = ["SETTINGS_FORMAT", "StudySettings", "load_settings", "settings_hash"]

SETTINGS_FORMAT: Final = "stipi-study-settings"

#: The config sections whose fields a settings file may set, and their models.
_SECTIONS: Final[dict[str, type[BaseModel]]] = {
    "measurement": MeasurementConfig,
    "analysis": AnalysisSettings,
}


class ImagingChange(BaseModel):
    """Eqs. (1)-(2) settings to use when S_k is counted again (unset: as recorded).

    Attributes
    ----------
    threshold_p : int or None
        Threshold p of Eq. (1) [8-bit intensity, 0..255].
    roi : ROI or None
        Region of interest [px]; given as null: the whole frame.
    saturation_limit_fraction : float or None
        Fraction of ROI pixels at 255 above which a frame is flagged saturated [-].
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    threshold_p: int | None = Field(None, ge=0, le=255)
    roi: ROI | None = None
    saturation_limit_fraction: float | None = Field(None, ge=0.0, le=1.0)


class StudySettings(BaseModel):
    """A settings file, validated (see the module doc).

    Attributes
    ----------
    calibration : Path or None
        Calibration file used instead of each session's (absolute once loaded).
    imaging : ImagingChange
        Threshold, ROI and saturation limit for the S_k count.
    measurement, analysis : dict
        Fields set over each session's recorded section, values as the models parse them.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["stipi-study-settings"] = SETTINGS_FORMAT
    version: Literal[1] = 1
    calibration: Path | None = None
    imaging: ImagingChange = ImagingChange()
    measurement: dict[str, Any] = {}
    analysis: dict[str, Any] = {}

    @property
    def threshold_p(self) -> int | None:
        return self.imaging.threshold_p

    @property
    def roi_given(self) -> bool:
        return "roi" in self.imaging.model_fields_set

    @property
    def roi(self) -> CircleROI | RectROI | None:
        return self.imaging.roi

    def changes_s_k_only(self) -> list[str]:
        """The fields given that act on the S_k count only (``imaging.*``)."""
        return [f"imaging.{name}" for name in sorted(self.imaging.model_fields_set)]

    def sections(self) -> dict[str, dict[str, Any]]:
        """The section fields to set over each session's (``AnalyzeRequest.sections``)."""
        out = {name: dict(getattr(self, name)) for name in _SECTIONS if getattr(self, name)}
        if self.imaging.saturation_limit_fraction is not None:
            out["imaging"] = {"saturation_limit_fraction": self.imaging.saturation_limit_fraction}
        return out

    def normalised(self, recompute_sk: bool) -> dict[str, Any]:
        """What the settings hash covers (see the module doc)."""
        calibration = None if self.calibration is None else hashing.file_hash(self.calibration)
        return {
            "format": SETTINGS_FORMAT,
            "version": 1,
            "calibration_sha256": calibration,
            "imaging": self.imaging.model_dump(mode="json", exclude_unset=True),
            "measurement": dict(sorted(self.measurement.items())),
            "analysis": dict(sorted(self.analysis.items())),
            "recompute_sk": recompute_sk,
        }


def settings_hash(settings: StudySettings, recompute_sk: bool) -> str:
    """``sha256:<hex>`` of the normalised settings (package version not included)."""
    return hashing.settings_hash(settings.normalised(recompute_sk))


def _loc(loc: tuple[int | str, ...]) -> str:
    tags = {"rect", "circle"}  # discriminator tags pydantic inserts
    return ".".join(str(p) for p in loc if p not in tags) or "(top level)"


def _field_adapter(info: FieldInfo) -> TypeAdapter[Any]:
    form: Any = Annotated[info.annotation, info]
    return TypeAdapter(form)


def _section_fields(source: str, name: str, given: Any) -> dict[str, Any]:
    """A section's fields checked one by one against the config model's field types."""
    if given is None:
        return {}
    if not isinstance(given, Mapping):
        raise ConfigError(f"{source}: field '{name}': must be a mapping of field: value")
    model = _SECTIONS[name]
    out: dict[str, Any] = {}
    for key, value in given.items():
        info = model.model_fields.get(str(key))
        if info is None:
            known = ", ".join(sorted(model.model_fields))
            raise ConfigError(f"{source}: field '{name}.{key}': unknown key (known: {known})")
        adapter = _field_adapter(info)
        try:
            parsed = adapter.validate_python(value)
        except ValidationError as exc:
            err = exc.errors()[0]
            raise ConfigError(f"{source}: field '{name}.{key}': {err['msg']}") from None
        out[str(key)] = adapter.dump_python(parsed, mode="json")
    return out


def parse_settings(data: Any, source: str, base: Path) -> StudySettings:
    """Validate a parsed settings document; relative paths are relative to ``base``.

    Raises
    ------
    ConfigError
        One line naming ``source`` and the field.
    """
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the settings must be a mapping, got {type(data).__name__}")
    data = dict(data)
    imaging = data.get("imaging")
    if isinstance(imaging, Mapping) and "threshold_p" in imaging and imaging["threshold_p"] is None:
        raise ConfigError(f"{source}: field 'imaging.threshold_p': give 0..255, or leave it out")
    for name in _SECTIONS:
        data[name] = _section_fields(source, name, data.get(name))
    try:
        settings = StudySettings.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        msg = "unknown key" if err["type"] == "extra_forbidden" else err["msg"]
        raise ConfigError(f"{source}: field '{_loc(tuple(err['loc']))}': {msg}") from None
    if settings.calibration is not None:
        path = settings.calibration
        path = path if path.is_absolute() else (base / path)
        path = path.resolve()
        try:
            load_calibration(path)
        except StipiError as exc:
            raise ConfigError(f"{source}: field 'calibration': {exc}") from None
        settings = settings.model_copy(update={"calibration": path})
    return settings


def load_settings(path: Path) -> tuple[StudySettings, Any]:
    """Read and validate a settings file; returns the settings and the document as given.

    Raises
    ------
    ConfigError
        The file cannot be read, is not YAML, or a field is wrong (one line).
    """
    data = load_yaml(read_utf8(path, "settings file"), str(path))
    return parse_settings(data, str(path), path.resolve().parent), data
