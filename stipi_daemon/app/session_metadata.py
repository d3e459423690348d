"""The session's metadata from the config and the command line.

The config's ``session`` section (:class:`~stipi_daemon.app.config.SessionSettings`)
holds subject, site, operator and note; the daemon's ``--subject``, ``--site``,
``--operator`` and ``--note`` options replace the config's values field by field (an
option not given keeps the config's). The result is recorded as the manifest's
``metadata`` (:mod:`stipi_daemon.storage.metadata`). A bad option value is one
:class:`~stipi_daemon.errors.ConfigError` line naming the option.
"""

from __future__ import annotations

from collections.abc import Mapping

from stipi_daemon.app.config import DaemonConfig
from stipi_daemon.errors import ConfigError
from stipi_daemon.storage.metadata import METADATA_FIELDS, Metadata, metadata_problem

__all__ = ["apply_metadata_options", "session_metadata"]


def apply_metadata_options(config: DaemonConfig, options: Mapping[str, str | None]) -> DaemonConfig:
    """``config`` with the command line's metadata options in its ``session`` section.

    Parameters
    ----------
    config : DaemonConfig
        The loaded config.
    options : mapping
        ``{"subject": ..., "site": ..., "operator": ..., "note": ...}``; None (or a missing
        key) keeps the config's value.

    Raises
    ------
    ConfigError
        ``--<field>: <problem>`` for a value that breaks the metadata rules.
    """
    update: dict[str, str] = {}
    for field in METADATA_FIELDS:
        value = options.get(field)
        if value is None:
            continue
        problem = metadata_problem(field, value)
        if problem is not None:
            raise ConfigError(f"--{field}: {problem}")
        update[field] = value
    if not update:
        return config
    return config.model_copy(update={"session": config.session.model_copy(update=update)})


def session_metadata(config: DaemonConfig) -> Metadata:
    """The manifest's ``metadata`` record of a run with ``config``."""
    return {field: getattr(config.session, field) for field in METADATA_FIELDS}
