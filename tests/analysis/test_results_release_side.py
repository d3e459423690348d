"""Which side of T_0 the release lies on, as the daemon tells the recovery models."""

from __future__ import annotations

import numpy as np

from stipi_daemon.analysis.results import release_side


def test_t0_at_a_frame_is_after_the_release_else_either() -> None:
    t = np.arange(0.0, 2.0, 1 / 60.0)
    # measurement/release.py: a T_0 that is a frame's time is the first frame at or after
    # the release, which lies before it
    assert release_side(t, float(t[61])) == "before"
    # a T_0 that is the force drop itself (interpolated between samples) is no frame's time
    assert release_side(t, float(t[61]) + 0.004) == "either"
