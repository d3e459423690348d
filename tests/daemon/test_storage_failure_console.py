"""What the operator reads when storing fails mid-run (issue 16): the session video's muxer
fails (PyAV raises ``av.ExternalError`` from FFmpeg, injected into the real recorder's
write on the 20th frame of an MJPG scene). The run stops as a ``fault``: one error line on
stderr naming the video, and the console says the measurement *stopped* because storing
failed - not "aborted", which is the word for Ctrl-C - and where the recording is."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import av
import pytest

from stipi_daemon.cli import main
from tests.daemon._support import short_config


def test_a_video_failure_says_stopped_not_aborted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from stipi_daemon.storage import video as video_module

    # an MJPG camera: passthrough, muxed in the capture thread
    config = short_config(tmp_path, {}, pixel_format="mjpg", speed=0.0)
    write, calls = video_module.write_video_frame, [0]

    def failing_at_the_20th(*args: Any, **kwargs: Any) -> None:
        calls[0] += 1
        if calls[0] == 20:
            raise av.ExternalError(-1, "injected muxer failure")  # type: ignore[call-arg]
        write(*args, **kwargs)

    monkeypatch.setattr(video_module, "write_video_frame", failing_at_the_20th)
    capsys.readouterr()
    assert main(["--config", str(config)]) != 0
    out, err = capsys.readouterr()
    (session,) = (tmp_path / "sessions").iterdir()
    ours = [line for line in err.splitlines() if line.startswith("stipi-daemon: error:")]
    assert len(ours) == 1 and "the session video could not be written" in ours[0], err
    assert "measurement aborted" not in out
    assert f"measurement stopped: storing failed; what was recorded is in {session}" in out
    assert f"stipi-daemon analyze {session}" in out  # what to do with it
    assert json.loads((session / "summary.json").read_text())["status"] == "fault"
