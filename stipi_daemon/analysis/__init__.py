"""Pure analysis core: the paper's Eqs. 1-10 and the severity classification.

Nothing in this package does I/O except the explicit load/save functions of
:mod:`~stipi_daemon.analysis.calibration` and :mod:`~stipi_daemon.analysis.severity`.
"""
