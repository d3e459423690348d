"""The lazy registry: every registered name resolves, unknown names fail clearly."""

from __future__ import annotations

import inspect

import pytest

from stipi_daemon import registry
from stipi_daemon.registry import ADAPTERS, SIMULATED, RegistryError, load, target


@pytest.mark.parametrize("name", sorted(SIMULATED | ADAPTERS))
def test_every_entry_resolves(name: str) -> None:
    module_name, _, attribute = target(name).partition(":")
    obj = load(name)
    assert obj.__name__ == attribute
    assert inspect.getmodule(obj) is not None
    assert obj.__module__ == module_name


def test_simulated_entries_live_in_sim_and_adapters_do_not() -> None:
    assert all(t.startswith("stipi_daemon.sim.") for t in SIMULATED.values())
    assert not any(t.startswith("stipi_daemon.sim.") for t in ADAPTERS.values())
    assert not set(SIMULATED) & set(ADAPTERS)


def test_unknown_name_is_a_clear_error() -> None:
    with pytest.raises(RegistryError, match=r"'camera:nope'.*registered: .*camera:simulator"):
        load("camera:nope")
    with pytest.raises(LookupError):
        target("transport:carrier-pigeon")


def test_broken_target_names_module_and_attribute(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(registry.SIMULATED, "test:missing_module", "stipi_daemon.sim.nope:X")
    monkeypatch.setitem(registry.SIMULATED, "test:missing_attr", "stipi_daemon.sim.camera:Nope")
    with pytest.raises(RegistryError, match=r"cannot import stipi_daemon\.sim\.nope"):
        load("test:missing_module")
    with pytest.raises(RegistryError, match=r"stipi_daemon\.sim\.camera has no attribute 'Nope'"):
        load("test:missing_attr")
