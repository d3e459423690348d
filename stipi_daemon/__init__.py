"""stipi-daemon: acquisition and analysis for the STIP-I tactile imaging probe.

The package is split into a pure core (``analysis``, ``protocol``, ``sim``) that does no
I/O, and thin adapters (transports, cameras, storage) around it.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("stipi-daemon")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
