"""Session reports: figures, parameter tables and a self-contained HTML page.

``stipi-daemon report SESSION`` (and the daemon at the end of every run) writes
``<session>/report/report.html`` with the figures also as PNGs: force and S_k over time
with the phases, the fitted recovery with residuals, the VPR curves of Eq. (10) against the
reference grades with the severity window and threshold (the paper's Figs. 10-12), the
parameter table and representative frames with their thresholding. ``--compare`` overlays
several sessions and tabulates mean and spread per grade (the paper's Tables I-II).

One module per concept. Pure (no files, no drawing):

- :mod:`.inputs`: what the report reads from a session (:class:`~.inputs.ReportInput`);
- :mod:`.figures`: the arrays each figure plots (force, S_k, recovery fit, VPR curves,
  window search);
- :mod:`.parameter_table`: the parameter table, its rows as data, and the flags' meanings;
- :mod:`.panels`: the representative frames thresholded again with the session's p and ROI;
- :mod:`.compare`: several sessions side by side (``--compare``), overlays and statistics
  per grade (only complete sessions averaged);
- :mod:`.recovery_models`: the recovery models side by side (their table with weights and
  95 % intervals, its plain text, each model's curve on the recovery S_k);
- :mod:`.numbers`: the one rounding rule of every table, caption and legend;
- :mod:`.verdict`: the verdict block and each quantity's validity.

Shell: :mod:`.load` reads a session directory into a ``ReportInput``; :mod:`.render` draws
(matplotlib); :mod:`.html` builds the page; :mod:`.write` writes the files
(:func:`~.write.write_session_report`, :func:`~.write.write_compare_report`);
:mod:`.frames` stores and reads the representative frames. This package module imports
only :mod:`.frames`, so the daemon can store frames without loading matplotlib until the
report is drawn (which frames to keep is chosen in
:mod:`stipi_daemon.measurement.representative_frames`).
"""

from stipi_daemon.report.frames import (
    RepresentativeFrame,
    read_representative_frames,
    write_representative_frames,
)

__all__ = [
    "RepresentativeFrame",
    "read_representative_frames",
    "write_representative_frames",
]
