from __future__ import annotations

import dataclasses
import enum
import math
import re
import tempfile
from pathlib import Path, PurePosixPath

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.schema import (
    FORCE_SAMPLES,
    FRAMES,
    LIVE_PARAMETERS,
    TABLES,
    coerce_row,
    coerce_rows,
    schema_ddl,
    to_jsonable,
)

DOCS = Path(__file__).resolve().parents[2] / "docs" / "storage.md"


def test_every_column_carries_unit_and_doc() -> None:
    for table in TABLES:
        assert table.doc
        for column in table.columns:
            assert column.unit and column.doc, (table.name, column.name)
            if column.unit == "s":
                assert column.name.endswith("_s")
            if column.unit == "us":
                assert column.name.endswith("_us")


def test_docs_describe_every_table_and_column() -> None:
    text = DOCS.read_text(encoding="utf-8")
    for table in TABLES:
        assert f"### `{table.name}`" in text, table.name
        section = text.split(f"### `{table.name}`", 1)[1].split("###", 1)[0]
        for column in table.columns:
            assert re.search(rf"\| `{column.name}` \|", section), (table.name, column.name)


def test_ddl_creates_the_tables() -> None:
    import sqlite3

    conn = sqlite3.connect(":memory:")
    for statement in schema_ddl():
        conn.execute(statement)
    names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    conn.close()
    assert names == {"meta", *(t.name for t in TABLES)}


def test_coerce_row_normalises_types() -> None:
    row = coerce_row(
        FORCE_SAMPLES, (np.int64(3), np.uint16(1023), 2**32 - 1, 2**40, np.float32(0.5), np.nan)
    )
    assert row == (3, 1023, 2**32 - 1, 2**40, 0.5, None)
    assert all(type(v) in (int, float, type(None)) for v in row)
    assert coerce_row(FRAMES, (1, 1.0, 2.0, 5, [Flag.SATURATED_FRAME, Flag.ROI_CLIPPED])) == (
        1,
        1.0,
        2.0,
        5,
        "saturated_frame,roi_clipped",
    )
    flag_set = frozenset({Flag.ROI_CLIPPED, Flag.EMPTY_ROI, Flag.SATURATED_FRAME})
    assert coerce_row(FRAMES, (1, 1.0, 2.0, 5, flag_set))[4] == (
        "empty_roi,roi_clipped,saturated_frame"
    )
    assert coerce_row(LIVE_PARAMETERS, (1.0, "t_r_s", -math.inf))[2] == -math.inf


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ((1, 2, 3), "force_samples row 4: expected 6 values"),
        ("abcdef", "force_samples row 4: expected a sequence"),
        ((True, 1, 1, 1, 1.0, None), "column sample_index: True is not an integer"),
        ((1, "7", 1, 1, 1.0, None), "column adc_counts: '7' is not an integer"),
        ((1, 1, 1, 1, math.inf, None), "column t_host_s: inf is not a finite number"),
        ((1, 1, 1, 1, None, None), "column t_host_s: a number is required, got None"),
        ((1, 1, 1, 1, 1.0, "2"), "column force_n: '2' is not a real number"),
        ((1, 1, 1, -(2**63) - 1, 1.0, None), "column t_mcu_us: -9223372036854775809 does not"),
    ],
)
def test_coerce_row_errors_name_table_row_and_column(row: object, message: str) -> None:
    with pytest.raises(SessionError, match=re.escape(message)):
        coerce_row(FORCE_SAMPLES, row, 4)


def test_coerce_rows_structured_array_needs_every_field() -> None:
    arr = np.zeros(2, dtype=[("seq", "i8"), ("s_k", "i8")])
    with pytest.raises(SessionError, match=r"lacks field.*t_capture_host_s"):
        coerce_rows(FRAMES, arr)
    with pytest.raises(SessionError, match="is not a string"):
        coerce_rows(FRAMES, [(1, 1.0, 1.0, 3, 7)])


class _Color(enum.Enum):
    RED = "red"


@dataclasses.dataclass
class _Point:
    x_mm: float
    y_mm: float


def test_to_jsonable() -> None:
    value = {
        "np": np.float32(1.5),
        "i": np.int16(-3),
        "arr": np.arange(3),
        "nan": math.nan,
        "inf": np.inf,
        "t": (1, 2),
        "flag": Flag.NOT_SETTLED,
        "enum": _Color.RED,
        "path": PurePosixPath("/a/b"),
        "dc": _Point(1.0, 2.0),
        "none": None,
        "flags": frozenset({Flag.NOT_SETTLED, Flag.CONSTANT_SERIES}),
    }
    assert to_jsonable(value) == {
        "np": 1.5,
        "i": -3,
        "arr": [0, 1, 2],
        "nan": None,
        "inf": None,
        "t": [1, 2],
        "flag": "not_settled",
        "enum": "red",
        "path": "/a/b",
        "dc": {"x_mm": 1.0, "y_mm": 2.0},
        "none": None,
        "flags": ["constant_series", "not_settled"],
    }
    with pytest.raises(SessionError, match=r"cfg.a\[1\]: bytes value"):
        to_jsonable({"a": [1, b"x"]}, "cfg")
    with pytest.raises(SessionError, match="key 1 is not a string"):
        to_jsonable({1: 2})


_int64 = st.integers(-(2**63), 2**63 - 1)
_finite = st.floats(allow_nan=False, allow_infinity=False)
_force_rows = st.lists(
    st.tuples(
        st.integers(0, 2**32 - 1),
        st.integers(0, 1023),
        st.integers(0, 2**32 - 1),
        _int64,
        _finite,
        st.one_of(st.none(), st.floats(allow_nan=True)),
    ),
    max_size=40,
)


@settings(max_examples=25, deadline=None)
@given(rows=_force_rows, names=st.lists(st.text(max_size=20), max_size=5))
def test_property_round_trip_is_exact(
    rows: list[tuple[int, int, int, int, float, float | None]], names: list[str]
) -> None:
    options = StorageOptions(min_free_bytes=0, background_commit=False)
    with tempfile.TemporaryDirectory() as tmp:
        with SessionWriter.create(tmp, {}, {}, session_id="p", options=options) as writer:
            writer.add_force_samples(rows)
            for i, name in enumerate(names):
                writer.add_event(float(i), name, {"name": name, "i": i})
            writer.finish("complete")
        with SessionReader(Path(tmp) / "p") as reader:
            got = reader.force_samples().tolist()
            events = reader.events()
    assert len(got) == len(rows)
    for g, r in zip(got, rows, strict=True):
        assert g[:5] == r[:5]
        want = math.nan if r[5] is None else r[5]
        assert (math.isnan(g[5]) and math.isnan(want)) or g[5] == want
    assert [(e.kind, e.detail) for e in events] == [
        (n, {"name": n, "i": i}) for i, n in enumerate(names)
    ]
