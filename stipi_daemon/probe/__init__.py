"""The probe: its link over any transport (serial, BLE via bleak) as a stream of events.

:mod:`.link` (:class:`~stipi_daemon.probe.link.ProbeLink`: decoding, sample accounting,
clock mapping, commands, heartbeat), :mod:`.transports` (one module per link, chosen by the
config's ``kind``), :mod:`.nus` (the Nordic UART Service UUIDs and advertising data).
Simulated probes live in :mod:`stipi_daemon.sim` and are reached only through the
transport registry.
"""
