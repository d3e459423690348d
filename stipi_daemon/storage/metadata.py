"""Session metadata: who was measured, where, by whom, and a free note.

A session's ``manifest.json`` holds ``metadata = {"subject", "site", "operator", "note"}``
(each a string or null), written at creation from the config's ``session`` section and
the daemon's ``--subject/--site/--operator/--note`` options (:mod:`stipi_daemon.app`).
This module owns the rules a value must follow (:func:`metadata_problem`), and reading
the record back from a manifest (:func:`metadata_of`): a session recorded before
metadata existed reads as all null. It stores what it is given and decides nothing else.

Rules: ``subject``, ``site`` and ``operator`` are one line of at most
:data:`MAX_CHARS` characters, no control characters, no surrounding spaces (they are
searched by exact match: ``sessions list --subject S``); ``note`` may span lines (tabs
and newlines allowed, other control characters not) up to :data:`MAX_CHARS` characters.
An empty string is refused (leave the field out instead).
"""

from __future__ import annotations

import unicodedata
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Final

from stipi_daemon.errors import SessionError

#: The metadata fields, in the order they are shown and exported.
METADATA_FIELDS: Final[tuple[str, ...]] = ("subject", "site", "operator", "note")
#: Longest value of each field [characters].
MAX_CHARS: Final[dict[str, int]] = {"subject": 64, "site": 64, "operator": 64, "note": 2000}
#: What each field holds (CLI help, export docs).
FIELD_DOCS: Final[dict[str, str]] = {
    "subject": "who or what was measured (participant code, phantom, specimen)",
    "site": "where the session was recorded (lab, clinic)",
    "operator": "who held the probe",
    "note": "free text (body site, conditions); may span lines",
}

Metadata = dict[str, str | None]


def metadata_problem(field: str, value: object) -> str | None:
    """What is wrong with ``value`` for metadata ``field`` (one line), or None if it is fine.

    ``None`` is always fine (the field is not set).
    """
    if field not in MAX_CHARS:
        return f"unknown metadata field (fields: {', '.join(METADATA_FIELDS)})"
    if value is None:
        return None
    if not isinstance(value, str):
        return f"must be text, got {type(value).__name__}"
    limit = MAX_CHARS[field]
    multiline = field == "note"
    shape = (
        f"text of at most {limit} characters"
        if multiline
        else f"one line of at most {limit} characters"
    )
    if not value.strip():
        return f"is empty ({shape}; leave it out instead)"
    if len(value) > limit:
        return f"is {len(value)} characters long ({shape})"
    for ch in value:
        if multiline and ch in "\n\t":
            continue
        category = unicodedata.category(ch)
        if ch in "\r\n" or category in ("Zl", "Zp"):
            return f"contains a line break ({shape})"
        if category.startswith("C"):
            return f"contains control character U+{ord(ch):04X} ({shape})"
    if not multiline and value != value.strip():
        return f"has leading or trailing spaces ({shape})"
    return None


def check_metadata(values: Mapping[str, object], where: str) -> Metadata:
    """Every field of ``values`` validated, missing ones as None.

    Raises
    ------
    SessionError
        ``<where>: metadata field '<f>': <problem>`` for the first bad or unknown field.
    """
    for field in values:
        problem = metadata_problem(field, values[field])
        if problem is not None:
            raise SessionError(f"{where}: metadata field {field!r}: {problem}")
    return {f: v if isinstance(v := values.get(f), str) else None for f in METADATA_FIELDS}


def metadata_of(manifest: Mapping[str, Any], path: Path | str = "manifest.json") -> Metadata:
    """A manifest's ``metadata`` (all None for a session recorded before it existed).

    Raises
    ------
    SessionError
        ``metadata`` is not an object, or one of its values breaks the rules (names the
        manifest file and the field).
    """
    record = manifest.get("metadata")
    if record is None:
        return dict.fromkeys(METADATA_FIELDS)
    if not isinstance(record, dict):
        raise SessionError(
            f"{path}: field 'metadata' must be an object, got {type(record).__name__}"
        )
    return check_metadata(record, str(path))


def matches(metadata: Metadata, wanted: Mapping[str, str | None]) -> bool:
    """Whether ``metadata`` equals every non-None value of ``wanted`` exactly."""
    return all(v is None or metadata.get(k) == v for k, v in wanted.items())
