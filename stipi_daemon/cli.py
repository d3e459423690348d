"""Command-line entry point ``stipi-daemon``.

Only argument parsing and dispatch live here; every subcommand calls into the package.
User-facing errors (:class:`~stipi_daemon.errors.StipiError`) are printed as one line on
stderr, never as a traceback; the exit statuses are :data:`EXIT_STATUSES`.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

from stipi_daemon import __version__
from stipi_daemon.commands import register_all
from stipi_daemon.errors import (
    EXIT_BAD_INPUT,
    EXIT_DAMAGED,
    ConfigError,
    DamagedSessionError,
    StipiError,
    Terminated,
)
from stipi_daemon.storage.metadata import FIELD_DOCS, METADATA_FIELDS

#: What each exit status means (``--help`` and README.md say the same).
EXIT_STATUSES = """exit status:
  0    the command did its work; a measurement was made, whatever its verdict (the
       verdict is in the output and in summary.json)
  1    a fault stopped the measurement before it had results (analyze: no results);
       the output could not be written (a full disk)
  2    bad input: arguments, a config, scene or data file, a session not found
  3    analyze --recompute-sk: the recount did not reproduce the stored S_k
  4    a session's stored data is damaged (corrupt database, failed integrity check)
  129  the terminal closed (SIGHUP); 130 interrupted (Ctrl-C, or the measurement's
       output closed or full); 143 terminated (SIGTERM); 141 the output was closed"""
#: errno of a write to standard output that failed: disk full, quota, file too large, I/O.
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO})


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="stipi-daemon",
        epilog=EXIT_STATUSES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=(
            "Acquisition and analysis for the STIP-I tactile imaging probe: force and\n"
            "video of an indenter pitting test, turned into pitting depth, rebound force,\n"
            "recovery time, elasticity, viscosity and an edema severity class."
        ),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="run one measurement as FILE configures it (e.g. configs/demo.yaml)",
    )
    parser.add_argument(
        "--realtime",
        action="store_true",
        help="pace simulated devices at real time instead of the config's run.speed "
        "(the results are the same)",
    )
    parser.add_argument("--quiet", action="store_true", help="print only the results' path")
    parser.add_argument(
        "--scene",
        type=Path,
        metavar="PATH",
        help="with --config: the scene the simulated probe and camera play instead of the "
        "config's (e.g. configs/scenes/grade2.yaml)",
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        dest="overrides",
        metavar="KEY=VALUE",
        help="with --config: change one config field by its dotted path, validated like the "
        "file (repeatable), e.g. --set measurement.stop_when_settled=true",
    )
    for field in METADATA_FIELDS:
        parser.add_argument(
            f"--{field}",
            dest=f"metadata_{field}",
            metavar="TEXT",
            help=f"with --config: the session's {field}, {FIELD_DOCS[field]} (replaces the "
            f"config's session.{field}; stored in manifest.json metadata)",
        )
    subparsers = parser.add_subparsers(title="commands", metavar="COMMAND")
    register_all(subparsers)
    return parser


def _run(args: argparse.Namespace) -> int:
    from stipi_daemon.app.config import load_config
    from stipi_daemon.app.daemon import run_measurement
    from stipi_daemon.app.session_metadata import apply_metadata_options

    config = load_config(args.config, scene=args.scene, overrides=args.overrides)
    config = apply_metadata_options(config, _metadata_options(args))
    outcome = run_measurement(config, speed=1.0 if args.realtime else None, quiet=args.quiet)
    if args.quiet:
        print(outcome.session_dir)
    return outcome.exit_code


def _metadata_options(args: argparse.Namespace) -> dict[str, str | None]:
    """The daemon's ``--subject/--site/--operator/--note`` values (None: not given)."""
    return {f: getattr(args, f"metadata_{f}", None) for f in METADATA_FIELDS}


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        handler = getattr(args, "handler", None)
        if (args.scene is not None or args.overrides) and (handler is not None or not args.config):
            raise ConfigError(
                "--scene/--set change the config of a measurement: give them with --config "
                "FILE and no command"
            )
        given = any(v is not None for v in _metadata_options(args).values())
        if given and (handler is not None or not args.config):
            raise ConfigError(
                "--subject/--site/--operator/--note describe a measurement: give them with "
                "--config FILE and no command"
            )
        if handler is None and args.config is not None:
            return _run(args)
        if handler is None:
            parser.print_help()
            return 0
        result: int = handler(args)
        return result
    except DamagedSessionError as exc:
        print(f"stipi-daemon: error: {exc}", file=sys.stderr)
        return EXIT_DAMAGED
    except StipiError as exc:
        print(f"stipi-daemon: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Terminated as exc:  # SIGTERM, SIGHUP, standard output failed: as after Ctrl-C
        with contextlib.suppress(OSError):  # one line, if stderr can still be written
            print(f"stipi-daemon: {exc.reason}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        # Ctrl-C: the daemon has already closed its devices and finished the session as
        # 'aborted' (asyncio.run cancels it and re-raises the interrupt here).
        print("stipi-daemon: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # Whatever read the output stopped reading (``sessions list | head``): nothing more
        # can reach it. Stdout goes to /dev/null so that Python's own flush at exit does not
        # fail again; exit status as a shell gives a process ended by SIGPIPE.
        from stipi_daemon.app.console import stdout_to_devnull

        stdout_to_devnull()
        return 128 + signal.SIGPIPE
    except OSError as exc:
        if not _stdout_failed(exc):
            raise
        # Standard output cannot be written (``>/dev/full``, an I/O error): one line.
        with contextlib.suppress(OSError):
            print(f"stipi-daemon: error: cannot write the output: {exc}", file=sys.stderr)
        return 1


def _stdout_failed(exc: OSError) -> bool:
    """Whether ``exc`` is standard output failing (a print to a full disk, an I/O error:
    no file name, an errno of writing), in which case stdout now points at /dev/null so
    that Python's flush at exit does not fail again. Files the commands write raise
    StipiError naming the file instead."""
    from stipi_daemon.app.console import stdout_to_devnull

    if exc.filename is not None or exc.errno not in _WRITE_ERRNOS or sys.stdout is None:
        return False
    with contextlib.suppress(OSError, ValueError):
        stdout_to_devnull()
    return True


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
