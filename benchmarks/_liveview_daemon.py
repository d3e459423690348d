"""The live view's cost to the real daemon at 720p60 (a part of ``liveview_cost.py``).

The daemon runs as it does for an operator (``python -m stipi_daemon --config FILE
--quiet``, a process of its own pinned to the benchmark's CPU). The probe is the emulated
Feather (:func:`benchmarks.daemon_latency.probe_process`: the firmware's model playing the
grade-III scene at 100 Hz) in a process of its own on the other CPU, on a pty the daemon
opens as ``probe.transport: {kind: serial}``, as a real probe's firmware runs on its MCU
(so the daemon's CPU is its own work only). The camera delivers 1280x720 MJPG frames at 60
fps which the daemon decodes as it does a real MJPG camera's (``camera: {kind: file, pace:
true, loop: true}``: the capture thread reads frame k's JPEG, waits for its capture time
and only then decodes it to gray; the video rendered once by ``stipi-daemon simulate`` from
a 2 s excerpt of the grade-III scene with sensor noise, so its JPEGs cost what a camera's
do). The session video is stored as for a real probe (``storage.video: passthrough``);
``run: {clock: wall, speed: 1}``; ``view.enabled: true``. Once it prints the view's
address, 0, 1 or 20 viewers (a process on the other CPU, a websocket each, taking the
frames the server pushes) connect; after ``WARM_S`` the daemon process's CPU (``utime +
stime`` of ``/proc/<pid>/stat``, every thread) is read at the start and the end of a window
of fixed wall time; then the daemon is stopped (SIGTERM) and reaped (``os.wait4``, its
whole CPU beside).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
W, H, FPS = 1280, 720, 60.0
#: Viewers per mode of the real daemon's runs [-].
DAEMON_MODES = {"0 viewers": 0, "1 viewer": 1, "20 viewers": 20}
#: Wall time from the view's address to the start of the CPU window [s] (viewers connect).
WARM_S = 2.0
#: Longest wait for the daemon to print the view's address [s].
START_TIMEOUT_S = 120.0
_TICK_S = 1.0 / os.sysconf("SC_CLK_TCK")


def prepare(tmp: Path) -> dict[str, Any]:
    """Render the camera's MJPG video once (``stipi-daemon simulate``) and write its
    calibration; return the daemon's config without ``storage``."""
    import dataclasses

    import yaml

    from stipi_daemon.analysis.calibration import save_calibration
    from stipi_daemon.analysis.imaging import CircleROI
    from stipi_daemon.sim.physics import scaled_calibration
    from stipi_daemon.sim.scene import load_scene

    grade3 = ROOT / "configs" / "scenes" / "grade3.yaml"
    doc = yaml.safe_load(grade3.read_text())
    doc["name"] = "grade3_liveview_720p"
    doc["force_profile"].update({"approach_s": 0.5, "hold_s": 1.0, "recovery_s": 0.5})
    doc["camera"]["pixel_format"] = "mjpg"  # as an MJPG camera sends it
    doc["effects"] = [{"name": "sensor_noise", "sigma_levels": 2.0}]  # a sensor's JPEGs
    scene = tmp / "grade3_liveview_720p.yaml"
    scene.write_text(yaml.safe_dump(doc))
    out = tmp / "render"
    subprocess.run(
        [
            *(sys.executable, "-m", "stipi_daemon", "simulate", str(scene), "--out", str(out)),
            *("--resolution", f"{W}x{H}", "--fps", f"{FPS:g}", "--quiet"),
        ],
        check=True,
    )
    truth = json.loads((out / "ground_truth.json").read_text())
    rendered = load_scene(scene).with_camera(width=W, height=H, fps=FPS)
    disc = CircleROI(kind="circle", **{k: float(v) for k, v in truth["roi"].items()})
    cal = dataclasses.replace(scaled_calibration(rendered)[0], roi=disc)
    cal_path = save_calibration(tmp / "calibration_720p.json", cal)
    video = next(p for p in sorted(out.iterdir()) if p.name.startswith("video."))
    return {
        "probe": {"transport": {"kind": "serial", "port": "?"}, "rate_hz": 100},
        "probe_scene": str(grade3),
        "camera": {"kind": "file", "path": str(video), "pace": True, "loop": True},
        "calibration": str(cal_path),
        "imaging": {
            "threshold_p": int(truth["frame"]["threshold_p"]),
            "roi": disc.model_dump(mode="json"),
        },
        "run": {"speed": 1.0, "clock": "wall"},
        "view": {"enabled": True},
    }


def _cpu_s(pid: int) -> float:
    """CPU time of process ``pid`` so far, every thread, user + system [s]."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) * _TICK_S  # utime, stime: fields 14, 15


def _address(daemon: subprocess.Popen[bytes], err: Path) -> str:
    """The view's address, once the daemon has printed it (on stderr, ``--quiet``)."""
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        for line in err.read_text(errors="replace").splitlines():
            if "live view: http://" in line:
                return line.split("live view: ", 1)[1].split()[0]
        if daemon.poll() is not None:
            break
        time.sleep(0.05)
    daemon.kill()
    daemon.wait()
    raise RuntimeError(f"the daemon printed no view address:\n{err.read_text()[-3000:]}")


def _probe(scene: str, work: Path, cpus: set[int]) -> tuple[subprocess.Popen[bytes], Path]:
    """The emulated Feather in a process of its own on ``cpus``, on a pty at the returned
    path, until its stdin closes."""
    from benchmarks.daemon_latency import start_probe

    link = work / "ttyFEATHER"
    probe, _ = start_probe(scene, link, sorted(cpus))
    return probe, link


def _stop(daemon: subprocess.Popen[bytes]) -> Any:
    """SIGTERM (SIGKILL after 30 s), then reap it: its resource usage (``os.wait4``)."""
    daemon.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 30.0
    while True:
        pid, _, usage = os.wait4(daemon.pid, os.WNOHANG)
        if pid:
            daemon.returncode = 0  # reaped here, not by Popen
            return usage
        if time.monotonic() > deadline:
            daemon.kill()
            deadline = float("inf")
        time.sleep(0.05)


def run_daemon_mode(
    tmp: Path, config: dict[str, Any], mode: str, window_s: float, viewer_cpus: set[int], run: int
) -> dict[str, Any]:
    """One run of the daemon with ``DAEMON_MODES[mode]`` viewers: its CPU over the window
    [s], the window's wall time [s], its whole CPU (``os.wait4``) [s], what the viewers got."""
    import shutil

    work = tmp / f"run{run}"
    work.mkdir()
    cfg = {k: v for k, v in config.items() if k != "probe_scene"}
    cfg["storage"] = {"root": str(work / "sessions"), "min_free_mb": 0}
    probe, link = _probe(config["probe_scene"], work, viewer_cpus)
    cfg["probe"] = {**cfg["probe"], "transport": {"kind": "serial", "port": str(link)}}
    cfg["storage"]["video"] = "passthrough"  # as configured for a real probe
    path = work / "daemon.yaml"
    path.write_text(json.dumps(cfg))  # YAML is a superset of JSON
    err = work / "stderr.txt"
    try:
        with err.open("wb") as err_f:
            daemon = subprocess.Popen(
                [sys.executable, "-m", "stipi_daemon", "--config", str(path), "--quiet"],
                stdout=subprocess.DEVNULL,
                stderr=err_f,
                cwd=work,
            )
        url = _address(daemon, err)
        n = DAEMON_MODES[mode]
        viewers = None
        if n:
            viewers = subprocess.Popen(
                [
                    *(sys.executable, str(ROOT / "benchmarks" / "liveview_cost.py")),
                    *("--viewers", str(n), "--url", url),
                    *("--seconds", repr(WARM_S + window_s + 0.5)),
                    *("--cpus", ",".join(map(str, sorted(viewer_cpus)))),
                ],
                stdout=subprocess.PIPE,
                text=True,
            )
        time.sleep(WARM_S)
        t0, cpu0 = time.monotonic(), _cpu_s(daemon.pid)
        time.sleep(window_s)
        t1, cpu1 = time.monotonic(), _cpu_s(daemon.pid)
        alive = daemon.poll() is None
        got: dict[str, float] = {}
        if viewers is not None:
            out, _ = viewers.communicate(timeout=60)
            got = json.loads(out.strip().splitlines()[-1])
        usage = _stop(daemon)
    finally:
        probe.communicate(timeout=30)  # stdin closed: the probe ends
    if not alive:
        raise RuntimeError(f"the daemon ended during the window:\n{err.read_text()[-3000:]}")
    shutil.rmtree(work / "sessions", ignore_errors=True)
    return {
        "cpu_s": cpu1 - cpu0,
        "wall_s": t1 - t0,
        "total_cpu_s": usage.ru_utime + usage.ru_stime,
        "viewers": got,
    }


def measure_daemon(
    tmp: Path, window_s: float, rounds: int, viewer_cpus: set[int]
) -> dict[str, list[dict[str, Any]]]:
    """Every mode of :data:`DAEMON_MODES`, ``rounds`` times, the order rotating."""
    config = prepare(tmp)
    modes = tuple(DAEMON_MODES)
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    k = 0
    for r in range(rounds):
        for mode in modes[r % len(modes) :] + modes[: r % len(modes)]:
            k += 1
            got = run_daemon_mode(tmp, config, mode, window_s, viewer_cpus, k)
            runs[mode].append(got)
            print(
                f"daemon round {r + 1}/{rounds}: {mode}: {got['cpu_s']:.2f} s CPU in "
                f"{got['wall_s']:.2f} s",
                flush=True,
            )
    return runs
