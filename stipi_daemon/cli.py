"""Command-line entry point ``stipi-daemon``.

Only argument parsing and dispatch live here; every subcommand calls into the package.
User-facing errors (:class:`~stipi_daemon.errors.StipiError`) are printed as one line on
stderr with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from stipi_daemon import __version__
from stipi_daemon.errors import StipiError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stipi-daemon",
        description=(
            "Acquisition and analysis for the STIP-I tactile imaging probe: force and "
            "video of an indenter pitting test, turned into pitting depth, rebound force, "
            "recovery time, elasticity, viscosity and an edema severity class."
        ),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        handler = getattr(args, "handler", None)
        if handler is None:
            parser.print_help()
            return 0
        result: int = handler(args)
        return result
    except StipiError as exc:
        print(f"stipi-daemon: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
