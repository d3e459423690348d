"""Lazy registry: adapters chosen by config kind, imported by name only when used.

Runtime code (the application, the probe link and its transports, the cameras, storage,
measurement, analysis, protocol, report) never imports :mod:`stipi_daemon.sim`: a config
that asks for a simulated or emulated device (``camera.kind: simulator``,
``probe.transport.kind: emulated``, a BLE probe with ``emulate`` or ``hci`` set) names it
here, and :func:`load` imports the implementation on first use, by a ``"module:attribute"``
string (bleak's habit of choosing its backend by name). A run on real devices therefore
never loads the simulator, and the layer rule "runtime imports no ``sim``" holds
statically, for every import statement in the package.

:data:`SIMULATED` lists the simulated and emulated implementations, :data:`ADAPTERS` the
real ones that are chosen by config kind in the same way (so a source's module, with its
heavy dependencies, loads only when a config asks for it). Names read
``"<role>:<kind>"``: ``camera:<kind>`` and ``transport:<kind>`` follow the config's
``kind`` field.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any, Final

__all__ = ["ADAPTERS", "SIMULATED", "RegistryError", "load", "target"]

#: Simulated and emulated implementations by registered name: ``"module:attribute"``.
SIMULATED: Final[dict[str, str]] = {
    # The scene simulator as a live camera (camera.kind: simulator).
    "camera:simulator": "stipi_daemon.sim.camera:SimulatorCamera",
    # An emulated Feather on a pty behind the real serial path (transport.kind: emulated).
    "transport:emulated": "stipi_daemon.sim.emulated_transport:EmulatedTransport",
    # An emulated BLE probe playing a scene on a virtual radio (ble transport's `emulate`).
    "ble:emulated_probe": "stipi_daemon.sim.ble.emulation:start_emulated_probe",
    # bleak on Bumble's host stack: a virtual radio or a dongle (ble transport's `hci`).
    "ble:bumble_adapter": "stipi_daemon.sim.ble.bleak_backend:BumbleAdapter",
    # A simulated scene's calibration, threshold p, waveguide ROI and ground truth.
    "scene:imaging": "stipi_daemon.sim.imaging:scene_imaging",
}

#: Real adapters chosen by config kind, by registered name: ``"module:attribute"``.
ADAPTERS: Final[dict[str, str]] = {
    "camera:v4l2": "stipi_daemon.cameras.v4l2:V4L2Camera",
    "camera:file": "stipi_daemon.cameras.video_file:VideoFileCamera",
    "transport:serial": "stipi_daemon.probe.transports.serial:SerialTransport",
    "transport:ble": "stipi_daemon.probe.transports.ble:BleTransport",
}


class RegistryError(LookupError):
    """A name is not registered, or its ``"module:attribute"`` target cannot be imported."""


def target(name: str) -> str:
    """The ``"module:attribute"`` string registered as ``name``.

    Raises
    ------
    RegistryError
        ``name`` is in neither :data:`SIMULATED` nor :data:`ADAPTERS` (the message lists
        the registered names).
    """
    found = SIMULATED.get(name) or ADAPTERS.get(name)
    if found is None:
        known = ", ".join(sorted(SIMULATED | ADAPTERS))
        raise RegistryError(f"no implementation registered as {name!r} (registered: {known})")
    return found


def load(name: str) -> Any:
    """Import and return the object registered as ``name`` (a class or a function).

    The module is imported on the first call (Python caches it afterwards), so nothing
    registered here is loaded by a run that does not ask for it.

    Parameters
    ----------
    name : str
        A registered name, e.g. ``"camera:simulator"`` or ``"transport:serial"``.

    Raises
    ------
    RegistryError
        ``name`` is not registered, or its module or attribute is missing.
    """
    dotted = target(name)
    module_name, _, attribute = dotted.partition(":")
    try:
        module = import_module(module_name)
    except ImportError as exc:
        raise RegistryError(f"{name!r}: cannot import {module_name} ({exc})") from exc
    try:
        return getattr(module, attribute)
    except AttributeError:
        raise RegistryError(f"{name!r}: {module_name} has no attribute {attribute!r}") from None
