"""The report says what is valid: verdict, validity column, gaps and outliers in the plots.

Sessions are variants of the recorded grade-I session: frames cut out around T_0 (a camera
gap over the release), one dark frame in the recovery, and ``summary["validity"]`` /
``summary["verdict"]`` set as the analysis records them (schema of docs/analysis.md).
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.lines import Line2D

from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.report import render as r
from stipi_daemon.report.compare import compare_table
from stipi_daemon.report.figures import force_figure, s_k_figure, vpr_figure
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.parameter_table import parameter_table
from stipi_daemon.report.series import broken_line, find_gaps, isolated_outliers
from stipi_daemon.report.verdict import UNKNOWN_LINE, read_validity, session_verdict
from stipi_daemon.report.write import REPORT_HTML, render_session_report

QUANTITIES = (
    "depth_mm",
    "rebound_force_n",
    "recovery_time_s",
    "elasticity_kpa",
    "viscosity_n_s_per_mm2",
    "severity",
    "tau_s",
    "applied_force_n",
    "viscosity_fit_n_s_per_mm2",
    "severity_fit",
)


@pytest.fixture(scope="module")
def inp(demo_session: Path) -> ReportInput:
    return load_report_input(demo_session)


def with_validity(
    inp: ReportInput,
    verdict: tuple[str, str] = ("complete", "Complete: every result is valid."),
    sid: str | None = None,
    **statuses: tuple[str, list[str], str | None],
) -> ReportInput:
    """``inp`` whose summary records validity (every quantity valid unless given) and verdict."""
    summary: dict[str, Any] = copy.deepcopy(dict(inp.summary or {}))
    summary["validity"] = {q: {"status": "valid", "flags": [], "reason": None} for q in QUANTITIES}
    for q, (status, flags, reason) in statuses.items():
        summary["validity"][q] = {"status": status, "flags": flags, "reason": reason}
    summary["verdict"] = {"status": verdict[0], "line": verdict[1]}
    return ReportInput(**{**inp.__dict__, "summary": summary, "session_id": sid or inp.session_id})


def release_gap_copy(inp: ReportInput, before_s: float = 0.7, after_s: float = 0.5) -> ReportInput:
    """``inp`` without the frames from T_0 - ``before_s`` to T_0 + ``after_s``."""
    assert inp.t0_s is not None
    t = inp.frame_times_s
    keep = (t < inp.t0_s - before_s) | (t > inp.t0_s + after_s)
    return ReportInput(
        **{
            **inp.__dict__,
            "frame_seq": inp.frame_seq[keep],
            "frame_times_s": t[keep],
            "s_k_px": inp.s_k_px[keep],
        }
    )


def _line(fig: Any, gid: str) -> Line2D:
    (line,) = [a for ax in fig.axes for a in ax.get_lines() if a.get_gid() == gid]
    return line


# --------------------------------------------------------------------------------------------
# Pure series helpers
# --------------------------------------------------------------------------------------------


def test_gaps_are_intervals_beyond_one_and_a_half_periods() -> None:
    t = np.arange(0.0, 10.0, 0.1)
    cut = np.delete(t, np.arange(40, 52))  # 12 frames lost after 3.9 s
    (gap,) = find_gaps(cut)
    assert gap.start_s == pytest.approx(3.9) and gap.end_s == pytest.approx(5.2)
    assert gap.missing == 12 and gap.duration_s == pytest.approx(1.3)
    assert find_gaps(t) == ()
    jitter = t + np.random.default_rng(0).uniform(-0.02, 0.02, t.size)
    assert find_gaps(jitter) == ()  # jitter within 1.5 periods is no gap
    lt, lv = broken_line(cut, np.ones(cut.size), (gap,))
    assert lt.size == cut.size + 1
    k = int(np.flatnonzero(np.isnan(lv))[0])
    assert lt[k - 1] == gap.start_s and lt[k + 1] == gap.end_s  # the NaN sits inside the gap
    np.testing.assert_array_equal(np.delete(lt, k), cut)


def test_isolated_outliers_ignore_the_release_step_and_noise() -> None:
    t = np.arange(0.0, 40.0, 0.1)
    rng = np.random.default_rng(3)
    s = np.where(t < 10.0, 9000.0, 2000.0 + 6000.0 * (1.0 - np.exp(-(t - 10.0) / 4.0)))
    s = s + rng.normal(0.0, 20.0, t.size)
    assert not isolated_outliers(t, s, 10.0).any()
    s[200], s[300] = 14000.0, 0.0  # one dark, one bright frame
    assert np.flatnonzero(isolated_outliers(t, s, 10.0)).tolist() == [200, 300]
    assert not isolated_outliers(t, s, None).any()


# --------------------------------------------------------------------------------------------
# Figures: gaps break the lines, are shaded; release, T_0, S_0 and outliers are marked
# --------------------------------------------------------------------------------------------


def test_a_gap_over_the_release_breaks_the_line_and_is_shaded(inp: ReportInput) -> None:
    cut = release_gap_copy(inp)
    assert cut.t0_s is not None
    sk = s_k_figure(cut)
    gap = max(sk.gaps, key=lambda g: g.duration_s)
    assert gap.start_s < cut.t0_s - 0.7 and gap.end_s > cut.t0_s + 0.5
    # The plotted line: every stored frame, plus one NaN inside each gap.
    assert sk.line_t_s.size == sk.t_s.size + len(sk.gaps)
    inside = (sk.line_t_s > gap.start_s) & (sk.line_t_s < gap.end_s)
    assert np.isnan(sk.line_s_k_px[inside]).all() and inside.sum() == 1
    fig = r.draw_s_k(sk)
    x = np.asarray(_line(fig, "s_k").get_xdata(), dtype=float)
    y = np.asarray(_line(fig, "s_k").get_ydata(), dtype=float)
    k = int(np.searchsorted(x, gap.start_s))
    assert x[k] == gap.start_s and np.isnan(y[k + 1]) and x[k + 2] == gap.end_s
    spans = [p for p in fig.axes[0].patches if p.get_gid() == "frame_gap"]
    assert len(spans) == len(sk.gaps)
    xs = [(p.get_x(), p.get_x() + p.get_width()) for p in spans]
    assert (gap.start_s, gap.end_s) in [pytest.approx(v) for v in xs]
    texts = [t.get_text() for t in fig.axes[0].texts]
    assert f"frame gap {gap.duration_s:.2f} s" in texts
    assert not [p for p in fig.axes[0].patches if p.get_gid() == "release_gap"]
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any(lb.startswith(f"frame gaps: {len(sk.gaps)} (longest") for lb in labels)
    assert "release detected" in labels and "$T_0$ (start of recovery)" in labels
    assert any(lb.startswith("$S_0$ =") for lb in labels)
    # When the analysis records that the release was not observed, its span is marked.
    summary: dict[str, Any] = copy.deepcopy(dict(cut.summary or {}))
    summary["results"]["pitting"]["observation"] = {
        "release_gap_s": [gap.start_s, gap.end_s],
        "outlier_frame_times_s": [],
    }
    fig = r.draw_s_k(s_k_figure(ReportInput(**{**cut.__dict__, "summary": summary})))
    (span,) = [p for p in fig.axes[0].patches if p.get_gid() == "release_gap"]
    assert (span.get_x(), span.get_x() + span.get_width()) == pytest.approx(
        (gap.start_s, gap.end_s)
    )
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "release not observed (no frame around $T_0$)" in labels


def test_the_recorded_session_has_no_gap_and_the_force_line_is_the_samples(
    inp: ReportInput,
) -> None:
    sk = s_k_figure(inp)
    assert sk.gaps == () and sk.outlier_t_s.size == 0
    np.testing.assert_array_equal(sk.line_s_k_px, sk.s_k_px)
    f = force_figure(inp)
    np.testing.assert_array_equal(f.line_t_s[~np.isin(f.line_t_s, f.t_s)].size, len(f.gaps))
    assert f.release_s == (inp.summary or {})["measurement"]["t0_s"]


def test_outlier_frames_are_marked(inp: ReportInput) -> None:
    assert inp.t0_s is not None
    s = inp.s_k_px.copy()
    k = int(np.searchsorted(inp.frame_times_s, inp.t0_s + 6.0))
    s[k] = 4.0 * float(np.nanmax(s))  # a dark frame mid-recovery
    # A session recorded before the analysis recorded its outliers: the report finds them.
    old_summary: dict[str, Any] = copy.deepcopy(dict(inp.summary or {}))
    old_summary["results"]["pitting"].pop("observation", None)
    dark = ReportInput(**{**inp.__dict__, "s_k_px": s, "summary": old_summary})
    sk = s_k_figure(dark)
    assert sk.outlier_source == "report"
    np.testing.assert_array_equal(sk.outlier_t_s, [inp.frame_times_s[k]])
    fig = r.draw_s_k(sk)
    assert sk.outlier_s_k_px.tolist() == [s[k]]
    # The line leaves the outlier out (no spike); the marker sits at the axis edge.
    assert inp.frame_times_s[k] not in sk.line_t_s.tolist()
    y = _line(fig, "outliers").get_ydata()
    assert list(y) == [fig.axes[0].get_ylim()[1]] and s[k] > fig.axes[0].get_ylim()[1]
    # What the analysis recorded wins over the report's own check.
    summary: dict[str, Any] = copy.deepcopy(dict(dark.summary or {}))
    t_other = float(inp.frame_times_s[k + 5])
    summary["results"]["pitting"]["observation"] = {"outlier_frame_times_s": [t_other]}
    recorded = s_k_figure(ReportInput(**{**dark.__dict__, "summary": summary}))
    assert recorded.outlier_source == "analysis"
    assert recorded.outlier_t_s.tolist() == [t_other]
    # The fit figure leaves the recorded outlier out of the fitted frames and marks it.
    from stipi_daemon.report.figures import fit_figure

    fit = fit_figure(ReportInput(**{**dark.__dict__, "summary": summary}))
    assert fit is not None and inp.t0_s is not None
    assert fit.rejected_t_since_t0_s.tolist() == [t_other - inp.t0_s]
    assert t_other - inp.t0_s not in fit.t_since_t0_s.tolist()
    x = r.draw_fit(fit)
    assert list(_line(x, "fit_rejected").get_xdata()) == [t_other - inp.t0_s]


# --------------------------------------------------------------------------------------------
# Verdict and parameter table
# --------------------------------------------------------------------------------------------


def test_invalid_quantities_are_not_shown_as_results(inp: ReportInput, tmp_path: Path) -> None:
    reason = "release not observed: no frame between 18.80 and 20.00 s"
    bad = with_validity(
        release_gap_copy(inp),
        ("invalid", "Not valid: D_p, E, eta, severity (release not observed)."),
        depth_mm=("invalid", ["release_not_observed"], reason),
        elasticity_kpa=("invalid", [], f"D_p is invalid ({reason})"),
        viscosity_n_s_per_mm2=("invalid", [], "E is invalid"),
        severity=("invalid", [], "eta is invalid"),
        recovery_time_s=("flagged", ["not_settled"], "T_r is only a lower bound"),
    )
    rows = {row.key: row for row in parameter_table(bad.summary)}
    for key in (
        "depth_mm",
        "depth_change_mm",
        "s0_px",
        "elasticity_kpa",
        "severity_paper_estimator",
    ):
        assert not rows[key].shown_as_result, key
    assert rows["depth_mm"].validity is not None and rows["depth_mm"].validity.reason == reason
    assert rows["recovery_time_s"].shown_as_result
    assert rows["t0_s"].validity is None
    # The paper estimator's VPR curve is not drawn from invalid E and eta.
    vpr = vpr_figure(bad.results, load_reference(), validity=None)
    assert "paper" in {c.kind for c in vpr.measurements}
    vpr = vpr_figure(bad.results, load_reference(), validity=read_validity(bad.summary))
    assert "paper" not in {c.kind for c in vpr.measurements} and vpr.omitted
    render_session_report(bad, tmp_path)
    page = (tmp_path / REPORT_HTML).read_text(encoding="utf-8")
    assert 'class="badge badge-invalid" id="status">invalid<' in page
    assert '<span id="verdict-line">some primary results cannot be trusted</span>' in page
    assert 'data-key="depth_mm" data-invalid="1">—' in page
    depth = (bad.summary or {})["results"]["pitting"]["depth_mm"]
    assert f'data-key="depth_mm">{depth:.4g}<' not in page
    assert f"invalid: {reason}" in page
    assert (
        '<li data-quantity="depth_mm"><b>D_p</b> (pitting depth) '
        f'<span class="v-invalid">invalid</span>: {reason} '
    ) in page
    assert '<li data-quantity="recovery_time_s">' in page
    assert '<span class="v-invalid">D_p = — (not valid)</span>' in page
    assert "Not drawn, as not valid: this session&#x27;s depth curves D(t) (D_p not valid" in page
    assert "the paper estimator&#x27;s curve (E or η not valid" in page


def test_complete_only_when_every_primary_quantity_is_valid(inp: ReportInput) -> None:
    ok = with_validity(inp)
    assert session_verdict(ok.summary, "complete").status == "complete"
    # A summary that claims complete with a flagged primary quantity is shown as flagged.
    claim = with_validity(inp, recovery_time_s=("flagged", ["not_settled"], "lower bound"))
    v = session_verdict(claim.summary, "complete")
    assert v.status == "flagged" and "caveat" in v.line
    assert [p.quantity for p in v.problems] == ["recovery_time_s"]
    # A flagged secondary quantity does not change the verdict but is named.
    tau = with_validity(inp, tau_s=("flagged", ["time_constant_outside_window"], "tau long"))
    v = session_verdict(tau.summary, "complete")
    assert v.status == "complete" and [p.quantity for p in v.problems] == ["tau_s"]
    # A session that did not complete is incomplete whatever its quantities.
    assert session_verdict(ok.summary, "fault").status == "incomplete"


def test_old_sessions_read_as_validity_unknown(inp: ReportInput, tmp_path: Path) -> None:
    summary = {k: v for k, v in (inp.summary or {}).items() if k not in ("validity", "verdict")}
    old = ReportInput(**{**inp.__dict__, "summary": summary})
    v = session_verdict(old.summary, "complete")
    assert v.status == "unknown" and UNKNOWN_LINE in v.line.lower()
    rows = {row.key: row for row in parameter_table(summary)}
    assert rows["depth_mm"].validity is not None
    assert rows["depth_mm"].validity.status == "unknown" and rows["depth_mm"].shown_as_result
    render_session_report(old, tmp_path)
    page = (tmp_path / REPORT_HTML).read_text(encoding="utf-8")
    assert 'id="status">unknown<' in page
    assert f'<span id="verdict-line">{UNKNOWN_LINE}</span>' in page
    malformed = {**summary, "validity": {"depth_mm": "?"}, "verdict": "?"}
    assert session_verdict(malformed, "complete").status == "invalid"


# --------------------------------------------------------------------------------------------
# Comparison
# --------------------------------------------------------------------------------------------


def test_compare_averages_only_complete_sessions_and_keeps_flags(inp: ReportInput) -> None:
    a = with_validity(inp, sid="a")
    b = with_validity(
        inp,
        ("flagged", "Complete with caveats on T_r."),
        sid="b",
        recovery_time_s=("flagged", ["not_settled"], "lower bound"),
    )
    c = with_validity(
        inp,
        ("invalid", "Not valid: D_p."),
        sid="c",
        depth_mm=("invalid", ["release_not_observed"], "release not observed"),
    )
    summary_c: dict[str, Any] = copy.deepcopy(dict(c.summary or {}))
    summary_c["results"]["pitting"]["depth_mm"] = 100.0  # a wrong value that must not count
    c = ReportInput(**{**c.__dict__, "summary": summary_c})
    summary_b: dict[str, Any] = copy.deepcopy(dict(b.summary or {}))
    summary_b["results"]["pitting"]["recovery_time_s"] = 1000.0  # flagged: must not count
    summary_b["results"]["pitting"]["flags"] = ["not_settled"]
    b = ReportInput(**{**b.__dict__, "summary": summary_b})
    table = compare_table([a, b, c], ["I", "I", "I"])
    assert [v.status for v in table.verdicts] == ["complete", "flagged", "invalid"]
    (group,) = table.groups
    assert group.session_ids == ("a",)
    left = dict(group.left_out)
    assert left["b"].startswith("verdict flagged: T_r flagged (not_settled)")
    assert left["c"].startswith("verdict invalid: D_p invalid (release_not_observed)")
    stats = {s.key: s for s in group.stats}
    assert stats["depth_mm"].n == 1
    assert stats["depth_mm"].mean == (inp.summary or {})["results"]["pitting"]["depth_mm"]
    assert stats["recovery_time_s"].mean == pytest.approx(
        (inp.summary or {})["results"]["pitting"]["recovery_time_s"]
    )
    # Each session keeps its flags and each value its validity with the flags.
    sessions = {s.session_id: s for s in table.sessions}
    assert "not_settled" in sessions["b"].flags
    tr = sessions["b"].values["recovery_time_s"]
    assert (tr.status, tr.flags) == ("flagged", ("not_settled",))
    assert sessions["c"].values["depth_mm"].status == "invalid"


def test_compare_page_says_what_was_left_out(inp: ReportInput) -> None:
    from stipi_daemon.report.html import compare_page

    a = with_validity(inp, sid="a")
    c = with_validity(
        inp,
        ("invalid", "Not valid: D_p."),
        sid="c",
        depth_mm=("invalid", ["release_not_observed"], "release not observed"),
    )
    page = compare_page(table=compare_table([a, c], ["I", "I"]), figures=[], meta=[])
    assert '<li data-left-out="c">I: c: verdict invalid: D_p invalid' in page
    assert '<td class="num" data-validity="invalid">—<span class="not-valid">' in page
    assert (
        '<span class="badge badge-invalid">invalid</span><br>D_p invalid: release not observed'
    ) in page
    assert '<td data-flags="c"><span class="flag">' in page
    assert '<th data-group="I">I (n = 1)</th>' in page


def test_figures_say_when_t_r_or_tau_is_not_valid(inp: ReportInput) -> None:
    from stipi_daemon.report.figures import fit_figure

    bad = with_validity(
        inp,
        ("invalid", "Not valid: T_r."),
        recovery_time_s=("invalid", ["no_recovery"], "S_k did not rise after T_0"),
        tau_s=("invalid", ["fit_not_converged"], "the recovery fit did not converge"),
    )
    sk = s_k_figure(bad)
    assert sk.recovery_time_invalid == "S_k did not rise after T_0"
    texts = [t.get_text() for t in r.draw_s_k(sk).axes[0].texts]
    assert any(t.startswith("$T_r$ =") and t.endswith("(not valid)") for t in texts)
    fit = fit_figure(bad)
    assert fit is not None and fit.tau_invalid == "the recovery fit did not converge"
    title = r.draw_fit(fit).axes[0].get_title()
    assert "τ not valid: the recovery fit did not converge" in title
    assert s_k_figure(with_validity(inp)).recovery_time_invalid is None


def test_force_gaps_break_the_force_line_and_nan_frames_are_marked(inp: ReportInput) -> None:
    assert inp.t0_s is not None
    t = inp.force_times_s
    keep = (t < inp.t0_s - 0.5) | (t > inp.t0_s + 0.5)  # a force dropout over the release
    cut = ReportInput(**{**inp.__dict__, "force_times_s": t[keep], "force_n": inp.force_n[keep]})
    f = force_figure(cut)
    gap = max(f.gaps, key=lambda g: g.duration_s)
    assert gap.duration_s > 1.0
    fig = r.draw_force(f)
    y = np.asarray(_line(fig, "force").get_ydata(), dtype=float)
    x = np.asarray(_line(fig, "force").get_xdata(), dtype=float)
    inside = (x > gap.start_s) & (x < gap.end_s)
    assert inside.sum() == 1 and np.isnan(y[inside]).all()
    assert [p for p in fig.axes[0].patches if p.get_gid() == "force_gap"]
    assert any(tx.get_text().startswith("force gap ") for tx in fig.axes[0].texts)
    # Frames whose S_k is NaN are ticked at the bottom of the S_k figure.
    s = inp.s_k_px.copy()
    k = int(np.searchsorted(inp.frame_times_s, inp.t0_s + 3.0))
    s[k] = np.nan
    sk = s_k_figure(ReportInput(**{**inp.__dict__, "s_k_px": s}))
    assert sk.nan_frame_t_s.tolist() == [inp.frame_times_s[k]]
    ticks = _line(r.draw_s_k(sk), "nan_frames")
    assert list(ticks.get_xdata()) == [inp.frame_times_s[k]]


def test_every_assessed_quantity_has_a_name_on_the_page() -> None:
    from stipi_daemon.analysis import validity
    from stipi_daemon.report.verdict import QUANTITY_NAMES

    assessed = (*validity.PRIMARY_QUANTITIES, *validity.SECONDARY_QUANTITIES)
    assert set(assessed) == set(QUANTITY_NAMES) == set(QUANTITIES)
