"""Shared test configuration.

Tests that need an external toolchain (g++, avr-gcc, simavr) call :func:`require_tool`;
it skips when the tool is missing, unless ``STIPI_REQUIRE_TOOLCHAIN=1`` (set by ``.ci/run``)
turns the skip into a failure so that CI never passes by skipping what matters.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from hypothesis import settings

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_REFERENCE = REPO_ROOT.parent / "shared" / "reference"


def require_tool(*names: str) -> None:
    """Skip (or fail under ``STIPI_REQUIRE_TOOLCHAIN=1``) unless every named program is on PATH."""
    missing = [n for n in names if shutil.which(n) is None]
    if not missing:
        return
    msg = f"toolchain missing: {', '.join(missing)}"
    if os.environ.get("STIPI_REQUIRE_TOOLCHAIN") == "1":
        pytest.fail(msg + " (STIPI_REQUIRE_TOOLCHAIN=1)")
    pytest.skip(msg)


def require_path(path: Path, what: str) -> None:
    """Skip (or fail under ``STIPI_REQUIRE_TOOLCHAIN=1``) unless ``path`` exists."""
    if path.exists():
        return
    msg = f"toolchain missing: {what} ({path})"
    if os.environ.get("STIPI_REQUIRE_TOOLCHAIN") == "1":
        pytest.fail(msg + " (STIPI_REQUIRE_TOOLCHAIN=1)")
    pytest.skip(msg)


def pytest_addoption(parser: pytest.Parser) -> None:
    """Opt-in hardware tests: they run only when a device is named on the command line."""
    parser.addoption(
        "--camera-device",
        default=None,
        help="V4L2 camera (e.g. /dev/video0) for the opt-in camera hardware test",
    )
    parser.addoption(
        "--probe-port",
        default=None,
        help="serial port of a real probe (e.g. /dev/ttyACM0) for the opt-in probe hardware test",
    )


# ---------------------------------------------------------------------------------------
# Scheduling under pytest-xdist (``./dev test`` runs ``-n 2 --dist loadgroup``)
# ---------------------------------------------------------------------------------------

#: Tests that run devices against the clock (accelerated daemons, emulated probes on ptys,
#: BLE over the virtual radio, simavr, paced cameras) and assert on timing or on "nothing
#: lost". They share one xdist worker, so that two of them never compete for the CPU; the
#: other worker runs everything else.
REALTIME_TESTS = (
    "tests/daemon/",
    "tests/reliability/",
    "tests/ble/",
    "tests/firmware/test_simavr_hil.py",
    "tests/firmware/test_probe_link_simavr.py",
    "tests/cameras/test_stream.py",
    "tests/cameras/test_video_file.py",
    "tests/cameras/test_simulator.py",
    "tests/transports/",
    "tests/emulator/",
    "tests/test_probe.py",
    "tests/test_demo.py",
    "tests/test_offline.py",
    "tests/commands/test_analyze.py",
    "tests/commands/test_report.py",
    "tests/report/",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        rel = Path(str(item.fspath)).resolve().relative_to(REPO_ROOT).as_posix()
        if rel.startswith(REALTIME_TESTS):
            item.add_marker(pytest.mark.xdist_group("realtime"))


# Hypothesis: example timing varies with machine load; correctness, not speed, is tested
# (speed goals live in benchmarks/).
settings.register_profile("stipi", deadline=None, print_blob=True)
settings.load_profile("stipi")
