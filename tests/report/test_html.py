"""The page markup: numbers, escaping, missing figures (pure, no session needed)."""

from __future__ import annotations

import math

import pytest

from stipi_daemon.report.html import EmbeddedFigure, format_number, session_page
from stipi_daemon.report.parameter_table import ParameterRow


@pytest.mark.parametrize(
    ("value", "unit", "text"),
    [
        (None, "", "-"),
        (math.nan, "", "-"),
        (math.inf, "mm", "-"),
        (2.0, "", "2"),
        (2.92947, "mm", "2.929 mm"),
        (12989.79, "px", "12990 px"),
        (3.6e-05, "s", "3.6e-05 s"),
        (0.5, "-", "0.5"),
    ],
)
def test_format_number(value: float | None, unit: str, text: str) -> None:
    assert format_number(value, unit) == text


def _page(**overrides: object) -> str:
    args: dict[str, object] = {
        "session_id": "s1",
        "status": "complete",
        "meta": [("Camera", "cam")],
        "headline": "ok.",
        "figures": [],
        "rows": [],
        "flag_descriptions": {},
        "notes": [],
    }
    args.update(overrides)
    return session_page(**args)


def test_text_from_the_session_is_escaped() -> None:
    page = _page(
        session_id="<b>x</b>",
        notes=['<script>alert("x")</script>'],
        meta=[("Camera", 'a "quoted" & <odd> name')],
    )
    assert "<script>" not in page and "&lt;script&gt;" in page
    assert "&lt;b&gt;x&lt;/b&gt;" in page
    assert "a &quot;quoted&quot; &amp; &lt;odd&gt; name" in page


def test_missing_figure_and_empty_table_are_said() -> None:
    fig = EmbeddedFigure("frames", "Frames", "caption", None, "no frame stored")
    page = _page(figures=[fig], status="fault")
    assert "Not drawn: no frame stored" in page
    assert "The session has no results." in page
    assert 'class="status-other" id="status">fault<' in page


def test_table_rows_flags_and_legend() -> None:
    rows = [
        ParameterRow(
            "G",
            "T_r",
            "recovery time",
            "recovery_time_s",
            26.6,
            None,
            "s",
            ("not_settled",),
            "lower bound",
        ),
        ParameterRow("G", "τ", "time constant", "time_constant_s", 7.649, 3.2e-05, "s"),
    ]
    page = _page(rows=rows, flag_descriptions={"not_settled": "T_r is a lower bound."})
    assert 'data-key="recovery_time_s">26.6<' in page
    assert '<td class="num">3.2e-05</td>' in page
    assert '<span class="flag">not_settled</span>' in page
    assert "T_r is a lower bound." in page
    assert "Ground truth" not in page  # no truth column without a ground truth
