"""Subcommands of ``stipi-daemon``.

Each subcommand is one module here with a ``register(subparsers)`` function that adds its
parser and sets ``handler`` (a function taking the parsed namespace and returning an exit
status). :data:`COMMAND_MODULES` lists them in the order ``--help`` shows them.
"""

from __future__ import annotations

import argparse
import importlib
import re
from pathlib import Path
from typing import Protocol

from stipi_daemon.errors import ConfigError


class _Registrar(Protocol):
    def register(self, subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None: ...


#: Modules (relative to this package) that provide a ``register`` function.
COMMAND_MODULES: tuple[str, ...] = (
    "analyze",
    "calibrate",
    "flash",
    "mock_peripheral",
    "report",
    "sessions",
    "simulate",
    "study",
    "view",
)


def frame_size_arg(text: str) -> tuple[int, int]:
    """An argparse ``type``: a frame size ``WIDTHxHEIGHT`` [px], both > 0."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if m is None or min(int(m.group(1)), int(m.group(2))) == 0:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT in px, both > 0 (e.g. 1280x720), got {text!r}"
        )
    return int(m.group(1)), int(m.group(2))


def given_path(text: str, option: str = "--out") -> Path:
    """An output path given as text (argparse ``type=str``, as ``Path("")`` would be the
    current directory).

    Raises
    ------
    ConfigError
        An empty or blank value (one line): never taken as the current directory.
    """
    if not text.strip():
        raise ConfigError(f"{option} {text!r}: empty; give a directory or file name")
    return Path(text)


def out_path(text: str | None, option: str = "--out") -> Path | None:
    """:func:`given_path`, or None when the option was not given."""
    return None if text is None else given_path(text, option)


def add_sessions_root(parser: argparse.ArgumentParser) -> None:
    """``--root DIR`` and ``--config FILE``: where a command finds the sessions."""
    from stipi_daemon.storage import DEFAULT_ROOT

    parser.add_argument(
        "--root",
        type=Path,
        default=None,
        help="directory holding the sessions (default: the storage.root of --config, else "
        f"./{DEFAULT_ROOT})",
    )
    parser.add_argument(
        "--config",
        type=Path,
        default=argparse.SUPPRESS,
        metavar="FILE",
        help="daemon config whose storage.root holds the sessions",
    )


def register_all(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add every subcommand in :data:`COMMAND_MODULES` to ``subparsers``."""
    for name in COMMAND_MODULES:
        module: _Registrar = importlib.import_module(f"{__name__}.{name}")
        module.register(subparsers)
