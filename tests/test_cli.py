from __future__ import annotations

import subprocess
import sys

from stipi_daemon import __version__
from stipi_daemon.cli import main


def test_version_flag(capsys: object) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "stipi_daemon", "--version"], capture_output=True, text=True
    )
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"stipi-daemon {__version__}"


def test_help_lists_description() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "stipi_daemon", "--help"], capture_output=True, text=True
    )
    assert proc.returncode == 0
    assert "STIP-I" in proc.stdout


def test_no_arguments_prints_help_and_succeeds() -> None:
    assert main([]) == 0
