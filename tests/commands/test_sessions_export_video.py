"""``sessions export``/``show``: the video in a MATLAB export, damaged sessions, and a
session directory given by its bare name."""

from __future__ import annotations

import hashlib
from pathlib import Path

import av
import pytest

from stipi_daemon.cli import main
from stipi_daemon.errors import EXIT_DAMAGED
from tests.storage.conftest import write_full_session


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture
def root(tmp_path: Path) -> Path:
    root = tmp_path / "sessions"
    write_full_session(root, "a-complete")
    damaged = write_full_session(root, "d-damaged").directory / "video.mkv"
    with av.open(str(damaged)) as container:  # PyAV names where the last frame starts
        last = [p.pos for p in container.demux(video=0) if p.size][-1]
    with open(damaged, "r+b") as f:
        f.truncate(last)
    return root


def test_mat_export_prints_and_writes_the_video(
    root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    args = ["sessions", "export", "a-complete", "--root", str(root), "--format", "mat"]
    assert main([*args, "--out", str(out)]) == 0
    assert capsys.readouterr().out.splitlines() == [
        str(out / "a-complete.mat"),
        str(out / "a-complete.mkv"),
    ]
    assert _sha256(out / "a-complete.mkv") == _sha256(root / "a-complete" / "video.mkv")


@pytest.mark.parametrize("fmt", ["csv", "mat"])
def test_damaged_session_needs_allow_damaged(
    root: Path, tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    args = ["sessions", "export", "d-damaged", "--root", str(root), "--format", fmt]
    assert main([*args, "--out", str(out)]) == EXIT_DAMAGED
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1
    assert "integrity check failed" in captured.err and "--allow-damaged" in captured.err
    assert f"{root / 'd-damaged' / 'video.mkv'}: " in captured.err  # the problem's place
    assert not out.exists()
    assert main([*args, "--out", str(out), "--allow-damaged"]) == 0
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith("stipi-daemon: warning:")
    assert "exported as it is" in captured.err
    video = out / ("video.mkv" if fmt == "csv" else "d-damaged.mkv")
    assert str(video) in captured.out.splitlines()
    assert _sha256(video) == _sha256(root / "d-damaged" / "video.mkv")


def test_show_and_export_take_a_bare_directory_name(
    root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # A session directory outside the sessions root, named bare from its parent directory.
    write_full_session(tmp_path / "elsewhere", "copy")
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert main(["sessions", "show", "copy", "--root", str(root)]) == 0
    assert "session    copy" in capsys.readouterr().out
    out = tmp_path / "out"
    argv = ["sessions", "export", "copy", "--root", str(root), "--out", str(out), "--format", "mat"]
    assert main(argv) == 0
    assert capsys.readouterr().out.splitlines()[0] == str(out / "copy.mat")
    # The id lookup still works (and comes first) ...
    assert main(["sessions", "show", "a-complete", "--root", str(root)]) == 0
    assert "session    a-complete" in capsys.readouterr().out
    # ... and a name that is neither says where it looked, in one line.
    assert main(["sessions", "show", "garbage", "--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no such session" in err
    assert str(root / "garbage") in err and str(tmp_path / "elsewhere" / "garbage") in err
