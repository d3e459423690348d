"""What a lab user reads in a report: numbers, the two time constants, visible references,
the verdict block, the metadata, and a comparison that averages only like with like.

Figures are checked as Chromium shows them: every figure of a report is put on one page
(each ``<img>`` exactly as the report embeds it), screenshotted by headless Chromium, and
the reference curves and threshold are looked for at the pixels matplotlib placed them.
"""

from __future__ import annotations

import base64
import copy
import math
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.report import render as r
from stipi_daemon.report.compare import compare_table
from stipi_daemon.report.figures import GRADE_MATCH_NOTE, measurement_curves, vpr_figure
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.numbers import percent_text, value_text, value_with_uncertainty
from stipi_daemon.report.write import (
    REPORT_HTML,
    render_session_report,
    write_compare_report,
)
from tests.conftest import require_tool
from tests.report.test_browser import _screenshot
from tests.report.test_validity import with_validity


@pytest.fixture(scope="module")
def inp(demo_session: Path) -> ReportInput:
    return load_report_input(demo_session)


# --------------------------------------------------------------------------------------------
# One rounding rule
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "uncertainty", "texts"),
    [
        (16.01, 0.0001303, ("16.0100", "0.00013")),  # the compare table's "16.01 ± 0.0001303"
        (7.649032, 3.2e-05, ("7.64903", "0.000032")),  # 6 significant figures at most
        (123.456, 0.0996, ("123.46", "0.10")),  # 0.0996 rounds up to 0.10: two decimals
        (12989.79, 15.3, ("12990", "15")),
        (0.5, 30.0, ("0.5", "30")),  # a value is never rounded away entirely
        (-0.3, 0.012, ("-0.300", "0.012")),
        (5.0, 0.0, ("5", "0")),
        (2.92947, None, ("2.929", "-")),
        (None, 0.1, ("-", "0.1")),
    ],
)
def test_value_and_uncertainty_are_rounded_together(
    value: float | None, uncertainty: float | None, texts: tuple[str, str]
) -> None:
    assert value_with_uncertainty(value, uncertainty) == texts


@pytest.mark.parametrize(
    ("percent", "text"),
    [
        (0.0008376, "0.00"),  # the error column's unrounded 0.0008376
        (-0.004, "0.00"),  # no "-0.00"
        (0.0567, "0.06"),
        (1.234, "1.2"),
        (-3.14159, "-3.1"),
        (12.345, "12"),
        (150.2, "150"),
        (math.nan, "-"),
        (None, "-"),
    ],
)
def test_percentages_have_two_significant_figures_down_to_a_hundredth(
    percent: float | None, text: str
) -> None:
    assert percent_text(percent) == text


@settings(max_examples=200, deadline=None)
@given(
    st.floats(-1e6, 1e6, allow_nan=False).filter(lambda v: abs(v) > 1e-6),
    st.floats(1e-6, 1e5, allow_nan=False),
)
def test_rounding_keeps_the_value_within_half_a_last_digit(value: float, u: float) -> None:
    v_text, u_text = value_with_uncertainty(value, u)
    decimals = len(v_text.split(".")[1]) if "." in v_text else 0
    step = 10.0**-decimals
    if decimals == 0 and len(v_text.lstrip("-")) > 1:
        step = 10.0 ** (len(v_text.lstrip("-")) - len(v_text.lstrip("-").rstrip("0")))
    assert abs(float(v_text) - value) <= 0.5 * step * (1 + 1e-9) + 1e-12
    digits = u_text.replace(".", "").lstrip("0")
    assert 1 <= len(digits) <= 2 or float(u_text).is_integer()  # u: two significant figures
    assert abs(float(u_text) - u) <= 0.051 * u + 1e-12


def test_every_table_uses_the_one_rule(inp: ReportInput, tmp_path: Path) -> None:
    """Parameter table: value with its SE, error [%] to 0.01 %; no raw float repr left."""
    render_session_report(inp, tmp_path)
    page = (tmp_path / REPORT_HTML).read_text(encoding="utf-8")
    res = (inp.summary or {})["results"]
    tau, tau_se = value_with_uncertainty(
        res["fitted_recovery"]["tau_s"], res["fitted_recovery"]["tau_se_s"]
    )
    assert f'data-key="time_constant_s">{tau}<' in page and f">{tau_se}<" in page
    errors = re.findall(r'data-error="[^"]+">([^<]*)<', page)
    assert errors, "no error column"
    for e in errors:
        assert e == "-" or re.fullmatch(r"-?\d+(\.\d{1,2})?", e), e
    # Every number in a table cell has at most 6 significant figures.
    for cell in re.findall(r'<td class="num"[^>]*>([^<]*)<', page):
        for number in re.findall(r"\d+\.\d+", cell):
            assert len(number.replace(".", "").lstrip("0")) <= 6, cell


# --------------------------------------------------------------------------------------------
# Figs. 10 and 12: which time each curve decays with, and what its label says
# --------------------------------------------------------------------------------------------


def _results(tau_s: float, amplitude_px: float, offset_px: float) -> dict[str, Any]:
    return {
        "pitting": {"depth_mm": 2.0, "recovery_time_s": 9.0},
        "paper_estimator": {"elasticity_kpa": 300.0, "viscosity_n_s_per_mm2": 2.7},
        "fitted_recovery": {"tau_s": tau_s, "amplitude_px": amplitude_px, "offset_px": offset_px},
        "severity": {
            "paper_estimator": {"severity": "mild", "nearest_grade": "II"},
            "fitted_recovery": {"severity": "mild", "nearest_grade": "II"},
        },
    }


def test_each_legend_entry_names_the_time_its_curve_decays_with() -> None:
    tau, amp, off = 7.65, 9000.0, 10000.0
    # The paper's T_r of an ideal recovery: S_inf - A exp(-T/tau) = 0.98 S_inf (Eq. 6).
    t_r_tau = tau * math.log(amp / (0.02 * off))
    vpr = vpr_figure(_results(tau, amp, off), load_reference())
    fit = next(c for c in vpr.measurements if c.kind == "fitted")
    assert fit.decay_rate_per_s == pytest.approx(1.0 / tau)
    assert fit.normalised_rate_per_s == pytest.approx(1.0 / t_r_tau)
    assert f"τ = {value_text(tau, 's')}" in fit.label and "T_r(τ)" not in fit.label
    assert f"T_r(τ) = {value_text(t_r_tau, 's')}" in fit.normalised_label
    assert "τ =" not in fit.normalised_label.replace("T_r(τ) =", "")
    # The curve drawn under each label decays to 1/e at the time the label names.
    fig10 = r.draw_vpr(vpr)
    fig12 = r.draw_normalised(vpr)
    for fig, gid, time_s in ((fig10, "vpr_fitted", tau), (fig12, "normalised_fitted", t_r_tau)):
        line = _line(fig, gid)
        x, y = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
        y = y / y[0]
        assert np.interp(time_s, x, y) == pytest.approx(math.exp(-1.0), rel=1e-3)
        number = re.search(r"= ([\d.]+) s", line.get_label().split(":", 1)[1])
        assert number is not None and float(number.group(1)) == pytest.approx(time_s, rel=1e-3)
    # The two figures' labels of the fit differ; the paper estimator's is the same in both.
    paper = next(c for c in vpr.measurements if c.kind == "paper")
    assert paper.label == paper.normalised_label and fit.label != fit.normalised_label


def test_the_grade_is_said_to_be_matched_on_the_normalised_shape(inp: ReportInput) -> None:
    vpr = vpr_figure(inp.results, load_reference())
    assert vpr.grade_note.endswith(GRADE_MATCH_NOTE)
    grade = (inp.results or {})["severity"]["paper_estimator"]["nearest_grade"]
    assert f"nearest grade {grade}" in vpr.grade_note
    fig = r.draw_vpr(vpr)
    (note,) = [t for t in fig.axes[0].texts if t.get_gid() == "grade_note"]
    assert "normalised curve" in note.get_text() and "not on the depth" in note.get_text()
    assert vpr_figure(None, load_reference()).grade_note == ""


def _line(fig: Figure, gid: str) -> Line2D:
    (line,) = [a for ax in fig.axes for a in ax.get_lines() if a.get_gid() == gid]
    return line


def _legend_labels(fig: Figure) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.get_legend().get_texts()]


def _dashes(line: Line2D) -> object:
    """The line's dash pattern (``get_linestyle`` says "--" for every custom pattern)."""
    return line._unscaled_dash_pattern  # type: ignore[attr-defined]


def _check_styles(fig: Figure) -> None:
    """References above every session curve; the threshold in a style no reference has."""
    lines = fig.axes[0].get_lines()
    refs = [ln for ln in lines if "reference" in str(ln.get_gid())]
    sessions = [
        ln
        for ln in lines
        if str(ln.get_gid()).startswith(("session_", "vpr_paper", "vpr_fitted", "normalised_p"))
        or ln.get_gid() == "normalised_fitted"
    ]
    assert refs and sessions
    assert min(ln.get_zorder() for ln in refs) > max(ln.get_zorder() for ln in sessions)
    thresholds = [ln for ln in lines if ln.get_gid() == "threshold"]
    for thr in thresholds:
        for ref in refs:
            assert thr.get_color() != ref.get_color()
            assert _dashes(thr) != _dashes(ref)
        for s in sessions:
            assert (thr.get_color(), _dashes(thr)) != (s.get_color(), _dashes(s))
    labels = _legend_labels(fig)
    assert len(labels) == len(set(labels)), labels


def test_references_are_drawn_above_the_sessions_and_legends_are_unique(
    inp: ReportInput,
) -> None:
    vpr = vpr_figure(inp.results, load_reference())
    _check_styles(r.draw_vpr(vpr))
    _check_styles(r.draw_normalised(vpr))
    ref = vpr_figure(None, load_reference())
    wt = np.asarray(ref.window_sample_times_s)
    curves = measurement_curves(inp.results, ref.t_s, wt, "I")
    repeated = [("I", True, curves), ("I", True, curves), ("I", False, curves)]
    for normalised in (False, True):
        fig = r.draw_compare_vpr(ref, repeated, normalised=normalised)
        _check_styles(fig)
        labels = _legend_labels(fig)
        assert "I (2 sessions), η = E·T_r" in labels
        assert "I, not averaged (1 session), η = E·T_r" in labels


# --------------------------------------------------------------------------------------------
# Verdict block and metadata
# --------------------------------------------------------------------------------------------


def test_verdict_block_is_the_status_then_one_line_per_quantity(
    inp: ReportInput, tmp_path: Path
) -> None:
    bad = with_validity(
        inp,
        ("invalid", "Not valid: D_p, E, η, severity (a long recorded sentence, run on)."),
        depth_mm=("invalid", ["release_not_observed"], "no frame between 18.8 and 20.0 s"),
        elasticity_kpa=("invalid", ["release_not_observed"], "D_p is invalid"),
        recovery_time_s=("flagged", ["frame_gap_at_settling"], "T_r uncertain by 0.4 s"),
    )
    written = render_session_report(bad, tmp_path)
    page = (tmp_path / REPORT_HTML).read_text(encoding="utf-8")
    block = page[page.index('<section id="verdict"') : page.index("</section>")]
    assert "a long recorded sentence" not in block
    assert '<b>Verdict</b> <span class="badge badge-invalid" id="status">invalid</span>' in block
    items = re.findall(r'<li data-quantity="([^"]+)">', block)
    assert items == ["depth_mm", "recovery_time_s", "elasticity_kpa"]  # primary order
    assert "no frame between 18.8 and 20.0 s" in block and "T_r uncertain by 0.4 s" in block
    assert written.verdict.splitlines() == [
        "invalid (some primary results cannot be trusted)",
        "  D_p: invalid: no frame between 18.8 and 20.0 s [release_not_observed]",
        "  T_r: flagged: T_r uncertain by 0.4 s [frame_gap_at_settling]",
        "  E: invalid: D_p is invalid [release_not_observed]",
    ]


def test_session_metadata_is_shown_and_its_absence_said(inp: ReportInput, tmp_path: Path) -> None:
    given = {"subject": "P-017 <left>", "site": "Lab 2", "operator": None, "note": "a\nb"}
    shown = ReportInput(**{**inp.__dict__, "metadata": given})
    render_session_report(shown, tmp_path / "a")
    page = (tmp_path / "a" / REPORT_HTML).read_text(encoding="utf-8")
    assert '<dd data-field="subject">P-017 &lt;left&gt;</dd>' in page
    assert '<dd data-field="site">Lab 2</dd>' in page
    assert '<dd data-field="operator"><span class="v-unknown">not given</span></dd>' in page
    assert '<dd data-field="note">a<br>b</dd>' in page
    older = ReportInput(**{**inp.__dict__, "metadata": None})
    render_session_report(older, tmp_path / "b")
    page = (tmp_path / "b" / REPORT_HTML).read_text(encoding="utf-8")
    assert "Session metadata: none (recorded before subject, site, operator and note" in page
    broken = ReportInput(
        **{**inp.__dict__, "metadata": None, "metadata_problem": "manifest.json: field 'x'"}
    )
    render_session_report(broken, tmp_path / "c")
    page = (tmp_path / "c" / REPORT_HTML).read_text(encoding="utf-8")
    assert "Session metadata not shown: manifest.json: field &#x27;x&#x27;" in page


def test_metadata_is_read_from_the_manifest(demo_session: Path, tmp_path: Path) -> None:
    import json
    import shutil

    session = tmp_path / demo_session.name
    shutil.copytree(demo_session, session)
    manifest = json.loads((session / "manifest.json").read_text())
    manifest["metadata"] = {"subject": "S1", "site": None, "operator": "op", "note": None}
    (session / "manifest.json").write_text(json.dumps(manifest))
    assert load_report_input(session).metadata == manifest["metadata"]
    del manifest["metadata"]
    (session / "manifest.json").write_text(json.dumps(manifest))
    assert load_report_input(session).metadata is None
    manifest["metadata"] = {"subject": "two\nlines"}
    (session / "manifest.json").write_text(json.dumps(manifest))
    broken = load_report_input(session)
    assert broken.metadata is None and broken.metadata_problem is not None
    assert "subject" in broken.metadata_problem


# --------------------------------------------------------------------------------------------
# Comparison: by grade, complete sessions only, flags kept
# --------------------------------------------------------------------------------------------


def test_compare_never_averages_grades_or_flagged_sessions(inp: ReportInput) -> None:
    res = (inp.summary or {})["results"]
    a1, a2 = with_validity(inp, sid="a1"), with_validity(inp, sid="a2")
    summary: dict[str, Any] = copy.deepcopy(dict(a2.summary or {}))
    summary["results"]["pitting"]["depth_mm"] = 2.0 * res["pitting"]["depth_mm"]
    a2 = ReportInput(**{**a2.__dict__, "summary": summary})
    flagged = with_validity(
        inp, ("flagged", "x"), sid="f", depth_mm=("flagged", ["roi_clipped"], "ROI clipped")
    )
    other = with_validity(inp, sid="b")
    summary = copy.deepcopy(dict(other.summary or {}))
    summary["results"]["pitting"]["depth_mm"] = 100.0
    other = ReportInput(**{**other.__dict__, "summary": summary})
    table = compare_table([a1, flagged, a2, other], ["I", "I", "I", "II"])
    one, two = table.groups
    assert (one.label, one.session_ids, two.session_ids) == ("I", ("a1", "a2"), ("b",))
    assert [sid for sid, _ in one.left_out] == ["f"]
    depth = {s.key: s for s in one.stats}["depth_mm"]
    assert depth.mean == pytest.approx(1.5 * res["pitting"]["depth_mm"])  # not f, not b
    assert {s.key: s for s in two.stats}["depth_mm"].mean == 100.0
    assert "roi_clipped" in table.sessions[1].flags


def test_compare_report_in_chromium(
    demo_session: Path, second_session: Path, tmp_path: Path
) -> None:
    """Each compare figure as Chromium shows it; every reference visible on the sessions'."""
    written = write_compare_report(
        [demo_session, second_session, demo_session], tmp_path / "cmp", ["I", "II", "I"]
    )
    page = written.html_path.read_text(encoding="utf-8")
    assert page.count("<th data-group=") == 2 and "all sessions (n" not in page
    ref = vpr_figure(None, load_reference())
    wt = np.asarray(ref.window_sample_times_s)
    curves = [
        (lb, True, measurement_curves(load_report_input(s).results, ref.t_s, wt, lb))
        for lb, s in (("I", demo_session), ("II", second_session), ("I", demo_session))
    ]
    figs = {
        "compare_vpr": r.draw_compare_vpr(ref, curves, normalised=False),
        "compare_vpr_normalised": r.draw_compare_vpr(ref, curves, normalised=True),
    }
    shots = _figures_in_chromium(page, tmp_path)
    assert set(shots) == set(written.figures)
    for name, fig in figs.items():
        # The redrawn figure is the report's, byte for byte: its geometry is the report's.
        assert r.png_bytes(fig) == written.figures[name].read_bytes()
        _references_visible(fig, shots[name], ("reference_",))
    _threshold_visible(figs["compare_vpr_normalised"], shots["compare_vpr_normalised"])


def test_session_report_figures_in_chromium(inp: ReportInput, tmp_path: Path) -> None:
    """Each figure of a session report as Chromium shows it; Figs. 10 and 12 looked into."""
    written = render_session_report(inp, tmp_path / "rep")
    page = written.html_path.read_text(encoding="utf-8")
    shots = _figures_in_chromium(page, tmp_path)
    assert set(shots) == set(written.figures)
    vpr = vpr_figure(inp.results, load_reference())
    fig10, fig12 = r.draw_vpr(vpr), r.draw_normalised(vpr)
    assert r.png_bytes(fig10) == written.figures["vpr"].read_bytes()
    assert r.png_bytes(fig12) == written.figures["vpr_normalised"].read_bytes()
    # The recorded grade-I session's curve lies on grade I's reference in Fig. 12.
    grade = (inp.results or {})["severity"]["paper_estimator"]["nearest_grade"]
    assert grade == "I"
    _references_visible(fig10, shots["vpr"], ("vpr_reference_",))
    _references_visible(fig12, shots["vpr_normalised"], ("normalised_reference_",))
    _threshold_visible(fig12, shots["vpr_normalised"])


# --------------------------------------------------------------------------------------------
# Chromium helpers
# --------------------------------------------------------------------------------------------

_IMG = re.compile(
    r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)" alt="[^"]*" data-file="([^"]+)">'
)


def _figures_in_chromium(report_page: str, tmp_path: Path) -> dict[str, np.ndarray]:
    """Every figure of ``report_page`` (its ``<img>`` as embedded) in one Chromium screenshot,
    cut back into one image per figure; each is checked to be the PNG as written."""
    require_tool("chromium")
    found = [
        (m.group(2).removesuffix(".png"), m.group(0), m.group(1))
        for m in _IMG.finditer(report_page)
    ]
    assert found
    pngs = {
        name: cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        for name, _, data in found
    }
    width = max(p.shape[1] for p in pngs.values())
    height = sum(p.shape[0] for p in pngs.values())
    page = tmp_path / "figures.html"
    page.write_text(
        '<!DOCTYPE html><html><head><meta charset="utf-8"><style>body{margin:0;background:#fff}'
        "img{display:block}</style></head><body>"
        + "".join(tag for _, tag, _ in found)
        + "</body></html>",
        encoding="utf-8",
    )
    shot, log = _screenshot(page, tmp_path, (width, height))
    assert "net::ERR_" not in log
    out: dict[str, np.ndarray] = {}
    y = 0
    for name, png in pngs.items():
        h, w = png.shape[:2]
        part = shot[y : y + h, :w]
        y += h
        diff = np.abs(part.astype(int) - png.astype(int))
        assert float(diff.mean()) < 2.0, f"{name}: Chromium shows something else"
        assert float(part.std()) > 10.0, f"{name} is blank"
        out[name] = part
    return out


def _pixels(fig: Figure, x: Sequence[float], y: Sequence[float]) -> np.ndarray:
    """Data points of the first axes -> (column, row) in the figure's PNG."""
    xy = fig.axes[0].transData.transform(np.column_stack([x, y]))
    height = fig.get_size_inches()[1] * fig.dpi
    return np.column_stack([xy[:, 0], height - xy[:, 1]])


def _colour_near(img: np.ndarray, col: float, row: float, bgr: np.ndarray, radius: int) -> bool:
    c, rr = round(col), round(row)
    patch = img[max(rr - radius, 0) : rr + radius + 1, max(c - radius, 0) : c + radius + 1]
    return bool((np.abs(patch.astype(int) - bgr).max(axis=2) < 45).any())


def _bgr(hex_colour: str) -> np.ndarray:
    h = hex_colour.lstrip("#")
    return np.array([int(h[4:6], 16), int(h[2:4], 16), int(h[0:2], 16)])


def _references_visible(fig: Figure, img: np.ndarray, prefixes: tuple[str, ...]) -> None:
    """Along each reference curve (away from the legend, the axes and other references) its
    colour is on screen at most sample points, also where a session curve lies on it."""
    ax = fig.axes[0]
    legend = ax.get_legend().get_window_extent()
    height = fig.get_size_inches()[1] * fig.dpi
    refs = [ln for ln in ax.get_lines() if str(ln.get_gid()).startswith(prefixes)]
    assert refs
    ylo, yhi = ax.get_ylim()
    for ref in refs:
        x, y = np.asarray(ref.get_xdata()), np.asarray(ref.get_ydata())
        keep = (y > ylo + 0.06 * (yhi - ylo)) & (y < ylo + 0.94 * (yhi - ylo))
        px = _pixels(fig, x[keep], y[keep])[::8]
        others = [_pixels(fig, o.get_xdata(), o.get_ydata()) for o in refs if o is not ref]
        hits = total = 0
        for col, row in px:
            if legend.contains(col, height - row):
                continue
            if any(np.min(np.hypot(o[:, 0] - col, o[:, 1] - row)) < 6 for o in others):
                continue
            total += 1
            hits += _colour_near(img, col, row, _bgr(str(ref.get_color())), 3)
        assert total >= 5, f"{ref.get_gid()}: too few points to check"
        assert hits >= 0.8 * total, f"{ref.get_gid()}: visible at {hits} of {total} points"


def _threshold_visible(fig: Figure, img: np.ndarray) -> None:
    """The threshold's dark grey dots are on screen along its line, and none is red."""
    ax = fig.axes[0]
    (thr,) = [ln for ln in ax.get_lines() if ln.get_gid() == "threshold"]
    level = float(np.asarray(thr.get_ydata())[0])
    xs = np.linspace(*ax.get_xlim(), 60)[2:-2]
    px = _pixels(fig, xs, np.full(xs.size, level))
    curves = [
        _pixels(fig, ln.get_xdata(), ln.get_ydata()) for ln in ax.get_lines() if ln is not thr
    ]
    grey, red = _bgr(r.THRESHOLD_COLOUR), _bgr("#d62728")
    hits = total = 0
    for col, row in px:
        if any(np.min(np.hypot(c[:, 0] - col, c[:, 1] - row)) < 8 for c in curves if len(c)):
            continue
        total += 1
        hits += _colour_near(img, col, row, grey, 3)
        assert not _colour_near(img, col, row, red, 1), "red on the threshold line"
    assert total >= 10 and hits >= 0.8 * total, f"threshold visible at {hits} of {total}"
