"""Smoke test of benchmarks/study_reanalyze.py in its --quick mode: it runs and writes its
block of the docs between the markers, keeping the rest. The numbers are not checked:
timings belong in docs/, not in tests."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.xdist_group("realtime")
def test_quick_run_writes_its_block_and_keeps_the_rest(tmp_path: Path) -> None:
    out = tmp_path / "study.md"
    start, end = "<!-- reanalyze-benchmark:start -->", "<!-- reanalyze-benchmark:end -->"
    out.write_text(f"# Studies\n\nkept before\n\n{start}\nold\n{end}\n\nkept after\n")
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "study_reanalyze.py"),
            "--quick",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=580,
        check=False,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    text = out.read_text()
    assert "kept before" in text and "kept after" in text and "\nold\n" not in text
    assert text.count(start) == 1 and text.count(end) == 1
    for row in ("| serial |", "| 1 worker |", "| 2 workers |", "| 32 |"):
        assert row in text
    assert "Speed-up at 2 workers, steady:" in text and "serial part s =" in text
    assert "plain spawned processes" in text and "pure-Python loop" in text
