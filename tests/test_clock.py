from __future__ import annotations

import pytest

from stipi_daemon.clock import ScaledClock, SessionClock


class _Wall:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_scaled_clock_runs_at_speed() -> None:
    wall = _Wall()
    clock = ScaledClock(4.0, wall)
    assert isinstance(clock, SessionClock)
    assert clock.now() == 0.0
    wall.t += 2.5
    assert clock.now() == pytest.approx(10.0)
    assert clock.wall_seconds(10.0) == pytest.approx(2.5)


def test_bad_speed() -> None:
    with pytest.raises(ValueError, match="speed"):
        ScaledClock(0.0)


async def test_sleep_until_waits_scaled_time() -> None:
    clock = ScaledClock(50.0)
    await clock.sleep_until(1.0)  # 1 session second = 20 ms of wall time
    assert clock.now() >= 1.0
    before = clock.now()
    await clock.sleep_until(0.0)  # already past: returns at once
    assert clock.now() - before < 0.5
