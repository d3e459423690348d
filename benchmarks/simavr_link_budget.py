"""Sample-rate budget of the probe's UART link, measured on the firmware in simavr.

Runs the real firmware ELF in the libsimavr harness (firmware/feather32u4/simavr/), streams
at each rate of a sweep and counts what the host receives: index gaps, frames lost on the
link, STATUS.dropped, bytes per second on the wire, the sample-rate error in simulated time
and the simulation's speed. Two sweeps: the sample rate at the firmware's own UART speed,
and, at 1000 Hz, the link's byte rate (harness ``--uart-bytes-per-s``) to find the slowest
link that still carries every sample. Prints Markdown tables (pasted into docs/firmware.md,
"Measured in simulation").

Run: ``./dev python benchmarks/simavr_link_budget.py`` (needs avr-gcc and libsimavr-dev).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT))

import numpy as np  # noqa: E402

from stipi_daemon.protocol.messages import (  # noqa: E402
    AckStatus,
    SetRate,
    StreamStart,
    StreamStop,
)
from tests.firmware.simavr_probe import (  # noqa: E402
    BLE_PROBE_DONE_S,
    SimProbe,
    build,
    flatten,
    rate_hz,
    samples_of,
)


@dataclass(frozen=True)
class RunResult:
    """One streaming run: what the host saw."""

    rate_hz: int
    link_bytes_per_s: float
    samples_expected: int
    samples_received: int
    probe_dropped: int
    frames_lost: int
    wire_bytes_per_s: float
    rate_error_ppm: float
    speed: float


def run(rate: int, sim_seconds: float, link_bytes_per_s: float | None) -> RunResult:
    """Stream ``sim_seconds`` of simulated time at ``rate`` [Hz] and account for every sample."""
    extra = ["--uart-bytes-per-s", str(link_bytes_per_s)] if link_bytes_per_s else []
    probe = SimProbe("triangle:200:3100:0.5", extra)
    try:
        probe.wait_sim_time(BLE_PROBE_DONE_S)
        assert probe.command(SetRate(rate)).status == AckStatus.OK
        before = probe.next_status().dropped
        assert probe.command(StreamStart()).status == AckStatus.OK
        frames = probe.collect_samples(int(rate * sim_seconds), timeout_s=120)
        assert probe.command_retry(StreamStop()).status == AckStatus.OK
        after = probe.next_status().dropped
        uart = probe.log.of("UART")
        link = float(uart[-1]["bytes_per_s"]) if uart else float("nan")
        s = flatten(frames)
        first = samples_of(frames[0])
        last = samples_of(frames[-1])
        expected = last.first_index + last.count - first.first_index
        span_s = (s.t_us[-1] - s.t_us[0]) * 1e-6
        # Wire bytes between the first and the last SAMPLES frame's stream offsets.
        wire = frames[-1].stream_offset - frames[0].stream_offset
        lost = sum(
            f.lost_before
            for f in probe.rx.frames
            if frames[0].stream_offset < f.stream_offset <= frames[-1].stream_offset
        )
        return RunResult(
            rate_hz=rate,
            link_bytes_per_s=link,
            samples_expected=expected,
            samples_received=len(s.index),
            probe_dropped=after - before,
            frames_lost=lost,
            wire_bytes_per_s=wire / span_s,
            rate_error_ppm=(rate_hz(s) / rate - 1) * 1e6 if len(np.unique(s.index)) > 1 else 0.0,
            speed=probe.log.last_speed(),
        )
    finally:
        probe.close()


def table(results: list[RunResult]) -> str:
    head = (
        "| rate [Hz] | link [B/s] | samples taken | received | lost | STATUS.dropped | "
        "frames lost on link | wire [B/s] | rate error [ppm] | sim speed [x real time] |\n"
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    rows = "".join(
        f"| {r.rate_hz} | {r.link_bytes_per_s:.0f} | {r.samples_expected} | "
        f"{r.samples_received} | {r.samples_expected - r.samples_received} | "
        f"{r.probe_dropped} | {r.frames_lost} | {r.wire_bytes_per_s:.0f} | "
        f"{r.rate_error_ppm:+.0f} | {r.speed:.1f} |\n"
        for r in results
    )
    return head + rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated seconds per run")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    build("firmware", "harness")
    native = [run(r, args.seconds, None) for r in (16, 100, 250, 500, 1000)]
    print("Sample-rate sweep at the firmware's UART speed:\n")
    print(table(native))
    throttled = [run(1000, args.seconds, b) for b in (2000, 3000, 4000, 4500, 5000, 6000)]
    print("Link-speed sweep at 1000 Hz (harness --uart-bytes-per-s):\n")
    print(table(throttled))
    print(f"wall time {time.monotonic() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
