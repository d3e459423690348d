"""``export_session`` and the session's video: carried by every format, byte for byte
(hashlib); a session failing its integrity check (a cut-off video, counted by PyAV) is
not exported unless asked, and then carries its problems."""

from __future__ import annotations

import hashlib
from pathlib import Path

import av
import numpy as np
import pytest
import scipy.io

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, export_session
from tests.storage.conftest import Recorded, write_full_session


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _cut_last_frame(video: Path) -> None:
    """Truncate ``video`` where its last frame's packet starts (PyAV names the place)."""
    with av.open(str(video)) as container:
        positions = [p.pos for p in container.demux(video=0) if p.size]
    assert len(positions) >= 2
    with open(video, "r+b") as f:
        f.truncate(positions[-1])
    with av.open(str(video)) as container:
        assert sum(1 for p in container.demux(video=0) if p.size) == len(positions) - 1


def test_mat_export_carries_the_video_beside_it(recorded: Recorded, tmp_path: Path) -> None:
    out = tmp_path / "mat"
    video = recorded.directory / "video.mkv"
    with SessionReader(recorded.directory) as reader:
        written = export_session(reader, out, "mat")
    mat, mkv = out / f"{recorded.session_id}.mat", out / f"{recorded.session_id}.mkv"
    assert written == [mat, mkv]
    assert _sha256(mkv) == _sha256(video)
    data = scipy.io.loadmat(mat, simplify_cells=True)
    assert data["video_file"] == mkv.name
    assert len(data["integrity_problems"]) == 0
    # Again into the same place: the identical video is no conflict, the .mat is.
    with SessionReader(recorded.directory) as reader:
        with pytest.raises(SessionError, match=r"\.mat: exists already"):
            export_session(reader, out, "mat")
        assert export_session(reader, out, "mat", overwrite=True) == [mat, mkv]


def test_mat_export_of_a_session_without_video_names_none(tmp_path: Path) -> None:
    from stipi_daemon.storage import SessionWriter, StorageOptions

    options = StorageOptions(min_free_bytes=0)
    with SessionWriter.create(tmp_path / "sessions", {}, {}, session_id="n", options=options) as w:
        w.finish("complete")
    with SessionReader(tmp_path / "sessions" / "n") as reader:
        assert export_session(reader, tmp_path / "out", "mat") == [tmp_path / "out" / "n.mat"]
    data = scipy.io.loadmat(tmp_path / "out" / "n.mat", simplify_cells=True)
    assert np.size(data["video_file"]) == 0  # MATLAB's '' (loadmat: an empty array)


@pytest.mark.parametrize("fmt", ["csv", "mat"])
def test_damaged_session_is_exported_only_when_allowed(tmp_path: Path, fmt: str) -> None:
    recorded = write_full_session(tmp_path / "sessions")
    video = recorded.directory / "video.mkv"
    _cut_last_frame(video)
    damaged = _sha256(video)
    out = tmp_path / "out"
    with SessionReader(recorded.directory) as reader:
        with pytest.raises(SessionError) as refused:
            export_session(reader, out, fmt)  # type: ignore[arg-type]
        line = str(refused.value)
        assert "\n" not in line and "integrity check failed" in line
        assert f"{video}: " in line  # the video's problem, at its place
        assert "--allow-damaged" in line
        assert not out.exists()  # nothing written
        written = export_session(reader, out, fmt, allow_damaged=True)  # type: ignore[arg-type]
    if fmt == "csv":
        assert written[-2:] == [out / "video.mkv", out / "integrity.txt"]
        assert _sha256(out / "video.mkv") == damaged
        assert f"{video}: " in (out / "integrity.txt").read_text()
    else:
        mkv = out / f"{recorded.session_id}.mkv"
        assert written[-1] == mkv and _sha256(mkv) == damaged
        data = scipy.io.loadmat(out / f"{recorded.session_id}.mat", simplify_cells=True)
        problems = data["integrity_problems"]
        problems = [problems] if isinstance(problems, str) else list(problems)
        assert any(f"{video}: " in p for p in problems)
