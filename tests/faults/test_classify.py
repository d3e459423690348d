"""The matrix's own logic, without the daemon: case timing, truth ranges, classification
of a summary with and without issue 14's validity schema."""

from __future__ import annotations

from typing import Any

import pytest

from stipi_daemon.sim.scene import parse_scene

from .matrix import EARLY_14S_HOLD_LEAD_S, TOLERANCES, Case, classify, fast_cases, long_cases, truth


def _truth(case: Case) -> dict[str, dict[str, Any]]:
    return truth(case, parse_scene(case.scene_doc(), case.name))


def _summary(values: dict[str, Any], flags: list[str] | None = None) -> dict[str, Any]:
    return {
        "status": "complete",
        "results": {
            "pitting": {
                "depth_mm": values["depth_mm"],
                "rebound_force_n": values["rebound_force_n"],
                "recovery_time_s": values["recovery_time_s"],
                "flags": flags or [],
            },
            "paper_estimator": {
                "elasticity_kpa": values["elasticity_kpa"],
                "viscosity_n_s_per_mm2": values["viscosity_n_s_per_mm2"],
            },
            "severity": {"paper_estimator": {"severity": values["severity"], "flags": []}},
            "flags": ["outside_reference_range"],
        },
    }


def test_release_lead_sets_the_hold() -> None:
    early = Case("x", pre_s=4.5, release_lead_s=EARLY_14S_HOLD_LEAD_S)
    assert early.hold_s == pytest.approx(14.0) and early.t0_s == pytest.approx(19.5)
    assert Case("x", release_lead_s=0.0).hold_s == pytest.approx(14.90625)


def test_effects_are_placed_relative_to_the_release() -> None:
    case = Case("x", pre_s=4.5, release_lead_s=EARLY_14S_HOLD_LEAD_S, frame_gap_rel_s=(-0.7, 0.5))
    (gap,) = case.effects()
    assert gap["name"] == "frame_gap"
    assert (gap["t_start_s"], gap["t_end_s"]) == pytest.approx((18.8, 20.0))
    scene = parse_scene(case.scene_doc(), "x")
    assert scene.force_profile.release_s == pytest.approx(19.5)
    assert (scene.camera.width, scene.camera.height, scene.camera.fps) == (320, 240, 60.0)


def test_grids_have_unique_names() -> None:
    for grid in (fast_cases(), long_cases()):
        names = [c.name for c in grid]
        assert len(names) == len(set(names))
    assert len(long_cases()) == 210


def test_truth_ranges_contain_the_value_and_one_frame_of_s0() -> None:
    t = _truth(Case("x", "I"))
    for q in TOLERANCES:
        if q != "severity":
            assert t[q]["low"] < t[q]["value"] < t[q]["high"], q
    # grade I recovers fast: one frame after T_0 lowers D_p by more than the 5 % alone
    assert t["depth_mm"]["low"] < 0.9 * t["depth_mm"]["value"]
    assert t["severity"]["value"] == "mild"
    assert _truth(Case("x", "IV", tau_s=1e4))["severity"]["value"] == "severe"


def test_old_summary_valid_inside_is_ok_outside_is_a_silent_miss() -> None:
    t = _truth(Case("x", "II", window_s=15.0))
    exact = {q: v["value"] for q, v in t.items()}
    out = classify(_summary(exact), t)
    assert {v["outcome"] for v in out.values()} == {"ok"}
    wrong = exact | {"rebound_force_n": 2 * exact["rebound_force_n"], "severity": "severe"}
    out = classify(_summary(wrong), t)
    assert out["rebound_force_n"]["outcome"] == "SILENT MISS"
    assert out["severity"]["outcome"] == "SILENT MISS"
    assert out["depth_mm"]["outcome"] == "ok"  # the results' overall flags are not used
    flagged = classify(_summary(wrong, ["not_settled"]), t)
    assert flagged["rebound_force_n"]["outcome"] == "flagged"
    assert classify({"status": "aborted", "results": None}, t)["depth_mm"]["outcome"] == "invalid"


def test_validity_schema_decides_over_flags() -> None:
    t = _truth(Case("x", "I"))
    wrong = {q: v["value"] for q, v in t.items()} | {"depth_mm": 0.5 * t["depth_mm"]["value"]}
    summary = _summary(wrong, ["not_settled"])
    summary["validity"] = {q: {"status": "valid", "flags": [], "reason": None} for q in TOLERANCES}
    summary["validity"]["rebound_force_n"] = {"status": "invalid", "flags": [], "reason": "gap"}
    out = classify(summary, t)
    assert out["depth_mm"]["outcome"] == "SILENT MISS"
    assert out["rebound_force_n"]["outcome"] == "invalid"
    assert out["recovery_time_s"]["outcome"] == "ok"
