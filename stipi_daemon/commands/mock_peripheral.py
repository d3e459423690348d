"""``stipi-daemon mock-peripheral --scene SCENE``: the emulated probe as a real BLE peripheral.

Thin shell over :func:`stipi_daemon.sim.ble.mock_peripheral.serve`: opens a Bluetooth
controller with Bumble (``--transport usb:0``, ``hci-socket:0``, ``serial:...``,
``virtual:NAME`` for an in-process radio, or ``loopback:PORT`` for a virtual radio that a
daemon in another process reaches on 127.0.0.1:PORT with ``hci: loopback:PORT``), advertises
the probe's name and the Nordic UART Service, and streams the scene's load-cell samples in
the real wire protocol, answering commands as the firmware does, with the module's BLE
limits. A second machine's ``stipi-daemon`` (bleak on BlueZ) connects to it over the air as
to a probe (docs/bench.md). Optional periodic faults: drop the link, go silent, disappear.
Runs until ``--duration`` or Ctrl-C, then prints what the module did. The simulator is
imported only when the command runs.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
from pathlib import Path

__all__ = ["register", "run"]


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    parser = subparsers.add_parser(
        "mock-peripheral",
        help="emulate the probe as a BLE peripheral (Bumble) playing a scene",
        description=(
            "Advertise the probe's name and the Nordic UART Service on a Bluetooth controller "
            "driven by Bumble and stream SCENE's load-cell samples in the real wire protocol. "
            "No dongle: --transport loopback:9321 and a daemon with "
            "configs/probe-ble-loopback.yaml in another terminal. See docs/bench.md."
        ),
    )
    # dest differs from the top-level --scene (a measurement's scene override)
    parser.add_argument(
        "--scene", type=Path, required=True, dest="scene_file", help="scene YAML file"
    )
    parser.add_argument(
        "--transport",
        required=True,
        metavar="SPEC",
        help=(
            "controller: usb:0, hci-socket:0, serial:/dev/ttyACM0,1000000, virtual:NAME, or "
            "loopback:PORT (a virtual radio served on 127.0.0.1:PORT to other processes; "
            "0 picks a free port)"
        ),
    )
    parser.add_argument("--seed", type=int, default=None, help="scene seed (default: scene's)")
    parser.add_argument("--name", default="STIPI-01", help="advertised name (default STIPI-01)")
    parser.add_argument("--speed", type=float, default=1.0, help="session clock speed [-]")
    parser.add_argument("--duration", type=float, default=None, help="stop after [s, session]")
    parser.add_argument("--max-mtu", type=int, default=23, help="largest ATT MTU accepted [B]")
    parser.add_argument(
        "--connection-interval-ms", type=float, default=15.0, help="connection interval [ms]"
    )
    parser.add_argument(
        "--notifications-per-event", type=int, default=4, help="notifications per event"
    )
    parser.add_argument("--drop", type=float, default=0.0, help="notification loss chance [-]")
    parser.add_argument("--corrupt", type=float, default=0.0, help="bit-flip chance [-]")
    parser.add_argument("--delay-ms", type=float, default=0.0, help="extra latency [ms]")
    parser.add_argument("--disconnect-every", type=float, default=None, help="drop link [s]")
    parser.add_argument("--silent-every", type=float, default=None, help="go silent every [s]")
    parser.add_argument("--silent-for", type=float, default=3.0, help="silence length [s]")
    parser.add_argument("--disappear-every", type=float, default=None, help="vanish every [s]")
    parser.add_argument("--disappear-for", type=float, default=5.0, help="absence length [s]")
    parser.add_argument(
        "--refuse-connections", type=int, default=0, help="drop the first N connections at once"
    )
    parser.add_argument("--report-every", type=float, default=5.0, help="status line period [s]")
    parser.add_argument("--quiet", action="store_true", help="no status lines")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from stipi_daemon.sim.ble.mock_peripheral import MockPeripheralOptions, serve

    opts = MockPeripheralOptions(
        scene=args.scene_file,
        transport=args.transport,
        seed=args.seed,
        name=args.name,
        speed=args.speed,
        duration_s=args.duration,
        max_mtu=args.max_mtu,
        connection_interval_ms=args.connection_interval_ms,
        notifications_per_event=args.notifications_per_event,
        drop=args.drop,
        corrupt=args.corrupt,
        delay_ms=args.delay_ms,
        disconnect_every_s=args.disconnect_every,
        silent_every_s=args.silent_every,
        silent_for_s=args.silent_for,
        disappear_every_s=args.disappear_every,
        disappear_for_s=args.disappear_for,
        report_every_s=args.report_every,
        refuse_connections=args.refuse_connections,
        quiet=args.quiet,
    )
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(opts))
    return 0
