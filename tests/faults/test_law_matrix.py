"""Issue 37's acceptance: zero silent misses over the fault matrix's literature-law group.

Each case runs the real daemon (tests/faults/law_matrix.py) on a recovery from a law of the
literature (power-law, poroelastic, stretched exponential, a standard linear solid that
springs back inside the release frame; Kelvin-Voigt as the control) or with a camera or
sensor fault rendered by the test (LED flicker, pixel noise, vignetting, saturation, a load
cell at its rail, a 47 s frame gap, a run stopped 16 s into the recovery), and holds every
primary quantity (D_p, F_r, T_r, E, eta, class) to the law's truth: within tolerance, or
flagged / invalid. docs/reliability.md ("Literature laws and camera faults") lists the
cases and what they gave before issue 37's fixes.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from .law_matrix import LawCase, law_cases, run_law_case
from .matrix import row

#: Session clock speed: 0, as fast as the daemon goes (every device is simulated in the
#: process, so the clock waits for the daemon and the results do not depend on it).
SPEED = 0.0

#: The silent misses issue 37 has not fixed yet, run -> quantities (docs/reliability.md,
#: "Literature laws and camera faults", the table after the fixes). Not a tolerance: each
#: run must miss exactly these, so a fix (or a new miss) fails here until this ledger and
#: the document say so. D_p, E and eta: the pit recovers within the frame period after the
#: release and nothing yet tells S_0 from the hold's depth; vignetting: the rim's dark
#: pixels move T_r and no frame statistic reaches the live analysis yet; the pinned load
#: cell: its rail lies below the ADC's, which is all the rail rule knows.
OPEN_MISSES: dict[str, set[str]] = {
    "law-findley-n0.3": {"depth_mm", "elasticity_kpa"},
    "law-findley-n0.2": {"depth_mm", "elasticity_kpa"},
    "law-terzaghi-tau25s": {"depth_mm", "elasticity_kpa", "viscosity_n_s_per_mm2"},
    "law-terzaghi-tau12s": {"depth_mm", "elasticity_kpa", "viscosity_n_s_per_mm2"},
    "law-kww-tau6s-b0.5": {"depth_mm", "elasticity_kpa"},
    "law-kww-tau3s-b0.6": {"depth_mm", "elasticity_kpa"},
    "law-sls-springback-0.25": {"depth_mm", "elasticity_kpa", "viscosity_n_s_per_mm2"},
    "cam-noise-20-levels": {"depth_mm", "elasticity_kpa", "viscosity_n_s_per_mm2"},
    "cam-vignetting-strong": {"recovery_time_s"},
    "sensor-load-cell-pinned": {"elasticity_kpa", "viscosity_n_s_per_mm2"},
}


@pytest.mark.timeout(900)
@pytest.mark.xdist_group("realtime")
@pytest.mark.parametrize("case", law_cases(), ids=lambda c: c.name)
async def test_no_silent_miss_on_literature_laws(case: LawCase, tmp_path: Path) -> None:
    result = await run_law_case(case, tmp_path, SPEED)
    assert result.error is None, result.error
    # The fault happened as the case says (the run measures what it claims).
    rec = result.recorded
    if case.frame_gap_rel_s is not None:  # recorded as lost, or the run's camera fault
        a, b = case.frame_gap_rel_s
        lost = rec["frames_lost"] >= round((b - a) * 60.0) - 1
        assert lost or result.phase == "camera_stalled", (rec, result.phase)
    if case.stall_rel_s is not None:  # frames handed over past max_lag_s / 2 are dropped
        assert rec["frames_lost"] > 0, rec
    if case.stop_rel_s is not None:
        assert result.phase.startswith("aborted/analyze"), result.phase
    assert set(result.silent_misses) == OPEN_MISSES.get(case.name, set()), row(result)
