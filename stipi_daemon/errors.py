"""Typed errors shared by the whole package.

Every error the daemon reports to a user derives from :class:`StipiError`; the CLI prints
its message as one line and exits non-zero, without a traceback. Messages name the
problem and where it is (config field, file, byte offset).
"""

from __future__ import annotations

import math

#: Exit status of a command that did its work; of a measurement that was made, whatever
#: its verdict (the verdict is in the output and in ``summary.json``).
EXIT_OK = 0
#: Exit status of a measurement a fault stopped before it had results (or an analysis
#: that produced none).
EXIT_FAULT = 1
#: Exit status for bad input: arguments, a config, scene, calibration or data file, a
#: session that is not there (one line names the problem and where it is).
EXIT_BAD_INPUT = 2
#: Exit status of ``analyze --recompute-sk`` whose recount did not reproduce the stored S_k.
EXIT_S_K_NOT_REPRODUCED = 3
#: Exit status for a session whose stored data is damaged (:class:`DamagedSessionError`).
EXIT_DAMAGED = 4


class StipiError(Exception):
    """Base class of every error stipi-daemon reports to its user."""


class Terminated(KeyboardInterrupt):
    """A measurement was stopped by SIGTERM (``kill PID``, a service manager's stop), by
    SIGHUP (its terminal closed) or because its standard output failed (closed, full),
    and ended as after Ctrl-C: its session finished ``aborted``, its devices closed.

    ``reason`` is the one line the CLI prints (after ``stipi-daemon: ``), ``exit_code``
    its exit status (the shell's 128 + signal number for a signal).
    """

    def __init__(self, reason: str = "terminated (SIGTERM)", exit_code: int = 143) -> None:
        super().__init__(reason)
        self.reason = reason
        self.exit_code = exit_code


class AnalysisError(StipiError, ValueError):
    """Input to an analysis function cannot give a meaningful result.

    Raised for input outside a function's stated domain (e.g. a negative depth, an empty
    series, NaN in a required value) when no flagged result can be returned instead.
    """


def require_finite(name: str, value: float) -> float:
    """``value`` as a float, or :class:`AnalysisError` naming ``name`` when it is NaN or inf."""
    v = float(value)
    if not math.isfinite(v):
        raise AnalysisError(f"{name} must be finite, got {v}")
    return v


class CalibrationError(StipiError, ValueError):
    """Calibration data cannot determine the coefficients, or a calibration file is bad."""


class ConfigError(StipiError, ValueError):
    """A configuration, scene or calibration file is malformed; the message names file and field."""


class ProtocolError(StipiError, ValueError):
    """A wire-protocol message cannot be encoded or decoded."""


class SessionError(StipiError):
    """A session directory cannot be created, written or read.

    Raised for a bad session directory (missing, truncated or corrupt ``session.sqlite``,
    missing or wrong-version ``manifest.json``, unknown schema version), for rows that do not
    fit the session schema, and for too little free disk space; the message names the file
    (or table, row and column) and the problem, on one line.
    """


class DamagedSessionError(SessionError):
    """A session's stored data is damaged: its database is corrupt or unreadable, or it
    fails its integrity check (rows against the video, the video's frames). The CLI exits
    with :data:`EXIT_DAMAGED` for it."""


class DataFileError(StipiError, ValueError):
    """A recorded data file (CSV of samples or pairs, video) is missing, unreadable or malformed.

    The message names the file and, where it applies, the line and column.
    """


class CameraError(StipiError):
    """A camera or video source cannot be opened or stopped delivering frames.

    Raised for a missing or unreadable device or video file, a device that refuses to
    stream, and a camera that stays silent after every reopen attempt; the message names
    the device (``/dev/video0``) or file, on one line.
    """


class DeviceNotFoundError(StipiError):
    """A device the daemon was told to use is not there (serial port, BLE probe, camera).

    The message is one line naming the device or path, e.g. ``serial port /dev/ttyACM0 not
    found``.
    """


class LinkLostError(StipiError):
    """An open link to a device stopped working (unplugged, disconnected, silent, no answer).

    The message is one line naming the link and what was seen.
    """
