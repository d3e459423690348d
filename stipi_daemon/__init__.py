"""stipi-daemon: acquisition and analysis for the STIP-I tactile imaging probe.

One subpackage per concept; the layers read from the tree (docs/architecture.md, checked
by the import contracts in ``pyproject.toml``):

* pure core, no I/O: :mod:`.analysis` (the paper's equations, calibration, severity),
  :mod:`.protocol` (wire codec, probe-to-host clock mapping), :mod:`.measurement` (the
  state machine, live pipeline, merger, offline replay);
* adapters: :mod:`.probe` (the probe link and its transports), :mod:`.cameras`,
  :mod:`.storage` (session directories);
* :mod:`.sim`: the scene simulator and the emulated probe, which runtime code reaches only
  by name through :mod:`.registry`;
* the application: :mod:`.app` (daemon, offline analysis, config, console),
  :mod:`.report`, :mod:`.commands` and :mod:`.cli`;
* shared by all: :mod:`.clock` (the session clock) and :mod:`.errors`.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("stipi-daemon")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
