"""Pure core of one measurement (no I/O, no clock, no asyncio).

The acquisition shell feeds it timestamped events (force samples, camera frames, operator
buttons, link and camera watchdogs) and acts on the values it returns (prompts, warnings,
faults, the start of the analysis). Modules:

* :mod:`~stipi_daemon.measurement.state_machine`: the pit/release state machine of Section
  IV.B, a transition table and a table of time-driven rules, with its vocabulary beside it:
  :mod:`~stipi_daemon.measurement.settings` (``MeasurementConfig``, the thresholds and
  durations), :mod:`~stipi_daemon.measurement.events` (the inputs) and
  :mod:`~stipi_daemon.measurement.outputs` (phases, flags, advisories, prompts, faults,
  the start of the analysis).
* :mod:`~stipi_daemon.measurement.settling_tracker`: the online settling test that lets a
  recovery end before its 105 s window (rules shared with
  :mod:`~stipi_daemon.analysis.settling_rules`).
* :mod:`~stipi_daemon.measurement.pipeline`: one recording's series, the machine, live
  parameters and the whole-measurement analysis, events in and results out.
* :mod:`~stipi_daemon.measurement.merge`: merges the force and frame streams into one
  time-ordered event stream.
* :mod:`~stipi_daemon.measurement.replay`: offline replay of a stored session through the
  same pipeline.
"""
