"""Offline replay: same inputs give the live run's numbers; partial recoveries; comparisons."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.results import AnalysisSettings
from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.analysis.summary_diff import diff_results
from stipi_daemon.analysis.truth_comparison import compare_ground_truth
from stipi_daemon.app.offline_io import SessionData, read_session
from stipi_daemon.errors import AnalysisError, CalibrationError
from stipi_daemon.measurement.replay import (
    Recording,
    ReplaySetup,
    _events,
    calibration_from_mapping,
    replay,
)
from stipi_daemon.measurement.state_machine import (
    Arm,
    ForceSample,
    FrameSample,
    LinkLost,
    LinkRestored,
    MeasurementConfig,
    Phase,
)
from stipi_daemon.storage import SessionState
from tests._offline import record_session


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> SessionData:
    return read_session(record_session(tmp_path_factory.mktemp("offline")))


def _setup(data: SessionData, **analysis: object) -> ReplaySetup:
    cfg = data.manifest["config"]
    return ReplaySetup(
        MeasurementConfig.model_validate(cfg["measurement"]),
        AnalysisSettings.model_validate({**cfg["analysis"], **analysis}),
        calibration_from_mapping(data.manifest["calibration"], "manifest"),
        load_reference(),
    )


def _json(value: object) -> object:
    return json.loads(json.dumps(value, allow_nan=False))


def test_replay_reproduces_the_live_summary_exactly(session: SessionData) -> None:
    assert session.status is SessionState.COMPLETE and session.summary is not None
    outcome = replay(session.recording(), _setup(session))
    mine = _json(outcome.summary())
    assert isinstance(mine, dict)
    stored = {k: session.summary[k] for k in mine}
    assert diff_results(stored, mine, "summary") == []
    assert outcome.phase == Phase.DONE and not outcome.partial
    # The live run stops at the event that ends the recovery; rows that had already
    # arrived after it are stored but not fed, live and on replay alike.
    assert outcome.frames_fed <= session.frame_times_s.size
    assert session.frame_times_s.size - outcome.frames_fed < 30
    assert outcome.force_samples_fed <= session.force_times_s.size
    # The live parameters were shown during the recovery, as live.
    assert len(outcome.live) >= 5


def test_changed_settings_change_the_results(session: SessionData) -> None:
    outcome = replay(session.recording(), _setup(session, applied_force_n=20.0))
    assert outcome.result is not None and session.summary is not None
    stored_e = session.summary["results"]["paper_estimator"]["elasticity_kpa"]
    e = outcome.result.paper_model.elasticity_kpa if outcome.result.paper_model else None
    assert e is not None
    assert e == pytest.approx(stored_e * 20.0 / session.summary["results"]["applied_force_n"])


def test_recording_cut_during_recovery_is_analysed_as_partial(session: SessionData) -> None:
    assert session.summary is not None
    t0 = session.summary["measurement"]["t0_refined_s"]
    keep = session.frame_times_s <= t0 + 1.5  # T_r of grade I is 2.2 s: not settled yet
    rec = Recording(
        session.frame_times_s[keep],
        session.s_k_px[keep],
        session.force_times_s[session.force_times_s <= t0 + 1.5],
        session.force_n[session.force_times_s <= t0 + 1.5],
        session.t_arm_s,
    )
    closed = replay(rec, _setup(session))
    assert closed.result is None and closed.phase == Phase.ABORTED
    outcome = replay(rec, _setup(session), partial_recovery=True)
    assert outcome.partial and outcome.result is not None
    assert outcome.summary()["status"] == "partial"
    assert outcome.t0_s == pytest.approx(t0)
    # D_p depends only on S_0 (at T_0): the same as the full recording's.
    assert outcome.result.pitting.depth_mm == pytest.approx(
        session.summary["results"]["pitting"]["depth_mm"], rel=1e-12
    )
    assert Flag.NOT_SETTLED in outcome.result.flags
    assert any("into the recovery" in n for n in outcome.notes)
    assert any("not settled" in n for n in outcome.notes)


def test_recording_cut_before_the_release_has_no_results(session: SessionData) -> None:
    # Cut 5 s into the scene: during the pitting.
    cut = session.frame_times_s[0] + 5.0
    rec = Recording(
        session.frame_times_s[session.frame_times_s <= cut],
        session.s_k_px[session.frame_times_s <= cut],
        session.force_times_s[session.force_times_s <= cut],
        session.force_n[session.force_times_s <= cut],
    )
    outcome = replay(rec, _setup(session), partial_recovery=True)
    assert outcome.result is None and not outcome.partial
    assert outcome.analysis_error is not None and "pitting" in outcome.analysis_error
    assert any("before any recovery" in n for n in outcome.notes)


def test_events_are_merged_force_first_and_armed_once() -> None:
    rec = Recording(
        np.array([0.0, 0.5, 1.0]),
        np.array([1.0, 2.0, 3.0]),
        np.array([-0.1, 0.5, 0.7, 1.0]),
        np.array([1.0, 2.0, np.nan, 3.0]),
        t_arm_s=0.2,
    )
    feed = _events(rec)
    assert feed.skipped_force == 1
    assert feed.events == [
        ForceSample(-0.1, 1.0),
        FrameSample(0.0, 1.0),
        Arm(0.2),
        ForceSample(0.5, 2.0),
        FrameSample(0.5, 2.0),
        ForceSample(1.0, 3.0),
        FrameSample(1.0, 3.0),
    ]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"s_k_px": np.array([1.0])}, "2 frame times but 1 S_k values"),
        ({"frame_times_s": np.array([0.0, np.nan])}, "frame 1 has a non-finite time"),
        ({"frame_times_s": np.array([]), "s_k_px": np.array([])}, "holds no frame"),
        ({"force_n": np.array([1.0, 2.0])}, "1 force sample times but 2 forces"),
    ],
)
def test_recording_refuses_bad_input(kwargs: dict[str, np.ndarray], message: str) -> None:
    base: dict[str, np.ndarray] = {
        "frame_times_s": np.array([0.0, 1.0]),
        "s_k_px": np.array([1.0, 2.0]),
        "force_times_s": np.array([0.0]),
        "force_n": np.array([1.0]),
    }
    with pytest.raises(AnalysisError, match=message):
        Recording(**{**base, **kwargs})


def test_calibration_from_mapping() -> None:
    cal = calibration_from_mapping(
        {
            "alpha1_mm_per_px2": 1e-7,
            "alpha2_mm_per_px": 2e-3,
            "c1_px": 10.0,
            "c2_px_per_n": 100.0,
            "threshold_p": 90,
            "s0_valid_range_px": [0.0, 100.0],
            "source": "ignored",
        },
        "m.json",
    )
    assert cal == Calibration(1e-7, 2e-3, 10.0, 100.0, threshold_p=90, s0_valid_range_px=(0, 100))
    with pytest.raises(CalibrationError, match=r"^m.json: calibration lacks c1_px$"):
        calibration_from_mapping(
            {"alpha1_mm_per_px2": 0, "alpha2_mm_per_px": 1, "c2_px_per_n": 1}, "m.json"
        )
    with pytest.raises(CalibrationError, match=r"^m.json: field 'c2_px_per_n': must be > 0"):
        calibration_from_mapping(
            {"alpha1_mm_per_px2": 0, "alpha2_mm_per_px": 1, "c1_px": 0, "c2_px_per_n": -1}, "m.json"
        )


def test_diff_results_names_every_difference() -> None:
    a = {"x": 1.0, "y": [1, 2], "z": {"k": None}, "only_a": 1}
    b = {"x": 1.0000000001, "y": [1], "z": {"k": 0.0}, "only_b": 2}
    assert diff_results(a, b) == [
        "results.only_a: only in the stored results",
        "results.only_b: only in the recomputed results",
        "results.x: stored 1.0, recomputed 1.0000000001",
        "results.y: 2 items stored, 1 recomputed",
        "results.z.k: stored None, recomputed 0.0",
    ]
    assert diff_results(a, a) == []


def test_compare_ground_truth_errors_and_tolerances() -> None:
    summary = {
        "results": {
            "pitting": {"depth_mm": 2.019, "rebound_force_n": 5.0, "recovery_time_s": None},
            "fitted_recovery": {"tau_s": 1.0, "model": None},
            "applied_force_n": 16.0,
            "paper_estimator": {"elasticity_kpa": 300.0, "viscosity_n_s_per_mm2": 1.0},
        }
    }
    truth = {
        "depth_mm": 2.0,
        "rebound_force_n": 5.0,
        "recovery_time_s": 2.0,
        "time_constant_s": 1.03,
        "applied_force_n": 0.0,
        "elasticity_kpa": 300.0,
        "viscosity_n_s_per_mm2": 1.0,
    }
    rows = {r.name: r for r in compare_ground_truth(summary, truth)}
    assert rows["depth_mm"].error_percent == pytest.approx(0.95)
    assert rows["depth_mm"].within_tolerance is True
    assert rows["time_constant_s"].within_tolerance is False  # -2.9 % > 2 %
    assert rows["recovery_time_s"].error_percent is None  # no measured T_r
    assert rows["applied_force_n"].error_percent is None  # zero truth
    assert rows["viscosity_from_time_constant_n_s_per_mm2"].truth is None
    assert rows["viscosity_n_s_per_mm2"].within_tolerance is None  # no tolerance
    assert all(r.measured is None for r in compare_ground_truth({"results": None}, truth))


def test_session_fixture_is_real(session: SessionData, tmp_path: Path) -> None:
    """The fixture comes from the live daemon: frames at 60 fps, load cell at 100 Hz.

    Force times are the probe's clock mapped onto the session clock (clock sync), so their
    spacing is 10 ms up to the fitted drift.
    """
    assert np.median(np.diff(session.frame_times_s)) == pytest.approx(1 / 60, rel=1e-6)
    assert np.median(np.diff(session.force_times_s)) == pytest.approx(0.01, rel=1e-3)
    assert session.t_arm_s is not None
    assert 0.0 <= session.t_arm_s < session.frame_times_s[0]  # armed before the scene starts


def test_watchdog_events_are_replayed(session: SessionData) -> None:
    rec = session.recording()
    lost = dataclasses.replace(rec, link_events=(LinkLost(0.5),))
    outcome = replay(lost, _setup(session))
    assert outcome.phase == Phase.LINK_LOST and outcome.result is None
    back = dataclasses.replace(rec, link_events=(LinkLost(0.5), LinkRestored(1.0)))
    assert replay(back, _setup(session)).phase == Phase.DONE
    with pytest.raises(AnalysisError, match="not a watchdog event"):
        dataclasses.replace(rec, link_events=(Arm(0.0),))
