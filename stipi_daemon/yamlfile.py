"""YAML files a user edits (daemon configs, simulator scenes), read strictly.

PyYAML's ``safe_load`` keeps the last of two equal keys in one mapping, so a file with
``stop_when_settled: true`` near the top and ``stop_when_settled: false`` further down
silently runs with ``false``. :func:`load_yaml` refuses such a file: the one-line
:class:`~stipi_daemon.errors.ConfigError` names the file, the key and both lines. Merge
keys (``<<: *anchor``) still override what they merge, as YAML defines. Syntax errors name
the line and column. :func:`read_utf8` reads any text file a user gives (config, scene,
settings, calibration, CSV) as UTF-8: bytes that are not UTF-8 are one line naming the
file and the byte offset, never a traceback. Shared by every layer (like
:mod:`stipi_daemon.errors`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from yaml.nodes import MappingNode

from stipi_daemon.errors import ConfigError, StipiError

__all__ = ["decode_utf8", "load_yaml", "read_utf8"]

_MERGE_TAG = "tag:yaml.org,2002:merge"


class _StrictLoader(yaml.SafeLoader):
    """``SafeLoader`` that raises on a key given twice in one mapping."""

    def construct_mapping(self, node: MappingNode, deep: bool = False) -> dict[Any, Any]:
        first_line: dict[Any, int] = {}
        for key_node, _value_node in node.value:
            if key_node.tag == _MERGE_TAG:
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                line = first_line.get(key)
            except TypeError:  # an unhashable key: SafeLoader reports it below
                continue
            if line is not None:
                raise _DuplicateKeyError(key, line, key_node.start_mark.line + 1)
            first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


class _DuplicateKeyError(yaml.YAMLError):
    def __init__(self, key: Any, first_line: int, line: int) -> None:
        super().__init__(f"duplicate key {key!r}")
        self.key = key
        self.first_line = first_line
        self.line = line


def load_yaml(text: str, source: str) -> Any:
    """Parse YAML ``text``; errors are one line naming ``source`` and the line.

    Parameters
    ----------
    text : str
        The document.
    source : str
        What to call it in errors (a file path, ``--set KEY``).

    Raises
    ------
    ConfigError
        Not valid YAML (line and column), or a key given twice in one mapping (the key
        and both lines).
    """
    try:
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass
    except _DuplicateKeyError as exc:
        raise ConfigError(
            f"{source}: line {exc.line}: duplicate key '{exc.key}' (already given at line "
            f"{exc.first_line}; only one may stay)"
        ) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{source}: not valid YAML{where}: {problem}") from None


def decode_utf8(data: bytes, source: str, error: type[StipiError] = ConfigError) -> str:
    """``data`` decoded as UTF-8 (a leading byte-order mark dropped).

    Raises
    ------
    StipiError
        ``error``: one line naming ``source``, the byte offset and the byte that is not
        UTF-8.
    """
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        bom = 3 if data.startswith(b"\xef\xbb\xbf") else 0
        offset = exc.start + bom
        raise error(
            f"{source}: not UTF-8 text: byte 0x{data[offset]:02x} at byte offset {offset} "
            f"({exc.reason}); save the file as UTF-8"
        ) from None


def read_utf8(path: Path, what: str, error: type[StipiError] = ConfigError) -> str:
    """The text of the file ``path`` (a ``what``: "config file", "scene file"...), as UTF-8.

    Raises
    ------
    StipiError
        ``error``, one line naming the file: it cannot be read (missing, a directory, no
        permission), or it is not UTF-8 (the byte offset, :func:`decode_utf8`).
    """
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    return decode_utf8(data, str(path), error)
