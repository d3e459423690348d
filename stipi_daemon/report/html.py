"""The report's HTML page: one self-contained file, figures embedded as PNG data URIs.

This module owns the page's markup: a header with the session's identity and state, the
figures (PNG bytes embedded as ``data:image/png;base64`` URIs, so the page opens anywhere
with no other file, no script, no external style sheet or font), the parameter table
with uncertainties, flags and ground truth, the flags' meanings and the notes; and the
comparison page (per-session values, per-group and overall mean and spread). It builds
strings only (every text escaped); files are written by :mod:`stipi_daemon.report.write`.
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

from stipi_daemon import __version__
from stipi_daemon.report.compare import CompareGroup, CompareTable
from stipi_daemon.report.parameter_table import ParameterRow
from stipi_daemon.report.verdict import QuantityStatus, VerdictView

__all__ = [
    "EmbeddedFigure",
    "compare_page",
    "format_number",
    "session_page",
    "validity_text",
    "verdict_html",
]

_CSS = """
body { font-family: sans-serif; margin: 1.5em auto; max-width: 1060px; color: #222; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; }
h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; padding-bottom: 0.2em; margin-top: 1.6em; }
table { border-collapse: collapse; font-size: 0.9em; margin: 0.6em 0; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.55em; text-align: left; vertical-align: top; }
th { background: #f0f0f0; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
tr.group th { background: #e4ecf6; text-align: left; }
figure { margin: 1em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; margin-top: 0.3em; }
.missing { color: #a33; font-style: italic; }
.flag { font-family: monospace; background: #fff3cd; padding: 0 0.25em; border-radius: 3px; }
.verdict { border: 2px solid #ccc; border-radius: 6px; padding: 0.5em 0.9em; margin: 0.8em 0; }
.verdict p { margin: 0.3em 0; font-size: 1.05em; }
.badge { display: inline-block; padding: 0.1em 0.6em; border-radius: 4px; color: #fff;
  font-weight: bold; text-transform: uppercase; letter-spacing: 0.03em; margin-right: 0.5em; }
.verdict-complete { border-color: #1a7f37; } .badge-complete { background: #1a7f37; }
.verdict-flagged { border-color: #b35900; } .badge-flagged { background: #b35900; }
.verdict-invalid { border-color: #c62828; } .badge-invalid { background: #c62828; }
.verdict-incomplete { border-color: #6a1b9a; } .badge-incomplete { background: #6a1b9a; }
.verdict-unknown { border-color: #777; } .badge-unknown { background: #777; }
.v-valid { color: #1a7f37; } .v-flagged { color: #b35900; } .v-invalid { color: #c62828; }
.v-unknown { color: #777; }
tr.invalid td { background: #fbeaea; }
.not-valid { color: #999; font-size: 0.85em; display: block; }
td.verdict-cell { min-width: 18em; font-size: 0.9em; }
dl.meta { display: grid; grid-template-columns: max-content auto; gap: 0.15em 1em; }
dl.meta dt { font-weight: bold; }
dl.meta dd { margin: 0; }
footer { margin-top: 2em; font-size: 0.8em; color: #777; }
"""


@dataclass(frozen=True)
class EmbeddedFigure:
    """One figure of the page.

    Attributes
    ----------
    name : str
        Identifier (also the PNG's file stem).
    title, caption : str
        Heading and caption text.
    png : bytes or None
        The PNG; None when the figure could not be drawn.
    missing_reason : str
        Why ``png`` is None.
    """

    name: str
    title: str
    caption: str
    png: bytes | None
    missing_reason: str = ""


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def format_number(value: float | None, unit: str = "") -> str:
    """A value with 4 significant digits, ``-`` for None.

    Integers and values from 10^4 to 10^9 (pixel counts) are written in full, rounded to
    the unit, rather than in exponent notation.
    """
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if float(value).is_integer() and abs(value) < 1e9:
        text = f"{int(value)}"
    elif 1e4 <= abs(value) < 1e9:
        text = f"{value:.0f}"
    else:
        text = f"{value:.4g}"
    return f"{text} {unit}".strip() if unit and unit != "-" else text


def _page(title: str, body: Iterable[str]) -> str:
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{_e(title)}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n"
        + "\n".join(body)
        + f"\n<footer>Written by stipi-daemon {_e(__version__)}. Self-contained page: the "
        "figures are embedded; the same PNGs are written next to this file.</footer>\n"
        "</body>\n</html>\n"
    )


def _figure_html(fig: EmbeddedFigure) -> str:
    if fig.png is None:
        return (
            f'<section id="fig-{_e(fig.name)}"><h2>{_e(fig.title)}</h2>'
            f'<p class="missing">Not drawn: {_e(fig.missing_reason)}</p></section>'
        )
    data = base64.b64encode(fig.png).decode("ascii")
    return (
        f'<section id="fig-{_e(fig.name)}"><h2>{_e(fig.title)}</h2><figure>'
        f'<img src="data:image/png;base64,{data}" alt="{_e(fig.title)}" '
        f'data-file="{_e(fig.name)}.png">'
        f"<figcaption>{_e(fig.caption)}</figcaption></figure></section>"
    )


def _flags_html(flags: Sequence[str]) -> str:
    return " ".join(f'<span class="flag">{_e(f)}</span>' for f in flags)


def validity_text(v: QuantityStatus | None) -> str:
    """``valid``, ``flagged: <flags>``, ``invalid: <reason>`` or ``unknown`` (empty: None)."""
    if v is None:
        return ""
    if v.status == "flagged":
        return "flagged: " + (", ".join(v.flags) or v.reason or "caveat")
    if v.status == "invalid":
        return f"invalid: {v.reason or 'no reason recorded'}"
    return v.status


def _validity_cell(v: QuantityStatus | None) -> str:
    if v is None:
        return "<td></td>"
    return (
        f'<td class="v-{_e(v.status)}" data-validity="{_e(v.status)}">{_e(validity_text(v))}</td>'
    )


def _value_cell(r: ParameterRow) -> str:
    """The value, or "—" with the recorded value greyed when it is not valid."""
    value = r.value if isinstance(r.value, str) else format_number(r.value)
    if r.shown_as_result:
        return f'<td class="num" data-key="{_e(r.key)}">{_e(value)}</td>'
    raw = "" if r.value is None else f'<span class="not-valid">{_e(value)} not valid</span>'
    return f'<td class="num" data-key="{_e(r.key)}" data-invalid="1">—{raw}</td>'


def _parameter_table(rows: Sequence[ParameterRow]) -> str:
    has_truth = any(r.truth is not None for r in rows)
    head = ["Symbol", "Parameter", "Value", "± SE", "Unit", "Validity", "Flags", "Note"]
    if has_truth:
        head += ["Ground truth", "Error [%]"]
    out = ['<table id="parameters"><thead><tr>']
    out += [f"<th>{_e(h)}</th>" for h in head]
    out.append("</tr></thead><tbody>")
    group = None
    for r in rows:
        if r.group != group:
            group = r.group
            out.append(f'<tr class="group"><th colspan="{len(head)}">{_e(group)}</th></tr>')
        cells = [
            f"<td>{_e(r.symbol)}</td>",
            f"<td>{_e(r.name)}</td>",
            _value_cell(r),
            f'<td class="num">{_e(format_number(r.uncertainty))}</td>',
            f"<td>{_e(r.unit)}</td>",
            _validity_cell(r.validity),
            f"<td>{_flags_html(r.flags)}</td>",
            f"<td>{_e(r.note)}</td>",
        ]
        if has_truth:
            err = format_number(r.error_percent)
            err_cell = (
                f'<td class="num">{_e(err)}</td>'
                if r.shown_as_result or r.error_percent is None
                else f'<td class="num"><span class="not-valid">{_e(err)} not valid</span></td>'
            )
            cells += [f'<td class="num">{_e(format_number(r.truth))}</td>', err_cell]
        cls = "" if r.shown_as_result else ' class="invalid"'
        out.append(f"<tr{cls}>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _flag_legend(flags: Iterable[str], descriptions: dict[str, str]) -> str:
    shown = sorted(set(flags))
    if not shown:
        return "<p>No quality flag was raised.</p>"
    items = "".join(
        f"<dt>{_flags_html([f])}</dt><dd>{_e(descriptions.get(f, ''))}</dd>" for f in shown
    )
    return f'<dl class="meta">{items}</dl>'


def verdict_html(verdict: VerdictView, key_results: Sequence[tuple[str, str, str]] = ()) -> str:
    """The verdict box: coloured status and line, the flagged and invalid quantities.

    ``key_results`` are (symbol, value text, validity status) of the primary results.
    """
    st = _e(verdict.status)
    out = [
        f'<section id="verdict" class="verdict verdict-{st}">',
        f'<p><span class="badge badge-{st}" id="status">{st}</span>'
        f'<span id="verdict-line">{_e(verdict.line)}</span></p>',
    ]
    if key_results:
        out.append(
            '<p id="key-results">'
            + "; ".join(
                f'<span class="v-{_e(status)}">{_e(sym)} = {_e(text)}</span>'
                for sym, text, status in key_results
            )
            + "</p>"
        )
    if verdict.problems:
        out.append(
            '<table id="validity"><thead><tr><th>Quantity</th><th>Status</th><th>Reason</th>'
            "<th>Flags</th></tr></thead><tbody>"
        )
        for p in verdict.problems:
            out.append(
                f'<tr data-quantity="{_e(p.quantity)}"><td>{_e(p.symbol)} ({_e(p.name)})</td>'
                f'<td class="v-{_e(p.status)}">{_e(p.status)}</td><td>{_e(p.reason or "")}</td>'
                f"<td>{_flags_html(p.flags)}</td></tr>"
            )
        out.append("</tbody></table>")
    out.append("</section>")
    return "".join(out)


def session_page(
    *,
    session_id: str,
    verdict: VerdictView,
    key_results: Sequence[tuple[str, str, str]],
    meta: Sequence[tuple[str, str]],
    figures: Sequence[EmbeddedFigure],
    rows: Sequence[ParameterRow],
    flag_descriptions: dict[str, str],
    notes: Sequence[str],
) -> str:
    """The HTML page of one session.

    Parameters
    ----------
    session_id : str
        Identity of the session.
    verdict : VerdictView
        The verdict shown at the top (status, line, flagged and invalid quantities).
    key_results : sequence of (str, str, str)
        Symbol, value text and validity status of the primary results (may be empty).
    meta : sequence of (str, str)
        Header facts (created, end state, duration, source...).
    figures : sequence of EmbeddedFigure
        The figures, in display order.
    rows : sequence of ParameterRow
        The parameter table (empty: no results).
    flag_descriptions : dict
        Flag -> meaning, for the flags that appear.
    notes : sequence of str
        Notes of the run and the analysis.
    """
    body = [
        f"<h1>STIP-I session report: {_e(session_id)}</h1>",
        verdict_html(verdict, key_results),
        '<dl class="meta">'
        + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta)
        + "</dl>",
        "<nav><p>Figures: "
        + ", ".join(f'<a href="#fig-{_e(f.name)}">{_e(f.title)}</a>' for f in figures)
        + ', <a href="#table">parameters</a>.</p></nav>',
    ]
    body += [_figure_html(f) for f in figures]
    body.append('<section id="table"><h2>Parameters</h2>')
    if rows:
        body.append(
            "<p>Uncertainties are one standard error where the analysis provides one (the "
            "recovery fit); values without one are single readings. Validity: valid, flagged "
            "(a caveat, the flags that concern the value) or invalid (the value cannot be "
            "trusted and is not shown as a result: — with the reason, the recorded value "
            "greyed). Flags are explained below.</p>"
        )
        body.append(_parameter_table(rows))
    else:
        body.append('<p class="missing">The session has no results.</p>')
    flags = [f for r in rows for f in r.flags]
    body.append("<h2>Flags</h2>" + _flag_legend(flags, flag_descriptions))
    body.append("<h2>Notes</h2>")
    if notes:
        body.append("<ul>" + "".join(f"<li>{_e(n)}</li>" for n in notes) + "</ul>")
    else:
        body.append("<p>None.</p>")
    body.append("</section>")
    return _page(f"STIP-I session {session_id}", body)


def _stat_cell(group: CompareGroup, key: str) -> str:
    s = next(s for s in group.stats if s.key == key)
    counts = [
        f"{n} {what}"
        for n, what in (
            (s.n_excluded, "invalid excluded"),
            (s.n_flagged, "flagged included"),
            (s.n_unknown, "of unknown validity included"),
        )
        if n
    ]
    note = f'<span class="not-valid">{_e(", ".join(counts))}</span>' if counts else ""
    if s.mean is None:
        return f'<td class="num" data-key="{_e(key)}">-{note}</td>'
    sd = "" if s.sd is None else f" ± {format_number(s.sd)}"
    cv = "" if s.cv_percent is None else f" ({s.cv_percent:.1f} %)"
    text = _e(format_number(s.mean) + sd + cv)
    return f'<td class="num" data-key="{_e(key)}">{text}{note}</td>'


def _session_value_cell(value: float | None, status: str) -> str:
    """One session's value: "—" (value greyed, not valid) when invalid; flagged marked."""
    text = format_number(value)
    if value is not None and status == "invalid":
        return (
            f'<td class="num" data-validity="invalid">—'
            f'<span class="not-valid">{_e(text)} not valid</span></td>'
        )
    mark = f' <span class="v-{_e(status)}">({_e(status)})</span>' if status != "valid" else ""
    if value is None:
        mark = ""
    return f'<td class="num" data-validity="{_e(status)}">{_e(text)}{mark}</td>'


def compare_page(
    *,
    table: CompareTable,
    figures: Sequence[EmbeddedFigure],
    meta: Sequence[tuple[str, str]],
) -> str:
    """The HTML page comparing several sessions (Tables I and II style)."""
    params = [(s.key, s.symbol, s.unit) for s in table.overall.stats]
    head = [
        "Session",
        "Label",
        "Verdict",
        *[f"{sym} [{unit}]" for _, sym, unit in params],
        "Severity",
    ]
    out = ['<table id="sessions"><thead><tr>']
    out += [f"<th>{_e(h)}</th>" for h in head]
    out.append("</tr></thead><tbody>")
    for i, (sid, label) in enumerate(zip(table.session_ids, table.labels, strict=True)):
        v = table.verdicts[i]
        cells = [
            f"<td>{_e(sid)}</td>",
            f"<td>{_e(label)}</td>",
            f'<td class="verdict-cell"><span class="badge badge-{_e(v.status)}">'
            f"{_e(v.status)}</span> {_e(v.line)}</td>",
        ]
        cells += [_session_value_cell(s.values[i], s.statuses[i]) for s in table.overall.stats]
        cells.append(f"<td>{_e(table.severities[i] or '-')}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    per_session = "".join(out)
    groups = list(table.groups)
    if len(groups) == len(table.session_ids):
        groups = []  # every session is its own group: only the overall column is meaningful
    columns = [*groups, table.overall]
    stats = ['<table id="statistics"><thead><tr><th>Parameter</th>']
    stats += [f"<th>{_e(g.label)} (n = {len(g.session_ids)})</th>" for g in columns]
    stats.append("</tr></thead><tbody>")
    for key, sym, unit in params:
        row = [f"<th>{_e(sym)} [{_e(unit)}]</th>"]
        row += [_stat_cell(g, key) for g in columns]
        stats.append("<tr>" + "".join(row) + "</tr>")
    row = ["<th>severe (paper estimator)</th>"]
    row += [f'<td class="num">{g.severe_count} of {g.classified_count}</td>' for g in columns]
    stats.append("<tr>" + "".join(row) + "</tr>")
    stats.append("</tbody></table>")
    body = [
        f"<h1>STIP-I comparison of {len(table.session_ids)} sessions</h1>",
        '<dl class="meta">'
        + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta)
        + "</dl>",
        "<h2>Mean and spread per parameter</h2>",
        "<p>Cells: mean ± SD (CV). SD is the sample standard deviation (n - 1), CV = SD / "
        "|mean|; n counts the sessions of a column, a parameter may have fewer values. "
        "Sessions sharing a label (repeated trials) form a group. A value that is invalid in "
        "its session (see each session's verdict) is never averaged: it is left out of the "
        "mean and spread and the cell says how many were excluded; flagged values are "
        "included and counted.</p>",
        "".join(stats),
        "<h2>Each session</h2>",
        per_session,
    ]
    body += [_figure_html(f) for f in figures]
    return _page(f"STIP-I comparison of {len(table.session_ids)} sessions", body)
