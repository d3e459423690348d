"""Recorded sessions for the report tests (see :mod:`tests._report_sessions`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests._report_sessions import recorded_session


@pytest.fixture(scope="session")
def demo_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete grade-I session with a shortened recovery."""
    return recorded_session(tmp_path_factory, "grade1")


@pytest.fixture(scope="session")
def second_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete grade-II session with a shortened recovery (for comparisons)."""
    return recorded_session(tmp_path_factory, "grade2")
