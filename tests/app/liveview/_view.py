"""Shared pieces of the view tests: a live state with frames, a served view, raw requests."""

from __future__ import annotations

import http.client
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from stipi_daemon.app.liveview.server import ViewServer
from stipi_daemon.app.liveview.state import LiveState, ViewInfo
from stipi_daemon.measurement.pipeline import LiveParameters

#: The threshold p the test frames are counted with [8-bit intensity].
THRESHOLD_P = 100


def view_info(subject: str = "P-017", note: str = "left ankle") -> ViewInfo:
    return ViewInfo(
        session_id="20260101T000000-test",
        metadata={"subject": subject, "site": "Lab A", "operator": "AB", "note": note},
        threshold_p=THRESHOLD_P,
        roi={"kind": "circle", "cx_px": 80.0, "cy_px": 60.0, "radius_px": 50.0},
        pitting_duration_s=15.0,
        recovery_max_s=105.0,
        force_band_n=(14.5, 17.5),
    )


def frame_image(k: int, width: int = 160, height: int = 120) -> np.ndarray:
    """A bright frame with a dark disc whose radius grows with ``k`` (S_k > 0)."""
    img = np.full((height, width), 200, dtype=np.uint8)
    yy, xx = np.mgrid[0:height, 0:width]
    img[(xx - width // 2) ** 2 + (yy - height // 2) ** 2 <= (10 + k % 30) ** 2] = 30
    return img


def publish(state: LiveState, k: int) -> None:
    """Frame ``k`` (at 60 fps), a force reading and the session time, into ``state``."""
    t = k / 60.0
    img = frame_image(k)
    state.frame(k, t, int((img <= THRESHOLD_P).sum()), img)
    state.force_n(t, 16.0 + 0.1 * np.sin(k / 10.0))
    state.tick(t, None)


def flagged_params() -> LiveParameters:
    """Live parameters whose fitted tau has a large standard error (flagged)."""
    return LiveParameters(
        t_s=30.0,
        elapsed_s=10.0,
        depth_mm=1.2,
        rebound_force_n=3.0,
        recovery_time_s=8.0,
        settled=False,
        elasticity_kpa=12.0,
        tau_s=5.0,
        tau_se_s=4.0,
        viscosity_n_s_per_mm2=0.096,  # eta = E T_r = 12 kPa * 8 s (Eq. 8)
        viscosity_from_time_constant_n_s_per_mm2=0.06,  # eta_tau = E tau = 12 kPa * 5 s
    )


@contextmanager
def served(state: LiveState, host: str = "127.0.0.1") -> Iterator[ViewServer]:
    server = ViewServer(state, host, 0)
    server.start()
    try:
        yield server
    finally:
        server.stop()


def get(
    server: ViewServer, path: str, headers: dict[str, str] | None = None, method: str = "GET"
) -> tuple[int, dict[str, str], bytes]:
    """A raw request to the server (Host given as is, when in ``headers``)."""
    con = http.client.HTTPConnection(server.host, server.port, timeout=10)
    try:
        hdrs = dict(headers or {})
        con.putrequest(method, path, skip_host="Host" in hdrs)
        for k, v in hdrs.items():
            con.putheader(k, v)
        con.endheaders()
        r = con.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        con.close()
