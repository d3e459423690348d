"""The CLI as a process, when its output is closed or it is told to stop.

* What reads its output stops reading (``stipi-daemon ... | head``): a measurement goes on
  without its console - the data is the session's, not the console's, and a probe held on
  a patient is not started again because a pipe closed - and says so once on stderr. Any
  other command stops quietly with the shell's status for SIGPIPE (141), no traceback.
* SIGTERM (``kill PID``, a service manager's stop) ends a measurement as Ctrl-C does: the
  session finished ``aborted`` and whole, one line, the shell's status for SIGTERM (143).
  Without it the process died with the session left unfinished and locked.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

from stipi_daemon.storage import SessionReader
from tests.daemon._support import short_config


def _run_with_stdout_closed(argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """Run the CLI with its stdout a pipe whose reading end is already closed."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run(
            [sys.executable, "-m", "stipi_daemon", *argv],
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            cwd=cwd,
        )
    finally:
        os.close(write_end)


def test_a_measurement_goes_on_when_its_output_is_closed(tmp_path: Path) -> None:
    config = short_config(tmp_path, {}, speed=4.0)
    proc = _run_with_stdout_closed(["--config", str(config)], tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    warning = (
        "stipi-daemon: warning: the console's output was closed: the measurement goes on "
        "without it, its results are written to the session\n"
    )
    assert proc.stderr.count(warning) == 1, proc.stderr
    (session,) = (tmp_path / "sessions").iterdir()
    summary = json.loads((session / "summary.json").read_text())
    assert summary["status"] == "complete"
    assert summary["verdict"]["status"] == "complete", summary["verdict"]
    assert (session / "report" / "report.html").is_file()


def test_another_command_stops_quietly_when_its_output_is_closed(tmp_path: Path) -> None:
    (tmp_path / "sessions").mkdir()
    proc = _run_with_stdout_closed(
        ["sessions", "list", "--root", str(tmp_path / "sessions")], tmp_path
    )
    assert (proc.returncode, proc.stderr) == (141, "")
    # argparse's own output (--help, --version) ignores a closed output and exits 0
    proc = _run_with_stdout_closed(["--help"], tmp_path)
    assert (proc.returncode, proc.stderr) == (0, "")


def test_sigterm_ends_a_measurement_as_ctrl_c_does(tmp_path: Path) -> None:
    config = short_config(tmp_path, {}, speed=1.0)
    proc = subprocess.Popen(
        [sys.executable, "-m", "stipi_daemon", "--config", str(config)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert proc.stdout is not None
        for line in proc.stdout:  # recording: the stream is up and the operator was asked
            if "idle -> armed" in line:
                break
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err == "stipi-daemon: terminated (SIGTERM)\n"
    assert "measurement aborted; what was recorded is in" in out
    (session,) = (tmp_path / "sessions").iterdir()
    assert json.loads((session / "summary.json").read_text())["status"] == "aborted"
    assert not (session / "writer.lock").exists()
    with SessionReader(session) as reader:
        assert reader.integrity_check().ok
