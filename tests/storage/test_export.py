from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import TABLES, SessionReader, export_session
from stipi_daemon.storage.schema import Table
from tests.storage.conftest import SUMMARY, Recorded


def _parse_csv_value(kind: str, text: str) -> Any:
    if kind == "int":
        return int(text)
    if kind in ("real", "real_null"):
        return math.nan if text == "" else float(text)
    return text


def read_csv_table(path: Path, table: Table) -> list[tuple[Any, ...]]:
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == table.column_names
    kinds = [c.kind for c in table.columns]
    return [
        tuple(_parse_csv_value(k, v) for k, v in zip(kinds, row, strict=True)) for row in rows[1:]
    ]


def read_parquet_table(path: Path, table: Table) -> list[tuple[Any, ...]]:
    data = pq.read_table(path)
    assert tuple(data.column_names) == table.column_names
    assert (
        data.schema.field(table.column_names[0]).metadata[b"unit"] == table.columns[0].unit.encode()
    )
    columns = [data.column(name).to_pylist() for name in table.column_names]
    kinds = [c.kind for c in table.columns]
    return [
        tuple(
            math.nan if (v is None and k == "real_null") else v
            for k, v in zip(kinds, row, strict=True)
        )
        for row in zip(*columns, strict=True)
    ]


def assert_equal_to_reader(
    reader: SessionReader, table: Table, rows: list[tuple[Any, ...]]
) -> None:
    expected = reader.array(table).tolist()
    assert len(rows) == len(expected) > 0
    for got, want in zip(rows, expected, strict=True):
        for g, w in zip(got, want, strict=True):
            if isinstance(w, float):
                np.testing.assert_equal(g, w)  # exact, NaN equal to NaN
            else:
                assert g == w


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_reads_back_equal(recorded: Recorded, tmp_path: Path, fmt: str) -> None:
    out = tmp_path / "export"
    with SessionReader(recorded.directory) as reader:
        written = export_session(reader, out, fmt)  # type: ignore[arg-type]
        assert [p.name for p in written] == [f"{t.name}.{fmt}" for t in TABLES] + [
            f"validity.{fmt}",
            f"session.{fmt}",
            "manifest.json",
            "summary.json",
            "video.mkv",
        ]
        assert (out / "video.mkv").read_bytes() == (reader.directory / "video.mkv").read_bytes()
        read = read_csv_table if fmt == "csv" else read_parquet_table
        for table in TABLES:
            assert_equal_to_reader(reader, table, read(out / f"{table.name}.{fmt}", table))
    assert json.loads((out / "summary.json").read_text()) == SUMMARY
    # Events keep their JSON detail verbatim.
    events = read(out / f"events.{fmt}", TABLES[2])
    assert json.loads(events[0][2]) == {"supply_mv": 4100, "flags": [1, 0]}


def test_export_refuses_to_overwrite(recorded: Recorded, tmp_path: Path) -> None:
    with SessionReader(recorded.directory) as reader:
        export_session(reader, tmp_path, "csv")
        with pytest.raises(SessionError, match=r"force_samples\.csv: exists already"):
            export_session(reader, tmp_path, "csv")
        export_session(reader, tmp_path, "csv", overwrite=True)
        with pytest.raises(SessionError, match="export format 'xlsx'"):
            export_session(reader, tmp_path, "xlsx")  # type: ignore[arg-type]


def test_export_of_an_empty_session(tmp_path: Path) -> None:
    from stipi_daemon.storage import SessionWriter, StorageOptions

    options = StorageOptions(min_free_bytes=0)
    with SessionWriter.create(tmp_path / "sessions", {}, {}, session_id="e", options=options) as w:
        w.finish("aborted")
    with SessionReader(tmp_path / "sessions" / "e") as reader:
        export_session(reader, tmp_path / "csv", "csv")
        export_session(reader, tmp_path / "parquet", "parquet")
    assert (tmp_path / "csv" / "frames.csv").read_text() == (
        "seq,t_capture_host_s,t_host_s,s_k,flags\n"
    )
    assert pq.read_table(tmp_path / "parquet" / "frames.parquet").num_rows == 0


_VALID_SUMMARY = {
    "status": "complete",
    "results": {
        "pitting": {"depth_mm": 3.5, "rebound_force_n": 7.25, "recovery_time_s": 27.5},
        "paper_estimator": {"elasticity_kpa": 356.0, "viscosity_n_s_per_mm2": 9.8},
        "severity": {"paper_estimator": {"severity": "moderate", "nearest_grade": "2+"}},
        "fitted_recovery": {"tau_s": 12.0},
        "applied_force_n": 16.0,
    },
    "validity": {
        "depth_mm": {"status": "invalid", "flags": ["release_not_observed"], "reason": "gap"},
        "rebound_force_n": {"status": "flagged", "flags": ["a", "b"], "reason": "caveat"},
    },
    "verdict": {"status": "invalid", "line": "Not valid: D_p (gap)."},
}


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_carries_the_validity_of_each_quantity(tmp_path: Path, fmt: str) -> None:
    from stipi_daemon.storage import SessionWriter, StorageOptions

    options = StorageOptions(min_free_bytes=0)
    with SessionWriter.create(tmp_path / "sessions", {}, {}, session_id="v", options=options) as w:
        w.finish("complete", _VALID_SUMMARY)
    with SessionReader(tmp_path / "sessions" / "v") as reader:
        export_session(reader, tmp_path / "out", fmt)  # type: ignore[arg-type]
    path = tmp_path / "out" / f"validity.{fmt}"
    if fmt == "csv":
        import csv

        with open(path, encoding="utf-8") as f:
            rows = {r["quantity"]: r for r in csv.DictReader(f)}
        value = float(rows["depth_mm"]["value"])
    else:
        table = pq.read_table(path).to_pylist()
        rows = {r["quantity"]: r for r in table}
        value = rows["depth_mm"]["value"]
    assert value == 3.5
    assert rows["depth_mm"]["status"] == "invalid"
    assert rows["depth_mm"]["reason"] == "gap"
    assert rows["rebound_force_n"]["status"] == "flagged"
    assert rows["rebound_force_n"]["flags"] == "a;b"
    assert rows["recovery_time_s"]["status"] == "unknown"
    assert rows["severity"]["label"] == "moderate"
    assert rows["verdict"]["status"] == "invalid"
    assert rows["verdict"]["reason"] == "Not valid: D_p (gap)."
