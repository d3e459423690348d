"""The live view in a real browser (Debian's Chromium), during a real simulated run.

The daemon measures the short grade-I scene with ``view.enabled``; the test opens the
printed address in Chromium and watches the page while the run goes on: it must show the
phase and the prompt the console shows, the frame must change as frames come (with the
ROI outlined over it), the traces must grow. A second test serves a live state with
flagged parameters and hostile metadata: the flagged quantity is shown flagged, the
metadata as text.
"""

from __future__ import annotations

import io
import re
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import RunOutcome, run_measurement
from stipi_daemon.app.liveview.live import live_statuses
from stipi_daemon.app.liveview.state import LiveState
from tests.app.liveview._browser import chromium, screenshot, text, wait_for
from tests.app.liveview._view import flagged_params, publish, served, view_info
from tests.daemon._support import short_config

URL_LINE = re.compile(r"live view: (http://\S+)")


def _page_state(driver: Any) -> dict[str, Any]:
    return dict(
        driver.execute_script(
            "const f = document.getElementById('frame');"
            "return {phase: document.getElementById('phase').textContent,"
            " prompt: document.getElementById('prompt').textContent,"
            " seq: f.dataset.seq || null, width: f.naturalWidth,"
            " force: +(document.getElementById('trace-force').dataset.points || 0),"
            " sk: +(document.getElementById('trace-sk').dataset.points || 0),"
            " roi: document.querySelectorAll('#overlay .roi').length};"
        )
    )


@pytest.mark.timeout(300)
def test_the_live_page_follows_the_run(tmp_path: Path) -> None:
    cfg = short_config(tmp_path, {}, speed=1.0, measurement={"stop_when_settled": True})
    config = load_config(cfg, overrides=[])
    config = config.model_copy(update={"view": config.view.model_copy(update={"enabled": True})})
    out = io.StringIO()
    result: list[RunOutcome] = []
    run = threading.Thread(
        target=lambda: result.append(run_measurement(config, out=out, live=False)), daemon=True
    )
    samples: list[dict[str, Any]] = []
    with chromium(tmp_path / "profile") as driver:  # started before the run: it takes a while
        run.start()
        url = wait_for(lambda: (m := URL_LINE.search(out.getvalue())) and m.group(1), 60, "url")
        driver.get(url)
        wait_for(lambda: text(driver, "mode") == "live", why="the page's websocket")
        shot = False
        while run.is_alive():
            s = _page_state(driver)
            samples.append(s)
            if not shot and s["phase"] == "recovery" and s["seq"] and s["sk"] > 50:
                screenshot(driver, "liveview-live.png", tmp_path)
                shot = True
            time.sleep(0.2)
    run.join(timeout=60)
    assert result and result[0].exit_code == 0
    console = out.getvalue()
    phases_seen = {s["phase"] for s in samples}
    assert {"pitting", "recovery"} <= phases_seen, phases_seen
    for phase in phases_seen - {"-"}:  # every phase the page showed, the console showed
        assert f"-> {phase}:" in console or phase == "idle", phase
    prompt_keys = {
        line.split(">>", 1)[1].strip().split(":")[0]
        for line in console.splitlines()
        if ">>" in line
    }
    prompts = {s["prompt"].split(":")[0] for s in samples if s["prompt"]}
    assert prompts and prompts <= prompt_keys, (prompts, prompt_keys)
    seqs = [int(s["seq"]) for s in samples if s["seq"]]
    assert len(set(seqs)) >= 10, "the frame did not change as frames came"
    assert seqs == sorted(seqs)
    shown = [s for s in samples if s["seq"]]
    assert all(s["roi"] == 1 for s in shown)  # the ROI outlined over every frame shown
    # (an image that is being swapped for the next one has no size for a moment)
    assert sum(s["width"] > 0 for s in shown) >= 0.8 * len(shown)
    sk = [s["sk"] for s in samples]
    force = [s["force"] for s in samples]
    # the traces grew while the page watched (on a loaded machine the browser may show
    # few distinct states: the last against the first it drew, not against a fixed quarter)
    for trace in (sk, force):
        drawn = [n for n in trace if n > 0]
        assert drawn and trace[-1] > drawn[0], trace
    assert shot


def test_flagged_quantities_and_metadata_as_text(tmp_path: Path) -> None:
    hostile = "<img src=x onerror=\"document.title='owned'\">"
    state = LiveState(view_info(subject="P-<b>17</b>", note=hostile))
    params = flagged_params()
    statuses = live_statuses(params)
    assert statuses["tau_s"] == "flagged"
    state.live_parameters(params, statuses)
    state.phase_changed(1.0, "armed", "pitting", "force reached the band")
    state.set_prompt("Hold 16.0 ± 1.5 N: 9 s left")
    stop = threading.Event()

    def frames() -> None:
        k = 0
        while not stop.is_set():
            publish(state, k)
            k += 1
            time.sleep(1 / 30)

    feeder = threading.Thread(target=frames, daemon=True)
    feeder.start()
    try:
        with served(state) as server, chromium(tmp_path / "profile") as driver:
            driver.get(server.url)
            wait_for(lambda: text(driver, "phase") == "pitting", why="the phase")
            assert text(driver, "prompt") == "Hold 16.0 ± 1.5 N: 9 s left"
            assert wait_for(lambda: text(driver, "countdown").startswith("hold "), why="countdown")
            row = driver.execute_script(
                "const r = document.querySelector('#params tr[data-quantity=\"tau_s\"]');"
                "return r && [r.dataset.status, getComputedStyle(r.querySelector('.value')).color,"
                " r.querySelector('.status').textContent];"
            )
            assert row == ["flagged", "rgb(255, 153, 51)", "flagged"]
            ok_row = driver.execute_script(
                "const r = document.querySelector('#params tr[data-quantity=\"depth_mm\"]');"
                "return getComputedStyle(r.querySelector('.value')).color;"
            )
            assert ok_row != row[1]
            meta = text(driver, "meta")
            assert hostile in meta and "P-<b>17</b>" in meta
            assert driver.execute_script("return document.querySelectorAll('#meta *').length") == 0
            assert driver.title != "owned"
            first = wait_for(lambda: _page_state(driver)["seq"], why="a frame")
            wait_for(lambda: _page_state(driver)["seq"] not in (None, first), why="a new frame")
            n0 = _page_state(driver)["sk"]
            wait_for(lambda: _page_state(driver)["sk"] > n0, why="the S_k trace to grow")
    finally:
        stop.set()
        feeder.join()
