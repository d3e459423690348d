"""The page markup: numbers, escaping, missing figures (pure, no session needed)."""

from __future__ import annotations

import math

import pytest

from stipi_daemon.report.html import EmbeddedFigure, format_number, session_page
from stipi_daemon.report.parameter_table import ParameterRow
from stipi_daemon.report.verdict import QuantityStatus, VerdictView


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
        "verdict": VerdictView("complete", "Complete: every result is valid.", ()),
        "key_results": [],
        "meta": [("Camera", "cam")],
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
    page = _page(figures=[fig], verdict=VerdictView("incomplete", "Session incomplete.", ()))
    assert "Not drawn: no frame stored" in page
    assert "The session has no results." in page
    assert 'class="badge badge-incomplete" id="status">incomplete<' in page


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
    # The value is rounded with its standard error (2 significant figures).
    assert 'data-key="time_constant_s">7.64900<' in page
    assert '<td class="num">0.000032</td>' in page
    assert '<span class="flag">not_settled</span>' in page
    assert "T_r is a lower bound." in page
    assert "Ground truth" not in page  # no truth column without a ground truth


def test_verdict_names_each_flagged_or_invalid_quantity() -> None:
    problems = (
        QuantityStatus("depth_mm", "invalid", ("release_not_observed",), "no frame at T_0"),
        QuantityStatus("recovery_time_s", "flagged", ("not_settled",), "a lower bound"),
    )
    verdict = VerdictView("invalid", "Not valid: D_p.", problems)
    page = _page(verdict=verdict, key_results=[("D_p", "— (not valid)", "invalid")])
    assert 'class="badge badge-invalid" id="status">invalid<' in page
    assert '<span id="verdict-line">Not valid: D_p.</span>' in page
    assert (
        '<li data-quantity="depth_mm"><b>D_p</b> (pitting depth) '
        '<span class="v-invalid">invalid</span>: no frame at T_0 '
        '<span class="flag">release_not_observed</span></li>'
    ) in page
    assert (
        '<li data-quantity="recovery_time_s"><b>T_r</b> (recovery time) '
        '<span class="v-flagged">flagged</span>: a lower bound'
    ) in page
    assert '<span class="v-invalid">D_p = — (not valid)</span>' in page


def test_an_invalid_value_is_not_shown_as_a_result() -> None:
    bad = QuantityStatus("depth_mm", "invalid", ("release_not_observed",), "no frame at T_0")
    flagged = QuantityStatus("recovery_time_s", "flagged", ("not_settled",), "lower bound")
    rows = [
        ParameterRow("G", "D_p", "depth", "depth_mm", 0.58, None, "mm", validity=bad),
        ParameterRow("G", "T_r", "time", "recovery_time_s", 26.6, None, "s", validity=flagged),
        ParameterRow("G", "R", "radius", "indenter_radius_mm", 3.0, None, "mm"),
    ]
    page = _page(rows=rows)
    assert 'data-key="depth_mm" data-invalid="1">—<span class="not-valid">0.58 not valid' in page
    assert 'data-key="depth_mm">0.58<' not in page
    assert '<td class="v-invalid" data-validity="invalid">invalid: no frame at T_0</td>' in page
    assert 'data-key="recovery_time_s">26.6<' in page
    assert '<td class="v-flagged" data-validity="flagged">flagged: not_settled</td>' in page
    assert 'data-key="indenter_radius_mm">3<' in page
