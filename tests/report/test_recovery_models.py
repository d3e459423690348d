"""The report's recovery models, from a session the daemon recorded on a tissue that is not
Kelvin-Voigt (the two-time-constant scene): the table's numbers are summary.json's rounded by
the one rule, each drawn curve is the model's function at the drawn times (and, with the
data, gives back the fit's recorded residual sum of squares), the figure shows every curve
in Chromium, the command prints the same table, older summaries say in one line that they
have none, and the comparison names each session's best model."""

from __future__ import annotations

import html
import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from stipi_daemon.analysis.flags import FLAG_DESCRIPTIONS, Flag
from stipi_daemon.analysis.recovery_models import MODELS
from stipi_daemon.cli import main
from stipi_daemon.report import render as r
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.numbers import value_text
from stipi_daemon.report.recovery_models import (
    INTERVAL_QUANTITIES,
    recovery_models_figure,
    recovery_models_view,
)
from stipi_daemon.report.write import render_session_report, write_compare_report
from tests.report.test_lab_report import _bgr, _colour_near, _figures_in_chromium, _pixels


@pytest.fixture(scope="module")
def prony(prony_session: Path) -> ReportInput:
    return load_report_input(prony_session)


def _models(inp: ReportInput) -> Mapping[str, Any]:
    rm = (inp.results or {})["recovery_models"]
    assert isinstance(rm, Mapping)
    return rm


def _with_results(inp: ReportInput, **changes: Any) -> ReportInput:
    """A copy of ``inp`` whose results have ``changes`` (a value None: the key removed)."""
    summary = json.loads(json.dumps(inp.summary))
    for k, v in changes.items():
        if v is None:
            summary["results"].pop(k, None)
        else:
            summary["results"][k] = v
    return ReportInput(**{**inp.__dict__, "summary": summary})


def _four_significant(text: str, value: float) -> None:
    """``text`` is ``value`` to 4 significant figures (the rule for a value without an
    uncertainty), checked from the number itself, not by the report's function."""
    shown = float(text)
    if value == 0.0:
        assert shown == 0.0
        return
    step = 10.0 ** (math.floor(math.log10(abs(value))) - 3)
    assert abs(shown - value) <= 0.5 * step * (1 + 1e-9), (text, value)
    digits = text.lstrip("-").replace(".", "").lstrip("0")
    assert len(digits) <= 4 or float(text).is_integer(), (text, value)


def test_the_scene_is_not_kelvin_voigt_and_the_summary_says_so(prony: ReportInput) -> None:
    rm = _models(prony)
    assert rm["kelvin_voigt_rejected"] is True and rm["best_model"] == "two_exponential"
    assert set(rm["models"]) == set(MODELS)


def test_table_values_are_the_summary_rounded_by_the_rule(
    prony: ReportInput, tmp_path: Path
) -> None:
    rm = _models(prony)
    view = recovery_models_view(prony.results)
    assert view is not None
    assert [row.name for row in view.rows] == list(rm["models"])
    for row in view.rows:
        entry = rm["models"][row.name]
        assert row.best == (row.name == rm["best_model"])
        for key, text in (
            ("akaike_weight", row.akaike_weight),
            ("qaicc_weight", row.qaicc_weight),
            ("delta_qaicc", row.delta_qaicc),
        ):
            assert text == value_text(entry[key])
            _four_significant(text, entry[key])
        for key in INTERVAL_QUANTITIES:
            assert row.values[key] == value_text(entry[key])
            _four_significant(row.values[key], entry[key])
            lo, hi = entry["ci95"][key]
            assert row.intervals[key] == f"[{value_text(lo)}, {value_text(hi)}]"
            _four_significant(value_text(lo), lo)
            _four_significant(value_text(hi), hi)
        assert row.tau_meaning == entry["tau_meaning"]
    assert view.kelvin_voigt_rejected
    assert view.flag_text == FLAG_DESCRIPTIONS[Flag.KELVIN_VOIGT_REJECTED]
    assert rm["kelvin_voigt_rejection_rule"] in view.rejection_line
    assert value_text(rm["kelvin_voigt_delta_qaicc"]) in view.rejection_line

    # The page's table holds exactly these cells, one row per model, the best marked.
    written = render_session_report(prony, tmp_path / "rep")
    page = written.html_path.read_text(encoding="utf-8")
    for row in view.rows:
        m = re.search(rf'<tr data-model="{row.name}"( class="best")?>(.*?)</tr>', page)
        assert m is not None, row.name
        assert bool(m.group(1)) == row.best
        cells = [html.unescape(c) for c in re.findall(r'<td class="num">(.*?)</td>', m.group(2))]
        assert cells[:3] == [row.akaike_weight, row.qaicc_weight, row.delta_qaicc]
        shown = [c.replace('<span class="ci">', " ").replace("</span>", "") for c in cells[3:]]
        assert shown == [f"{row.values[k]} {row.intervals[k]}" for k in INTERVAL_QUANTITIES]
        assert html.escape(row.tau_meaning) in m.group(2)
    assert 'id="kv-rejection"' in page and "kelvin_voigt_rejected</span>" in page
    assert html.escape(view.flag_text) in page
    # ... and the figure sits on the page, the table after it.
    assert page.index('id="fig-recovery_models"') < page.index('id="recovery-models"')


def test_the_report_command_prints_the_same_table(
    prony_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["report", str(prony_session), "--out", str(tmp_path / "rep")]) == 0
    out = capsys.readouterr().out
    inp = load_report_input(prony_session)
    view = recovery_models_view(inp.results)
    assert view is not None
    for row in view.rows:
        head = next(ln for ln in out.splitlines() if f" {row.short_name}: Akaike" in ln)
        assert head.startswith(" * " if row.best else "   ")
        assert f"Akaike weight {row.akaike_weight}, QAICc weight {row.qaicc_weight}" in head
        for key, (sym, unit) in INTERVAL_QUANTITIES.items():
            assert f"{sym} = {row.values[key]} {row.intervals[key]} {unit}" in out
    assert view.rejection_line in out
    assert FLAG_DESCRIPTIONS[Flag.KELVIN_VOIGT_REJECTED] in out


def _spec_g(name: str, x: np.ndarray, p: Mapping[str, float]) -> np.ndarray:
    """g(x) as docs/analysis.md's table "Recovery models, model selection and intervals"
    writes it (not the models' code)."""
    if name == "kelvin_voigt":
        return np.exp(-x / p["tau_s"])
    if name == "two_exponential":
        w = p["weight_fast"]
        return w * np.exp(-x / p["tau_fast_s"]) + (1 - w) * np.exp(-x / p["tau_slow_s"])
    assert name == "power_law"
    n = p["exponent_n"]
    return (1 + x / (n * p["tau_s"])) ** -n


def test_each_curve_drawn_is_its_model_at_the_drawn_times(prony: ReportInput) -> None:
    rm = _models(prony)
    data = recovery_models_figure(prony)
    assert data is not None
    fig = r.draw_recovery_models(data)
    ax = fig.axes[0]
    lines = {str(ln.get_gid()): ln for ln in ax.get_lines()}
    t0 = (prony.results or {})["pitting"]["t0_s"]
    assert data.t_since_t0_s.size == rm["n_points"]  # the fitted frames, outliers left out
    (pts,) = [lines["models_data"]]
    for name, entry in rm["models"].items():
        line = lines[f"model_{name}"]
        x = np.asarray(line.get_xdata(), dtype=float)
        y = np.asarray(line.get_ydata(), dtype=float)
        np.testing.assert_array_equal(x, pts.get_xdata())
        p = entry["parameters"]
        shape = {k: v for k, v in p.items() if k not in ("offset_px", "amplitude_px")}
        model = MODELS[name].curve(
            x + t0, t0, offset=p["offset_px"], amplitude=p["amplitude_px"], **shape
        )
        np.testing.assert_allclose(y, model, rtol=1e-12, atol=1e-9)
        spec = p["offset_px"] - p["amplitude_px"] * _spec_g(name, x, p)
        np.testing.assert_allclose(y, spec, rtol=1e-9, atol=1e-6)
        # The data drawn minus the curve drawn is the fit's recorded residual sum of squares.
        rss = float(np.sum((np.asarray(pts.get_ydata(), dtype=float) - y) ** 2))
        assert rss == pytest.approx(entry["rss_px2"], rel=1e-6), name
        residual = lines.get(f"model_residual_{name}") or next(
            ln for ln in fig.axes[1].get_lines() if ln.get_gid() == f"model_residual_{name}"
        )
        np.testing.assert_allclose(residual.get_ydata(), np.asarray(pts.get_ydata()) - y)
    labels = ax.get_legend_handles_labels()[1]
    view = recovery_models_view(prony.results)
    assert view is not None
    for row in view.rows:
        label = next(lb for lb in labels if lb.startswith(row.short_name))
        assert f"Akaike w = {row.akaike_weight}" in label
        assert f"QAICc w = {row.qaicc_weight}" in label
        assert ("(best)" in label) == row.best
    styles = {
        (ln.get_color(), str(ln.get_linestyle()))
        for n, ln in lines.items()
        if n.startswith("model_")
    }
    assert len(styles) == len(rm["models"]), "every model has its own colour and dashes"


def test_the_figure_shows_every_curve_in_chromium(prony: ReportInput, tmp_path: Path) -> None:
    written = render_session_report(prony, tmp_path / "rep")
    assert "recovery_models" in written.figures
    data = recovery_models_figure(prony)
    assert data is not None
    fig = r.draw_recovery_models(data)
    assert r.png_bytes(fig) == written.figures["recovery_models"].read_bytes()
    shots = _figures_in_chromium(written.html_path.read_text(encoding="utf-8"), tmp_path)
    img = shots["recovery_models"]
    ax = fig.axes[0]
    legend = ax.get_legend().get_window_extent()
    height = fig.get_size_inches()[1] * fig.dpi
    for line in ax.get_lines():
        gid = str(line.get_gid())
        if not gid.startswith("model_"):
            continue
        x, y = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
        idx = np.linspace(0, x.size - 1, 60).astype(int)
        px = _pixels(fig, x[idx], y[idx])
        keep = [i for i, (c, rr) in enumerate(px) if not legend.contains(c, height - rr)]
        seen = sum(_colour_near(img, *px[i], _bgr(str(line.get_color())), 3) for i in keep)
        assert seen >= 0.6 * len(keep), f"{gid}: its colour at {seen} of {len(keep)} points"


def test_a_summary_without_recovery_models_says_so_in_one_line(
    prony: ReportInput, tmp_path: Path
) -> None:
    old = _with_results(prony, recovery_models=None)
    written = render_session_report(old, tmp_path / "rep")
    page = written.html_path.read_text(encoding="utf-8")
    assert "recovery_models" not in written.figures and "recovery_models" not in written.missing
    assert 'id="recovery-models-table"' not in page and "fig-recovery_models" not in page
    assert written.recovery_models.count("\n") == 0
    assert "not in this session's summary" in written.recovery_models
    assert html.escape(written.recovery_models) in page
    # A comparison the analysis refused: the reason from its note.
    refused = _with_results(prony, recovery_models=None)
    assert refused.summary is not None
    refused.summary["results"]["recovery_models"] = None
    refused.summary["results"]["notes"] = ["recovery models not compared: 3 samples after T_0"]
    written = render_session_report(refused, tmp_path / "rep2")
    assert written.recovery_models == "Recovery models: not compared: 3 samples after T_0."


def test_missing_intervals_and_parameters_say_why(prony: ReportInput) -> None:
    rm = json.loads(json.dumps(_models(prony)))
    pl = rm["models"]["power_law"]
    pl["ci95"] = dict.fromkeys(pl["ci95"])
    pl["flags"] = ["no_confidence_intervals"]
    kv = rm["models"]["kelvin_voigt"]
    kv["rebound_force_n"] = None
    kv["ci95"]["rebound_force_n"] = None
    kv["ci95"]["tau_s"] = None  # a value without its interval, bootstrap run: unbounded
    te = rm["models"]["two_exponential"]
    te["parameters"]["weight_fast"] = 1.5  # outside the model's bounds: not drawn, said why
    inp = _with_results(prony, recovery_models=rm)
    view = recovery_models_view(inp.results)
    assert view is not None
    rows = {row.name: row for row in view.rows}
    assert rows["power_law"].intervals["tau_s"].startswith("n/a (not computed: fewer than 12")
    assert rows["kelvin_voigt"].values["rebound_force_n"] == "-"
    assert rows["kelvin_voigt"].intervals["rebound_force_n"] == "n/a (no value)"
    assert rows["kelvin_voigt"].intervals["tau_s"].startswith("n/a (unbounded")
    data = recovery_models_figure(inp)
    assert data is not None
    curves = {c.name: c for c in data.curves}
    assert curves["two_exponential"].model_px.size == 0
    assert "weight_fast" in curves["two_exponential"].not_drawn
    assert "not drawn" in curves["two_exponential"].label
    assert curves["kelvin_voigt"].model_px.size == data.t_since_t0_s.size
    r.draw_recovery_models(data)  # draws the others


def test_compare_names_each_sessions_best_model(
    prony_session: Path, demo_session: Path, tmp_path: Path
) -> None:
    written = write_compare_report([prony_session, demo_session], tmp_path / "cmp")
    page = written.html_path.read_text(encoding="utf-8")
    assert "Best recovery model; Kelvin-Voigt" in page
    for session in (prony_session, demo_session):
        inp = load_report_input(session)
        rm = _models(inp)
        m = re.search(rf'<td data-recovery-model="{inp.session_id}">(.*?)</td>', page)
        assert m is not None
        decision = (
            "kelvin_voigt_rejected" if rm["kelvin_voigt_rejected"] else "Kelvin-Voigt not rejected"
        )
        assert html.unescape(m.group(1)) == f"{rm['best_model']}; {decision}"
    assert re.search(r'data-recovery-model="[^"]+">two_exponential; kelvin_voigt_rejected<', page)
