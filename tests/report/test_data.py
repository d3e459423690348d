"""Figure data: every plotted array equals the session's rows or the analysis' own numbers."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.severity import find_severity_window, load_reference
from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.compare import (
    COMPARE_PARAMETERS,
    compare_table,
    overlay_force,
    overlay_s_k,
)
from stipi_daemon.report.figures import (
    fit_figure,
    force_figure,
    phase_spans,
    s_k_figure,
    vpr_figure,
    window_search_figure,
)
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.panels import frame_panels
from stipi_daemon.report.parameter_table import PARAMETER_ROWS, flag_descriptions, parameter_table
from stipi_daemon.storage import SessionReader, Transition


@pytest.fixture(scope="module")
def inp(demo_session: Path) -> ReportInput:
    return load_report_input(demo_session)


def test_time_series_are_the_sessions_rows(demo_session: Path, inp: ReportInput) -> None:
    with SessionReader(demo_session) as reader:
        frames = reader.frames()
        force = reader.force_samples()
        transitions = reader.transitions()
    sk = s_k_figure(inp)
    np.testing.assert_array_equal(sk.t_s, frames["t_capture_host_s"])
    np.testing.assert_array_equal(sk.s_k_px, frames["s_k"])
    f = force_figure(inp)
    np.testing.assert_array_equal(f.t_s, force["t_host_s"])
    np.testing.assert_array_equal(f.force_n, force["force_n"])
    # Phases: one span per transition into a phase that lasted, in order, contiguous.
    starts = {t.t_host_s: t.new_state for t in transitions}
    assert all(starts[p.start_s] == p.phase for p in sk.phases)
    assert [p.phase for p in sk.phases][:4] == ["armed", "pitting", "release", "recovery"]
    for a, b in zip(sk.phases, sk.phases[1:], strict=False):
        assert a.end_s == b.start_s


def test_markers_are_the_summarys(inp: ReportInput) -> None:
    assert inp.summary is not None
    pit = inp.summary["results"]["pitting"]
    sk = s_k_figure(inp)
    assert (sk.t0_s, sk.ts_s, sk.s0_px, sk.s_max_px) == (
        pit["t0_s"],
        pit["ts_s"],
        pit["s0_px"],
        pit["s_max_px"],
    )
    assert sk.settle_level_px == pytest.approx(0.98 * pit["s_max_px"], rel=1e-15)
    assert sk.ts_s is not None and sk.t0_s is not None
    assert sk.ts_s - sk.t0_s == pytest.approx(pit["recovery_time_s"], abs=1e-9)
    f = force_figure(inp)
    m = inp.summary["measurement"]
    assert f.applied_force_n == inp.summary["results"]["applied_force_n"]
    assert f.hold_s == (m["t_pit_start_s"], min(m["t_pit_end_s"], pit["t0_s"]))
    assert (f.target_n, f.tolerance_n) == (16.0, 1.5)
    # F_a is the mean force over the hold: recompute it from the plotted samples.
    hold = (f.t_s >= f.hold_s[0]) & (f.t_s <= f.hold_s[1])
    assert float(np.nanmean(f.force_n[hold])) == pytest.approx(f.applied_force_n, rel=1e-12)


def test_fit_figure_is_the_fit(inp: ReportInput) -> None:
    assert inp.summary is not None
    fr = inp.summary["results"]["fitted_recovery"]
    fit = fit_figure(inp)
    assert fit is not None
    assert fit.t_since_t0_s.size == fr["n_points"]
    np.testing.assert_array_equal(fit.residual_px, fit.s_k_px - fit.model_px)
    # The residuals' RMS is the RMSE the fit reported over the same points.
    rms = math.sqrt(float(np.mean(fit.residual_px**2)))
    assert rms == pytest.approx(fr["rmse_px"], rel=1e-6)
    assert fit.model_px[0] == pytest.approx(
        fr["offset_px"] - fr["amplitude_px"] * math.exp(-fit.t_since_t0_s[0] / fr["tau_s"]),
        rel=1e-12,
    )
    assert fit.tau_se_s == fr["tau_se_s"]


def test_vpr_curves_reproduce_the_classification(inp: ReportInput) -> None:
    assert inp.summary is not None
    res = inp.summary["results"]
    ref = load_reference()
    vpr = vpr_figure(res, ref)
    # The paper's window and threshold (Section IV.C): 11-20 s, 62.0 % recovered.
    assert (vpr.window_start_s, vpr.window_end_s) == (11.0, 20.0)
    assert vpr.window_sample_times_s == tuple(float(v) for v in range(11, 21))
    assert vpr.threshold_recovered_percent == pytest.approx(62.0, abs=0.05)
    sw = find_severity_window(ref)
    assert vpr.threshold_depth_fraction == pytest.approx(sw.threshold_depth_fraction, rel=1e-12)
    # References: D_p at t = 0, decay E/eta (Table II), severity classes as the paper's.
    assert [c.label.split(" ")[1] for c in vpr.references] == ["I", "II", "III", "IV"]
    assert [c.severe for c in vpr.references] == [False, False, True, True]
    for c, g in zip(vpr.references, ref.grades, strict=True):
        assert c.depth_curve_mm is not None and g.depth_mm is not None
        assert c.depth_curve_mm[0] == g.depth_mm
        k = 100  # t = 10 s
        assert vpr.t_s[k] == pytest.approx(10.0)
        assert c.normalised[k] == pytest.approx(math.exp(-g.decay_rate_per_s * 10.0), rel=1e-12)
    # This session's curves: the window mean of each is what the summary classified.
    kinds = {c.kind: c for c in vpr.measurements}
    assert set(kinds) == {"paper", "fitted"}
    for kind, est in (("paper", "paper_estimator"), ("fitted", "fitted_recovery")):
        sev = res["severity"][est]
        c = kinds[kind]
        assert 100.0 * (1.0 - c.window_mean_depth_fraction) == pytest.approx(
            sev["recovered_percent"], rel=1e-9
        )
        assert c.severe == (sev["severity"] == "severe")
        assert c.depth_curve_mm is not None
        assert c.depth_curve_mm[0] == res["pitting"]["depth_mm"]
    assert kinds["paper"].decay_rate_per_s == pytest.approx(
        1.0 / res["pitting"]["recovery_time_s"], rel=1e-12
    )
    assert kinds["fitted"].decay_rate_per_s == pytest.approx(
        1.0 / res["fitted_recovery"]["tau_s"], rel=1e-12
    )


def test_vpr_without_results_shows_the_references_only() -> None:
    vpr = vpr_figure(None, load_reference())
    assert vpr.measurements == ()
    assert len(vpr.references) == 4


def test_window_search_is_fig_11() -> None:
    ws = window_search_figure(load_reference())
    assert [p[0] for p in ws.pairs] == ["I-II", "II-III", "III-IV"]
    _, starts, diffs = ws.pairs[1]
    assert float(starts[int(np.argmax(diffs))]) == 11.0 == ws.window_start_s
    assert starts[0] == 1.0 and starts[-1] == 41.0


def test_parameter_table_carries_values_uncertainties_flags_and_truth(
    inp: ReportInput,
) -> None:
    assert inp.summary is not None
    res = inp.summary["results"]
    rows = {r.key: r for r in parameter_table(inp.summary)}
    assert rows["depth_mm"].value == res["pitting"]["depth_mm"]
    assert rows["time_constant_s"].value == res["fitted_recovery"]["tau_s"]
    assert rows["time_constant_s"].uncertainty == res["fitted_recovery"]["tau_se_s"]
    assert rows["amplitude_px"].uncertainty == res["fitted_recovery"]["amplitude_se_px"]
    e = res["fitted_recovery"]["model"]["elasticity_kpa"]
    eta_row = rows["viscosity_from_time_constant_n_s_per_mm2"]
    assert eta_row.uncertainty == pytest.approx(e * res["fitted_recovery"]["tau_se_s"] / 1e3)
    assert rows["depth_mm"].flags == tuple(res["pitting"]["flags"])
    assert rows["elasticity_kpa"].value == res["paper_estimator"]["elasticity_kpa"]
    sev = res["severity"]["paper_estimator"]
    assert rows["severity_paper_estimator"].value == (
        f"{sev['severity']} (nearest grade {sev['nearest_grade']})"
    )
    # Simulated session: ground truth and error for the parameters it has.
    truth = inp.summary["ground_truth"]
    assert rows["depth_mm"].truth == truth["depth_mm"]
    assert rows["depth_mm"].error_percent == pytest.approx(
        100.0 * (res["pitting"]["depth_mm"] - truth["depth_mm"]) / truth["depth_mm"]
    )
    assert rows["s0_px"].truth == truth["s0_px"]
    assert rows["t0_s"].truth is None  # scene clock differs from the session clock


def test_parameter_table_without_results_is_empty() -> None:
    assert parameter_table(None) == ()
    assert parameter_table({"results": None}) == ()


def test_parameter_table_rows_follow_their_specs(inp: ReportInput) -> None:
    rows = parameter_table(inp.summary)
    assert [r.key for r in rows[: len(PARAMETER_ROWS)]] == [s.key for s in PARAMETER_ROWS]
    assert len({s.key for s in PARAMETER_ROWS}) == len(PARAMETER_ROWS)
    assert [r.key for r in rows[len(PARAMETER_ROWS) :]] == [
        "severity_paper_estimator",
        "recovered_percent_paper_estimator",
        "severity_fitted_recovery",
        "recovered_percent_fitted_recovery",
    ]


def test_parameter_table_notes_say_why_a_value_is_missing_or_bounded(inp: ReportInput) -> None:
    summary: dict[str, Any] = copy.deepcopy(dict(inp.summary or {}))
    res = summary["results"]
    res["pitting"]["flags"] = ["not_settled"]
    res["paper_estimator"] = None
    res["fitted_recovery"]["tau_s"] = None
    res["severity"]["fitted_recovery"] = None
    rows = {r.key: r for r in parameter_table(summary)}
    assert rows["recovery_time_s"].note == "lower bound: S_k had not settled"
    assert rows["recovery_time_s"].flags == ("not_settled",)
    for key in ("elasticity_kpa", "viscosity_n_s_per_mm2"):
        assert rows[key].value is None and rows[key].note == "undefined (see notes)"
    assert rows["time_constant_s"].note == "no fit (see flags and notes)"
    assert rows["viscosity_from_time_constant_n_s_per_mm2"].uncertainty is None
    fit_class = rows["severity_fitted_recovery"]
    assert fit_class.value is None and fit_class.note == "undefined (see notes)"
    assert "recovered_percent_fitted_recovery" not in rows


def test_flag_descriptions_come_from_the_enum() -> None:
    desc = flag_descriptions()
    assert desc["not_settled"].startswith("S_k never reached 98 %")
    from stipi_daemon.analysis.flags import Flag

    assert set(desc) == {f.value for f in Flag}


def test_frame_panels_recount_the_stored_s_k(inp: ReportInput) -> None:
    panels = frame_panels(inp)
    assert [p.kind for p in panels] == ["pitting", "recovery_start", "recovered"]
    for p in panels:
        assert p.s_k_recount_px == p.s_k_live_px == p.s_k_table_px
        assert int(np.count_nonzero(p.binary.astype(bool) & p.roi_mask)) == p.s_k_recount_px
        assert p.threshold_p == inp.calibration["threshold_p"]


def _variant(inp: ReportInput, sid: str, scale: float) -> ReportInput:
    """A copy of ``inp`` whose result values are scaled (for the comparison arithmetic)."""
    summary: dict[str, Any] = copy.deepcopy(dict(inp.summary or {}))
    res = summary["results"]
    for _, _, _, path in COMPARE_PARAMETERS:
        node = res
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = node[path[-1]] * scale
    return ReportInput(**{**inp.__dict__, "session_id": sid, "summary": summary})


def test_compare_table_mean_and_spread(inp: ReportInput) -> None:
    inputs = [_variant(inp, f"s{i}", scale) for i, scale in enumerate((1.0, 1.1, 0.8, 1.3))]
    table = compare_table(inputs, ["A", "A", "B", "B"])
    assert table.session_ids == ("s0", "s1", "s2", "s3")
    assert table.grouped_by == "label"
    assert [g.label for g in table.groups] == ["A", "B"]
    assert table.groups[0].session_ids == ("s0", "s1")
    assert not hasattr(table, "overall")  # different grades are never averaged together
    assert inp.summary is not None
    depth = inp.summary["results"]["pitting"]["depth_mm"]
    values = np.array([1.0, 1.1, 0.8, 1.3]) * depth
    assert [s.values["depth_mm"].value for s in table.sessions] == pytest.approx(list(values))
    for group, part in zip(table.groups, (values[:2], values[2:]), strict=True):
        stat = {s.key: s for s in group.stats}["depth_mm"]
        assert stat.n == 2
        assert stat.mean == pytest.approx(part.mean())
        assert stat.sd == pytest.approx(part.std(ddof=1))
        assert stat.cv_percent == pytest.approx(100 * part.std(ddof=1) / part.mean())
        assert group.severe_count <= group.classified_count == 2
    assert table.sessions[0].severity is not None and "(" in table.sessions[0].severity


def test_compare_table_handles_missing_values_and_bad_labels(inp: ReportInput) -> None:
    bare = ReportInput(**{**inp.__dict__, "session_id": "bare", "summary": {"results": None}})
    table = compare_table([inp, bare], ["x", "x"])
    (group,) = table.groups
    stat = {s.key: s for s in group.stats}["depth_mm"]
    assert table.sessions[1].values["depth_mm"].value is None
    # The bare session has no validity: it is left out of the mean, and says why.
    assert group.session_ids == () or group.session_ids == (inp.session_id,)
    assert [sid for sid, _ in group.left_out][-1] == "bare"
    assert stat.n <= 1 and stat.sd is None and stat.cv_percent is None
    assert table.labels == ("x", "x")
    assert table.sessions[1].severity is None
    # Without labels a session without a class is in no group, and that is said.
    table = compare_table([inp, bare])
    assert table.grouped_by == "nearest grade"
    assert [sid for sid, _ in table.ungrouped] == ["bare"]
    with pytest.raises(AnalysisError, match="2 labels for 1 sessions"):
        compare_table([inp], ["a", "b"])
    with pytest.raises(AnalysisError, match="no session"):
        compare_table([])


def test_overlays_are_aligned_on_each_t0(inp: ReportInput) -> None:
    (s,) = overlay_s_k([inp], ["x"])
    assert inp.t0_s is not None
    np.testing.assert_array_equal(s.t_since_t0_s, inp.frame_times_s - inp.t0_s)
    np.testing.assert_array_equal(s.values, inp.s_k_px)
    (f,) = overlay_force([inp])
    np.testing.assert_array_equal(f.values, inp.force_n)
    no_t0 = ReportInput(**{**inp.__dict__, "summary": None})
    assert overlay_s_k([no_t0]) == ()


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(0.0, 100.0, allow_nan=False), min_size=1, max_size=8, unique=True),
    st.floats(0.0, 200.0, allow_nan=False),
)
def test_phase_spans_partition_the_time(times: list[float], end: float) -> None:
    times = sorted(times)
    names = ["armed", "pitting", "release", "recovery", "analysis", "done", "x", "y"]
    transitions = [Transition(t, "a", names[i], "r") for i, t in enumerate(times)]
    spans = phase_spans(transitions, end)
    for s in spans:
        assert s.end_s > s.start_s
    if end > times[-1]:
        assert len(spans) == len(times)
        assert spans[-1].end_s == end
        assert sum(s.end_s - s.start_s for s in spans) == pytest.approx(end - times[0])
    else:
        # The last phase has not lasted: it is left out, the others end at the next one.
        assert len(spans) == len(times) - 1
        assert all(s.end_s <= times[-1] for s in spans)
