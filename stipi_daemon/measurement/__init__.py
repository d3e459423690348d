"""Pure core of one measurement: the pit/release state machine (no I/O, no asyncio).

The acquisition shell feeds it timestamped events (force samples, camera frames, operator
buttons, link and camera watchdogs) and acts on the values it returns (prompts, warnings,
faults, the start of the analysis).
"""
