"""``stipi-daemon flash``: put the probe firmware on the Feather 32u4 over USB.

Builds the firmware if needed, resets the board into its Caterina bootloader (1200-baud
touch), waits for the bootloader's port (which may come back under a new name) and runs
``avrdude -c avr109``, which verifies. This module parses the command line; the steps are
:func:`stipi_daemon.probe.flash.flash`. Every failure is one line on stderr: exit status 2
for a bad image or a missing port (checked before the board is touched), 1 for a failure
on the way.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from stipi_daemon.probe import flash as flashing


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "flash",
        help="build and flash the probe firmware (Feather 32u4, avrdude -c avr109)",
        description=(
            "Build the firmware if needed, reset the probe into its bootloader with a "
            "1200-baud touch, wait for the bootloader's serial port and write the hex with "
            "avrdude (verified). See docs/firmware.md."
        ),
    )
    parser.add_argument(
        "--port", default="/dev/ttyACM0", help="the probe's serial port (default /dev/ttyACM0)"
    )
    parser.add_argument(
        "--hex",
        type=Path,
        metavar="F",
        default=None,
        help="firmware hex to write (default: build firmware/feather32u4)",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds to wait for the bootloader's port (default 10)",
    )
    parser.add_argument(
        "--ports-glob",
        default="/dev/ttyACM*",
        metavar="GLOB",
        help="where the bootloader's port may appear (default /dev/ttyACM*)",
    )
    parser.add_argument("--avrdude", default="avrdude", help=argparse.SUPPRESS)
    parser.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    try:
        flashing.flash(
            args.port,
            args.hex,
            avrdude=args.avrdude,
            ports_glob=args.ports_glob,
            timeout_s=args.timeout,
        )
    except (flashing.ImageError, flashing.PortNotFoundError):
        raise  # bad input: one line and exit 2 through the CLI, like every other command
    except flashing.FlashError as exc:
        print(f"stipi-daemon flash: {exc}", file=sys.stderr)
        return 1
    return 0
