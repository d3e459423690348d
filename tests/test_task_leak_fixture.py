"""The suite's ``no_task_left_running`` fixture fails a test that leaves a task running."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO_ROOT

_TESTS = """
import asyncio

import pytest


async def test_leaves_a_task() -> None:
    asyncio.get_running_loop().create_task(asyncio.sleep(100), name="leaked-sleeper")


async def test_cancels_and_awaits() -> None:
    task = asyncio.get_running_loop().create_task(asyncio.sleep(100))
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task


@pytest.fixture
async def server():
    task = asyncio.get_running_loop().create_task(asyncio.sleep(100))
    yield
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


async def test_fixture_cleans_up(server: None) -> None:
    pass


def test_sync() -> None:
    pass


async def test_fails_and_leaks() -> None:
    asyncio.get_running_loop().create_task(asyncio.sleep(100))
    raise AssertionError("the real failure")
"""


def test_leftover_task_fails_the_test_and_nothing_else(tmp_path: Path) -> None:
    (tmp_path / "conftest.py").write_text(
        "from tests.conftest import no_task_left_running  # noqa: F401\n"
    )
    (tmp_path / "test_leaks.py").write_text(_TESTS)
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-q",
            "-p",
            "no:cacheprovider",
            "-o",
            "asyncio_mode=auto",
            "-o",
            "asyncio_default_fixture_loop_scope=function",
            "test_leaks.py",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    out = proc.stdout
    assert proc.returncode == 1, out + proc.stderr
    # The leak is an error (at teardown) of exactly the leaking test; a test that failed
    # anyway reports its own failure only.
    assert "1 failed, 4 passed, 1 error" in out, out
    assert "ERROR test_leaks.py::test_leaves_a_task" in out, out
    assert "leaked-sleeper" in out, out
    assert "FAILED test_leaks.py::test_fails_and_leaks - AssertionError: the real failure" in out
