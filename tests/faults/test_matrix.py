"""The fault-injection matrix's fast subset: zero silent misses (issue 14).

Each case runs the real daemon on simulated devices (tests/faults/matrix.py) with one
timing or imaging fault and holds every primary quantity of its summary (D_p, F_r, T_r,
E, eta, severity class) to the scene's truth: within tolerance, or flagged / invalid.
The long form is ``python -m tests.faults.matrix --long`` (docs/reliability.md).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from .matrix import Case, fast_cases, row, run_case

#: Session clock speed of the subset: the simulated camera renders a scene with frame
#: effects at ~1100 fps on one core; 6x asks 360 fps of it (matrix.camera_kept_up).
SPEED = 6.0


@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("case", fast_cases(), ids=lambda c: c.name)
async def test_no_silent_miss(case: Case, tmp_path: Path) -> None:
    result = await run_case(case, tmp_path, SPEED)
    assert result.error is None, result.error
    # The fault happened as the case says (the run measures what it claims).
    rec = result.recorded
    if case.frame_gap_rel_s is not None:
        a, b = case.frame_gap_rel_s
        assert rec["frames_lost"] >= round((b - a) * 60.0) - 1, rec
    if case.corrupt_rel_s:
        assert rec["frames_lost"] >= len(case.corrupt_rel_s), rec
    if case.force_dropout_rel_s is not None:
        assert rec["samples_lost"] > 0, rec
    assert not result.silent_misses, row(result)
