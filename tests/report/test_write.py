"""Written reports: every figure file exists and is the one embedded in a self-contained page."""

from __future__ import annotations

import base64
import re
import shutil
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import pytest

from stipi_daemon.app.finish import write_report
from stipi_daemon.errors import AnalysisError
from stipi_daemon.report.numbers import value_text, value_with_uncertainty
from stipi_daemon.report.write import (
    COMPARE_FIGURES,
    REPORT_DIR,
    REPORT_ERROR,
    REPORT_HTML,
    SESSION_FIGURES,
    WrittenReport,
    record_report_failure,
    write_compare_report,
    write_session_report,
)
from stipi_daemon.storage import SessionReader, SessionState
from tests._offline import interrupted_copy

_DATA_URI = re.compile(
    r'src="data:image/png;base64,([A-Za-z0-9+/=]+)" alt="([^"]*)" data-file="([^"]+)"'
)


def _check_png(path: Path) -> np.ndarray:
    """A readable PNG 1000 px wide that is not blank."""
    assert path.is_file() and path.stat().st_size > 10_000, path
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert img is not None, path
    assert img.shape[1] == 1000
    assert float(img.std()) > 10.0, f"{path} looks blank"
    return img


def _embedded(page: str) -> dict[str, bytes]:
    return {m.group(3): base64.b64decode(m.group(1)) for m in _DATA_URI.finditer(page)}


def _self_contained(page: str) -> None:
    assert "<script" not in page
    assert not re.search(r"(src|href)=\"(?!data:|#)", page), "page links to another file"
    assert "http://" not in page and "https://" not in page
    assert "@import" not in page and "url(" not in page


def _complete_page(written: WrittenReport, figures: Mapping[str, str]) -> str:
    """The page of a report with every figure drawn, each file embedded byte for byte."""
    assert written.missing == {}
    assert list(written.figures) == list(figures)
    page = written.html_path.read_text(encoding="utf-8")
    _self_contained(page)
    embedded = _embedded(page)
    for name, path in written.figures.items():
        _check_png(path)
        assert embedded[f"{name}.png"] == path.read_bytes()
    return page


def test_daemon_wrote_the_report_of_every_run(demo_session: Path) -> None:
    out = demo_session / REPORT_DIR
    page = (out / REPORT_HTML).read_text(encoding="utf-8")
    assert set(p.stem for p in out.glob("*.png")) == set(SESSION_FIGURES)
    assert set(_embedded(page)) == {f"{name}.png" for name in SESSION_FIGURES}


def test_session_report_figures_exist_and_are_embedded(demo_session: Path, tmp_path: Path) -> None:
    page = _complete_page(write_session_report(demo_session, tmp_path / "rep"), SESSION_FIGURES)
    with SessionReader(demo_session) as reader:
        summary = reader.summary
        sid = reader.session_id
    assert summary is not None
    res = summary["results"]
    assert sid in page and 'id="status">complete<' in page
    # The table shows the summary's numbers (4 significant digits) and the fit's SE.
    assert f'data-key="depth_mm">{res["pitting"]["depth_mm"]:.4g}<' in page
    tau, tau_se = value_with_uncertainty(
        res["fitted_recovery"]["tau_s"], res["fitted_recovery"]["tau_se_s"]
    )
    assert f'data-key="time_constant_s">{tau}<' in page and f">{tau_se}<" in page
    assert "Ground truth" in page
    sev = res["severity"]["paper_estimator"]
    assert f"{sev['severity']} (nearest grade {sev['nearest_grade']})" in page
    for flag in res["flags"]:
        assert f'<span class="flag">{flag}</span>' in page


def test_report_of_a_session_without_results(demo_session: Path, tmp_path: Path) -> None:
    """An interrupted session: time series drawn, results' figures listed as not drawn."""
    with SessionReader(demo_session) as reader:
        transitions = reader.transitions()
    t_recovery = next(t.t_host_s for t in transitions if t.new_state == "recovery")
    session = interrupted_copy(demo_session, tmp_path / "root", "cut", t_recovery + 0.5)
    stale = session / REPORT_DIR / "recovery_fit.png"
    stale.parent.mkdir()
    stale.write_bytes(b"an earlier report's figure")
    written = write_session_report(session)
    assert not stale.exists()
    assert written.html_path == session / REPORT_DIR / REPORT_HTML
    assert set(written.missing) == {"recovery_fit", "frames"}
    assert {"force", "s_k", "vpr", "vpr_normalised", "window_search"} <= set(written.figures)
    page = written.html_path.read_text(encoding="utf-8")
    assert 'id="status">incomplete<' in page
    assert "the session did not finish (interrupted: no summary.json)" in page
    assert "The session has no results." in page
    assert "Not drawn: the session has no results" in page
    assert "no summary.json" in page
    assert "No results were recorded; stipi-daemon analyze computes what the recording" in page
    with SessionReader(session) as reader:  # the session itself is untouched
        assert reader.status is SessionState.INTERRUPTED
        assert reader.integrity_check().ok


def test_report_failure_is_noted_and_the_session_kept(demo_session: Path, tmp_path: Path) -> None:
    session = tmp_path / "copy"
    shutil.copytree(demo_session, session, ignore=shutil.ignore_patterns(REPORT_DIR))
    (session / REPORT_DIR).write_text("a file where the report directory should be")
    line = write_report(session)
    assert line.startswith("report not written:")
    assert "cannot create report directory" in line
    with SessionReader(session) as reader:
        assert reader.status is SessionState.COMPLETE
        assert reader.integrity_check().ok
    (session / REPORT_DIR).unlink()
    note = record_report_failure(session, RuntimeError("boom"))
    assert note == session / REPORT_DIR / REPORT_ERROR
    assert "RuntimeError: boom" in note.read_text()
    assert write_report(session).startswith("report written to ")


def test_compare_report_tabulates_mean_and_spread(
    demo_session: Path, second_session: Path, tmp_path: Path
) -> None:
    written = write_compare_report(
        [demo_session, second_session, demo_session], tmp_path / "cmp", ["I", "II", "I"]
    )
    page = _complete_page(written, COMPARE_FIGURES)
    depths = []
    for s in (demo_session, second_session):
        with SessionReader(s) as reader:
            summary = reader.summary
        assert summary is not None
        depths.append(summary["results"]["pitting"]["depth_mm"])
    # Group I: two equal trials (SD 0); group II: one session. Grades I and II are never
    # averaged together: there is no column over all sessions.
    assert f"{value_text(depths[0])} ± 0 (0.00 %)" in page
    assert f"{value_text(depths[1])} (n = 1)" in page
    assert '<th data-group="I">I (n = 2)</th>' in page
    assert '<th data-group="II">II (n = 1)</th>' in page
    assert "all sessions" not in page.replace("no mean over all sessions", "")
    # Each session's verdict is shown (the recorded sessions are complete and valid).
    assert page.count('<td class="verdict-cell"><span class="badge badge-complete">') == 3
    assert "label I; ended complete; verdict complete" in page


def test_compare_needs_two_sessions_and_matching_labels(demo_session: Path, tmp_path: Path) -> None:
    with pytest.raises(AnalysisError, match="at least two sessions"):
        write_compare_report([demo_session], tmp_path)
    with pytest.raises(AnalysisError, match="1 labels for 2 sessions"):
        write_compare_report([demo_session, demo_session], tmp_path, ["a"])


def test_an_early_ended_session_shows_the_results_its_recording_allows(
    demo_session: Path, tmp_path: Path
) -> None:
    """An interrupted session analysed by ``analyze``: results shown, verdict incomplete."""
    from stipi_daemon.app.analyze import OUTPUT_FORMAT
    from stipi_daemon.cli import main
    from stipi_daemon.report.load import ANALYSIS_FORMAT

    assert ANALYSIS_FORMAT == OUTPUT_FORMAT
    with SessionReader(demo_session) as reader:
        transitions = reader.transitions()
    t_recovery = next(t.t_host_s for t in transitions if t.new_state == "recovery")
    session = interrupted_copy(demo_session, tmp_path / "root", "cut", t_recovery + 10.0)
    assert main(["analyze", str(session), "--quiet"]) == 0
    (doc,) = session.glob("analysis-*.json")
    (session / "analysis-00000000T000000Z.json").write_text("not json")  # passed over
    written = write_session_report(session)
    page = written.html_path.read_text(encoding="utf-8")
    assert 'id="status">incomplete<' in page
    assert f"Results computed from the recording by stipi-daemon analyze ({doc.name})" in page
    assert f"{doc.name} (stipi-daemon analyze of the recording)" in page
    assert "The session has no results." not in page
    assert 'data-key="depth_mm"' in page and "recovery_fit" in written.figures
    assert written.verdict.startswith("incomplete (the session did not finish (interrupted")
    with SessionReader(session) as reader:  # the recording itself is untouched
        assert reader.status is SessionState.INTERRUPTED
        assert reader.summary is None
