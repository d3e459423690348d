"""evolve: the state machine's fast replace gives what ``dataclasses.replace`` gives."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.measurement.evolve import evolve
from stipi_daemon.measurement.settling_tracker import SettlingTracker
from stipi_daemon.measurement.state_machine import MachineState, Phase, initial_state

_times = st.one_of(st.none(), st.floats(allow_nan=False, allow_infinity=False, width=64))
_changes = st.fixed_dictionaries(
    {},
    optional={
        "phase": st.sampled_from(list(Phase)),
        "now_s": st.floats(allow_nan=False, width=64),
        "t_release_s": _times,
        "oob_since_s": _times,
        "n_excursions": st.integers(0, 10**6),
        "contact": st.booleans(),
        "flags": st.frozensets(st.sampled_from(["a", "b", "not_settled"])),
        "last_prompt": st.text(max_size=20),
        "end_reason": st.one_of(st.none(), st.text(max_size=20)),
    },
)


@given(first=_changes, second=_changes)
def test_evolve_equals_replace_field_by_field(
    first: dict[str, object], second: dict[str, object]
) -> None:
    state = initial_state(1.5)
    a = evolve(evolve(state, **first), **second)
    b = dataclasses.replace(dataclasses.replace(state, **first), **second)  # type: ignore[arg-type]
    assert type(a) is MachineState and a == b
    for f in dataclasses.fields(MachineState):
        assert getattr(a, f.name) is getattr(b, f.name) or getattr(a, f.name) == getattr(b, f.name)
    assert evolve(state) == state and evolve(state) is not state
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.now_s = 3.0  # type: ignore[misc]  # still frozen


def test_the_settling_tracker_evolves_as_it_was_replaced() -> None:
    tracker = SettlingTracker.first(0.0, 100.0, 0.95)
    for k in range(1, 50):
        tracker = tracker.add(k / 60, 100.0 + 10 * k)
    assert dataclasses.replace(tracker) == tracker
    assert evolve(tracker, last_s=9.0) == dataclasses.replace(tracker, last_s=9.0)


def test_unknown_fields_and_records_it_cannot_copy_are_refused() -> None:
    with pytest.raises(TypeError, match="no field nows"):
        evolve(initial_state(0.0), nows=1.0)

    @dataclass(frozen=True, slots=True)
    class Slotted:
        x: int

    @dataclass(frozen=True)
    class Checked:
        x: int

        def __post_init__(self) -> None:
            if self.x < 0:
                raise ValueError("x < 0")

    with pytest.raises(TypeError, match="without slots"):
        evolve(Slotted(1), x=2)
    with pytest.raises(TypeError, match="__post_init__"):
        evolve(Checked(1), x=-1)
