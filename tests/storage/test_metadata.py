"""Session metadata rules (storage/metadata.py) and their place in the manifest."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from stipi_daemon.errors import SessionError
from stipi_daemon.storage import SessionReader, SessionWriter, StorageOptions
from stipi_daemon.storage.metadata import (
    MAX_CHARS,
    METADATA_FIELDS,
    check_metadata,
    metadata_of,
    metadata_problem,
)

OPTIONS = StorageOptions(min_free_bytes=0)


@pytest.mark.parametrize(
    ("field", "value", "problem"),
    [
        ("subject", "P-001\nP-002", "contains a line break"),
        ("subject", "P-001\r", "contains a line break"),
        ("site", "x" * 65, "is 65 characters long"),
        ("operator", " Dr. X", "has leading or trailing spaces"),
        ("subject", "", "is empty"),
        ("note", "  \n ", "is empty"),
        ("subject", "P\x00", "contains control character U+0000"),
        ("note", "bell\x07", "contains control character U+0007"),
        ("subject", "a\u200bb", "contains control character U+200B"),  # zero-width space
        ("note", "n" * 2001, "is 2001 characters long"),
        ("subject", 17, "must be text, got int"),
        ("age", "40", "unknown metadata field"),
    ],
)
def test_bad_values_are_named(field: str, value: object, problem: str) -> None:
    found = metadata_problem(field, value)
    assert found is not None and found.startswith(problem)
    assert "\n" not in found


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("subject", None),
        ("subject", "P-001"),
        ("subject", "x" * 64),  # the limit itself
        ("site", "Klinikum Süd, Raum 3"),
        ("note", "left ankle\nday 3\tafter rest"),
        ("note", "n" * 2000),
    ],
)
def test_good_values_pass(field: str, value: str | None) -> None:
    assert metadata_problem(field, value) is None


@given(st.text(max_size=80))
def test_a_one_line_field_never_stores_a_line_break(text: str) -> None:
    if metadata_problem("subject", text) is None:
        assert text == text.strip() and text and len(text) <= MAX_CHARS["subject"]
        assert not any(c in text for c in "\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029")
        assert len(text.splitlines()) == 1


def test_check_metadata_names_the_field_and_fills_missing_ones() -> None:
    assert check_metadata({"subject": "P-1"}, "x") == {
        "subject": "P-1",
        "site": None,
        "operator": None,
        "note": None,
    }
    with pytest.raises(SessionError, match=r"^x: metadata field 'site': is empty"):
        check_metadata({"subject": "P-1", "site": ""}, "x")


def test_manifest_holds_every_field(tmp_path: Path) -> None:
    with SessionWriter.create(
        tmp_path, {}, {}, session_id="m", options=OPTIONS, metadata={"subject": "P-9"}
    ) as w:
        w.finish("aborted")
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert manifest["metadata"] == {"subject": "P-9", "site": None, "operator": None, "note": None}
    with SessionReader(tmp_path / "m") as reader:
        assert reader.metadata["subject"] == "P-9"


def test_bad_metadata_creates_no_session(tmp_path: Path) -> None:
    with pytest.raises(SessionError, match="metadata field 'subject': contains a line break"):
        SessionWriter.create(
            tmp_path, {}, {}, session_id="m", options=OPTIONS, metadata={"subject": "a\nb"}
        )
    assert not (tmp_path / "m").exists()


def test_old_and_damaged_manifests(tmp_path: Path) -> None:
    # A session recorded before metadata existed reads as all null.
    assert metadata_of({}) == dict.fromkeys(METADATA_FIELDS)
    with pytest.raises(SessionError, match=r"^m\.json: field 'metadata' must be an object"):
        metadata_of({"metadata": ["P-1"]}, "m.json")
    with pytest.raises(SessionError, match=r"^m\.json: metadata field 'subject': must be text"):
        metadata_of({"metadata": {"subject": 5}}, "m.json")
