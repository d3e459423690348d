"""The live view of a measurement: when it is served, what it is told, and its address.

:func:`serving_live_view` starts a :class:`~.server.ViewServer` over a new
:class:`~.state.LiveState` when the config's ``view`` section (or an interactive run)
asks for it, prints its address on the console, and stops it when the block ends. The
acquisition publishes into the state (:mod:`stipi_daemon.app.acquisition`); the server
reads it in its own thread. A view that cannot listen (a port in use) is a warning: the
measurement goes on without it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

from stipi_daemon.app.liveview.server import ViewServer, is_loopback
from stipi_daemon.app.liveview.state import LiveState, ViewInfo
from stipi_daemon.errors import StipiError
from stipi_daemon.measurement.pipeline import LiveParameters

if TYPE_CHECKING:
    from stipi_daemon.app.config import ViewSettings
    from stipi_daemon.app.console import OperatorConsole

__all__ = ["RELATIVE_SE_FLAG", "live_statuses", "serving_live_view", "view_wanted"]

#: A fitted time constant whose standard error exceeds this fraction of it is flagged [-].
RELATIVE_SE_FLAG = 0.25

_log = logging.getLogger(__name__)


def view_wanted(settings: ViewSettings, console: OperatorConsole) -> bool:
    """Whether to serve the live view: ``view.enabled``, else when the run is interactive
    (the console writes to a terminal and is not quiet)."""
    if settings.enabled is not None:
        return settings.enabled
    return not console.quiet and console.out.isatty()


def live_statuses(params: LiveParameters) -> dict[str, str]:
    """Each live parameter's status as the view colours it: ``invalid`` (not computable
    yet), ``provisional`` (T_r before S_k has settled, and eta = E*T_r and eta_tau = E*tau
    that depend on it or on the fit), ``flagged`` (no pit: D_p <= 0; a fit whose tau has a
    standard error above :data:`RELATIVE_SE_FLAG` of it, and eta_tau from it), ``ok``."""

    def present(v: float | None) -> bool:
        return v is not None and math.isfinite(v)

    status = {
        "depth_mm": "ok" if present(params.depth_mm) else "invalid",
        "rebound_force_n": "ok" if present(params.rebound_force_n) else "invalid",
        "recovery_time_s": "ok" if params.settled else "provisional",
        "elasticity_kpa": "ok" if present(params.elasticity_kpa) else "invalid",
        "tau_s": "ok" if present(params.tau_s) else "invalid",
        "viscosity_n_s_per_mm2": "ok" if present(params.viscosity_n_s_per_mm2) else "invalid",
        "viscosity_from_time_constant_n_s_per_mm2": (
            "ok" if present(params.viscosity_from_time_constant_n_s_per_mm2) else "invalid"
        ),
    }
    if present(params.depth_mm) and params.depth_mm <= 0.0:
        status["depth_mm"] = "flagged"
    tau, se = params.tau_s, params.tau_se_s
    if present(tau) and (
        not present(se) or (tau is not None and se is not None and se > RELATIVE_SE_FLAG * abs(tau))
    ):
        status["tau_s"] = "flagged"
        if status["viscosity_from_time_constant_n_s_per_mm2"] == "ok":
            status["viscosity_from_time_constant_n_s_per_mm2"] = "flagged"
    for eta in ("viscosity_n_s_per_mm2", "viscosity_from_time_constant_n_s_per_mm2"):
        if not params.settled and status[eta] == "ok":
            status[eta] = "provisional"
    return status


@contextlib.contextmanager
def serving_live_view(
    settings: ViewSettings, info: ViewInfo, console: OperatorConsole
) -> Iterator[tuple[LiveState, ViewServer] | None]:
    """Serve the live view while the block runs, when :func:`view_wanted`; yields the state
    to publish into and the server (None: no view)."""
    if not view_wanted(settings, console):
        yield None
        return
    state = LiveState(info)
    server = ViewServer(state, settings.host, settings.port)
    try:
        url = server.start()
    except StipiError as exc:
        _say(console, f"warning: {exc}; measuring without the live view", "bold yellow")
        yield None
        return
    _say(console, f"live view: {url}", "bold")
    if not is_loopback(settings.host):
        _say(
            console,
            f"warning: the live view listens on {settings.host}, not loopback: other machines "
            "can reach it (the token in the address is all that keeps them out)",
            "bold yellow",
        )
    try:
        yield state, server
    finally:
        state.finish()
        server.stop()


def _say(console: OperatorConsole, text: str, style: str) -> None:
    """A line on the console; on stderr when the console is quiet (an explicit ``view``)."""
    if console.quiet:
        print(f"stipi-daemon: {text}", file=sys.stderr, flush=True)
    else:
        console.line(text, style=style)
