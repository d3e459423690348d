"""``stipi-daemon report``: a session's report, a comparison, and clear one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.report.write import COMPARE_FIGURES, REPORT_HTML, SESSION_FIGURES
from stipi_daemon.storage import SessionWriter, StorageOptions
from tests._report_sessions import recorded_session


@pytest.fixture(scope="module")
def demo_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return recorded_session(tmp_path_factory, "grade1")


@pytest.fixture(scope="module")
def second_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return recorded_session(tmp_path_factory, "grade2")


def test_report_session_by_path_and_by_id(
    demo_session: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "rep"
    assert main(["report", str(demo_session), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"report: {out / REPORT_HTML}" in text
    assert f"figures: {len(SESSION_FIGURES)} PNG(s)" in text
    assert "\nverdict: " in text  # the verdict the page shows, e.g. "complete: Complete: ..."
    assert sorted(p.stem for p in out.glob("*.png")) == sorted(SESSION_FIGURES)
    out2 = tmp_path / "rep2"
    args = ["report", demo_session.name, "--root", str(demo_session.parent), "--out", str(out2)]
    assert main(args) == 0
    assert (out2 / REPORT_HTML).is_file()


def test_report_compare(
    demo_session: Path,
    second_session: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "cmp"
    args = ["report", "--compare", str(demo_session), str(second_session), "--out", str(out)]
    assert main([*args, "--labels", "I", "II"]) == 0
    assert f"figures: {len(COMPARE_FIGURES)} PNG(s)" in capsys.readouterr().out
    page = (out / REPORT_HTML).read_text(encoding="utf-8")
    assert "<td>I</td>" in page and "<td>II</td>" in page


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["report"], "nothing to report"),
        (["report", "x", "--compare", "a", "b"], "not both"),
        (["report", "--compare", "a"], "at least two sessions"),
        (["report", "--compare", "a", "b", "--labels", "I"], "1 labels for 2 sessions"),
        (["report", "x", "--labels", "I"], "--labels applies to --compare"),
        (["report", "no-such-session", "--root", "/nonexistent"], "no such session"),
    ],
)
def test_report_errors_are_one_line(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_a_session_still_recording_is_reported_only_outside_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The directory of a session being recorded is its writer's, and the daemon writes the
    report there as it ends: ``report`` of a live session is one line and exit 2 (nothing
    written into it), or, with ``--out``, the report of what is recorded so far, which says
    why its frames are missing."""
    writer = SessionWriter.create(
        tmp_path / "sessions", {}, {}, session_id="live", options=StorageOptions(min_free_bytes=0)
    )
    try:
        writer.add_force_samples([(i, 0, i, i, i / 100, 1.0) for i in range(200)])
        writer.add_frames([(i, i / 30, i / 30, 1000, "") for i in range(60)])
        writer.commit()
        assert main(["report", str(writer.directory)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "the session is still recording" in err, err
        assert not (writer.directory / "report").exists()
        out = tmp_path / "so-far"
        assert main(["report", str(writer.directory), "--out", str(out)]) == 0
        text = capsys.readouterr().out
        assert "not drawn: frames: the session is still recording" in text, text
        assert (out / REPORT_HTML).is_file()
    finally:
        writer.close()
