"""Every quality flag says what it means (the report's flag legend shows it)."""

from __future__ import annotations

from stipi_daemon.analysis.flags import FLAG_DESCRIPTIONS, Flag


def test_every_flag_has_a_description() -> None:
    assert list(FLAG_DESCRIPTIONS) == list(Flag)
    for flag, text in FLAG_DESCRIPTIONS.items():
        assert text.strip() == text and text.endswith("."), flag
        assert " ".join(text.split()) == text, flag
