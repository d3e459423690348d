"""docs/study.md documents every column of the dataset, and the query benchmark runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from stipi_daemon.study.dataset import TABLE_COLUMNS

ROOT = Path(__file__).resolve().parents[2]


def test_every_column_is_documented_with_its_unit() -> None:
    text = (ROOT / "docs" / "study.md").read_text(encoding="utf-8")
    for table, columns in TABLE_COLUMNS.items():
        section = text[text.index(f"### {table}\n") :]
        section = section[: section.find("\n### ", 1) if "\n### " in section[1:] else None]
        for c in columns:
            assert f"| `{c.name}` |" in section, (table, c.name)
            row = section[section.index(f"| `{c.name}` |") :].splitlines()[0]
            assert f"| {c.unit or '-'} |" in row, (table, c.name, c.unit)


def test_query_benchmark_quick_writes_its_section_and_keeps_others(tmp_path: Path) -> None:
    out = tmp_path / "study.md"
    out.write_text("# Studies\n\n## Schema\n\nkept\n\n## Query benchmark\n\nold\n")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "study_query.py"), "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=110,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert "## Schema\n\nkept\n" in text and "\nold\n" not in text
    assert text.count("## Query benchmark") == 1
    assert "1,000,000 force-sample rows in 100 session files" in text
    assert "all three gave the same groups, counts, maxima and means" in text
