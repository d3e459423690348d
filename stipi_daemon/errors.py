"""Typed errors shared by the whole package.

Every error the daemon reports to a user derives from :class:`StipiError`; the CLI prints
its message as one line and exits non-zero, without a traceback. Messages name the
problem and where it is (config field, file, byte offset).
"""

from __future__ import annotations


class StipiError(Exception):
    """Base class of every error stipi-daemon reports to its user."""


class AnalysisError(StipiError, ValueError):
    """Input to an analysis function cannot give a meaningful result.

    Raised for input outside a function's stated domain (e.g. a negative depth, an empty
    series, NaN in a required value) when no flagged result can be returned instead.
    """


class CalibrationError(StipiError, ValueError):
    """Calibration data cannot determine the coefficients, or a calibration file is bad."""


class ConfigError(StipiError, ValueError):
    """A configuration, scene or calibration file is malformed; the message names file and field."""


class ProtocolError(StipiError, ValueError):
    """A wire-protocol message cannot be encoded or decoded."""
