"""Shared test configuration.

Every test runs under :func:`no_task_left_running`: a test that leaves an asyncio task
running at its end (its own fixtures' teardown included) fails, the way ophyd-async's
suite does; pytest-asyncio would otherwise cancel such tasks silently when it closes the
test's event loop, hiding a missing ``await``/``close()``.

Tests that need an external toolchain (g++, avr-gcc, simavr) call :func:`require_tool`;
it skips when the tool is missing, unless ``STIPI_REQUIRE_TOOLCHAIN=1`` (set by ``.ci/run``)
turns the skip into a failure so that CI never passes by skipping what matters.
"""

from __future__ import annotations

import asyncio
import os
import shutil
import signal
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from hypothesis import settings

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED_REFERENCE = REPO_ROOT.parent / "shared" / "reference"


def pytest_configure(config: pytest.Config) -> None:
    """Let the daemons the tests start take Ctrl-C. A suite started in the background by a
    non-interactive shell (``./dev test &``) inherits SIGINT ignored, and every process it
    starts would too: the tests that interrupt a daemon or a mock probe then fail. With a
    handler here, a started program gets SIGINT's default again (exec resets caught
    signals, not ignored ones)."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


#: Wall-clock limit for one cold build (and run) of firmware or host test code. A cold
#: ``make host-test`` took 180 s on 2 busy cores (the sanitizer build dominates); the limit
#: leaves more than 3x that, because a limit only has to catch a hang, not a slow machine.
COLD_BUILD_TIMEOUT_S = 600


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
        # A test that builds the firmware (its module's fixtures do, once) may wait for a
        # cold build on busy cores: the hang guard is the build's, not the default 120 s.
        if item.get_closest_marker("toolchain") and not item.get_closest_marker("timeout"):
            item.add_marker(pytest.mark.timeout(COLD_BUILD_TIMEOUT_S + 60))


# Hypothesis: example timing varies with machine load; correctness, not speed, is tested
# (speed goals live in benchmarks/).
settings.register_profile("stipi", deadline=None, print_blob=True)
settings.load_profile("stipi")


# ---------------------------------------------------------------------------------------
# No asyncio task may outlive its test
# ---------------------------------------------------------------------------------------


@pytest.fixture(autouse=True)
async def no_task_left_running(request: pytest.FixtureRequest) -> AsyncIterator[None]:
    """Fail a test that leaves asyncio tasks running in its event loop.

    Autouse, so set up before and torn down after the test's other function-scoped
    fixtures: the check sees what is still running once the test *and* its fixtures have
    cleaned up. Leftover tasks are cancelled (and awaited, up to 5 s) either way; the test
    fails only if it had not failed already, so that a leak does not hide the real failure.
    """
    loop = asyncio.get_running_loop()
    before = asyncio.all_tasks(loop)
    failed_before = request.session.testsfailed
    yield
    this = asyncio.current_task()
    left = sorted(
        (t for t in asyncio.all_tasks(loop) if t is not this and t not in before and not t.done()),
        key=repr,
    )
    running = [repr(task) for task in left]
    for task in left:
        task.cancel()
    if left:
        await asyncio.wait(left, timeout=5.0)
    if running and request.session.testsfailed == failed_before:
        pytest.fail(
            f"{len(running)} asyncio task(s) still running at the end of the test "
            "(cancel and await them in the test or its fixture):\n"
            + "\n".join(f"  {task}" for task in running),
            pytrace=False,
        )
