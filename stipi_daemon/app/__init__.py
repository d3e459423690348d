"""The application: configuration, the acquisition daemon, the operator console, offline I/O.

This layer wires the pure core (:mod:`stipi_daemon.analysis`, :mod:`stipi_daemon.protocol`,
:mod:`stipi_daemon.measurement`) to the adapters (:mod:`stipi_daemon.probe`,
:mod:`stipi_daemon.cameras`, :mod:`stipi_daemon.storage`) and is what the commands call.
"""
