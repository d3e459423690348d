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
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from stipi_daemon import __version__
from stipi_daemon.report.compare import (
    COMPARE_PARAMETERS,
    CompareGroup,
    CompareSession,
    CompareTable,
    SessionValue,
)
from stipi_daemon.report.numbers import percent_text, value_text, value_with_uncertainty
from stipi_daemon.report.parameter_table import ParameterRow
from stipi_daemon.report.recovery_models import (
    COLUMNS as MODEL_COLUMNS,
)
from stipi_daemon.report.recovery_models import (
    INTERVAL_QUANTITIES,
    RecoveryModelsView,
    row_cells,
)
from stipi_daemon.report.verdict import QuantityStatus, VerdictView

__all__ = [
    "EmbeddedFigure",
    "compare_page",
    "format_number",
    "metadata_html",
    "recovery_models_html",
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
.verdict ul { margin: 0.3em 0 0.3em 1.2em; padding: 0; }
.verdict li { margin: 0.15em 0; }
#verdict-line { color: #333; }
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
tr.best td { background: #eaf4ea; font-weight: bold; }
.ci { color: #555; font-size: 0.85em; display: block; }
.not-valid { color: #999; font-size: 0.85em; display: block; }
td.verdict-cell { min-width: 18em; font-size: 0.9em; }
dl.meta { display: grid; grid-template-columns: max-content auto; gap: 0.15em 1em; }
dl.meta dt { font-weight: bold; }
dl.meta dd { margin: 0; }
.scroll { overflow-x: auto; }
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
    """A value without an uncertainty, by the report's one rule (:func:`.numbers.value_text`)."""
    return value_text(value, unit)


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


def _row_numbers(r: ParameterRow) -> tuple[str, str]:
    """The row's value and standard error as text, rounded together (:mod:`.numbers`)."""
    if isinstance(r.value, str):
        return r.value, value_text(r.uncertainty)
    if r.uncertainty is None:
        return value_text(r.value), value_text(None)
    return value_with_uncertainty(r.value, r.uncertainty)


def _value_cell(r: ParameterRow, value: str) -> str:
    """The value, or "—" with the recorded value greyed when it is not valid."""
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
        value, se = _row_numbers(r)
        cells = [
            f"<td>{_e(r.symbol)}</td>",
            f"<td>{_e(r.name)}</td>",
            _value_cell(r, value),
            f'<td class="num">{_e(se)}</td>',
            f"<td>{_e(r.unit)}</td>",
            _validity_cell(r.validity),
            f"<td>{_flags_html(r.flags)}</td>",
            f"<td>{_e(r.note)}</td>",
        ]
        if has_truth:
            err = percent_text(r.error_percent)
            err_cell = (
                f'<td class="num" data-error="{_e(r.key)}">{_e(err)}</td>'
                if r.shown_as_result or r.error_percent is None
                else f'<td class="num"><span class="not-valid">{_e(err)} not valid</span></td>'
            )
            cells += [f'<td class="num">{_e(value_text(r.truth))}</td>', err_cell]
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


def verdict_html(
    verdict: VerdictView,
    key_results: Sequence[tuple[str, str, str]] = (),
    source: str = "",
) -> str:
    """The verdict block: the status, then one line per flagged or invalid quantity.

    ``key_results`` are (symbol, value text, validity status) of the primary results,
    shown after the quantities; ``source`` says where the results come from when they are
    not the recorded ones.
    """
    st = _e(verdict.status)
    out = [
        f'<section id="verdict" class="verdict verdict-{st}">',
        f'<p class="verdict-head"><b>Verdict</b> <span class="badge badge-{st}" id="status">'
        f'{st}</span><span id="verdict-line">{_e(verdict.line)}</span></p>',
    ]
    if verdict.problems:
        out.append('<ul id="validity">')
        for p in verdict.problems:
            flags = f" {_flags_html(p.flags)}" if p.flags else ""
            reason = f": {_e(p.reason)}" if p.reason else ""
            out.append(
                f'<li data-quantity="{_e(p.quantity)}"><b>{_e(p.symbol)}</b> ({_e(p.name)}) '
                f'<span class="v-{_e(p.status)}">{_e(p.status)}</span>{reason}{flags}</li>'
            )
        out.append("</ul>")
    if source:
        out.append(f'<p id="results-source">{_e(source)}</p>')
    if key_results:
        out.append(
            '<p id="key-results">Results: '
            + "; ".join(
                f'<span class="v-{_e(status)}">{_e(sym)} = {_e(text)}</span>'
                for sym, text, status in key_results
            )
            + "</p>"
        )
    out.append("</section>")
    return "".join(out)


def metadata_html(metadata: Mapping[str, str | None] | None, problem: str | None = None) -> str:
    """The session's metadata (subject, site, operator, note), or why there is none."""
    if problem is not None:
        return (
            '<section id="metadata"><p class="missing">Session metadata not shown: '
            f"{_e(problem)}</p></section>"
        )
    if metadata is None:
        return (
            '<section id="metadata"><p class="v-unknown">Session metadata: none (recorded '
            "before subject, site, operator and note were kept).</p></section>"
        )
    if not any(metadata.values()):
        return (
            '<section id="metadata"><p class="v-unknown">Session metadata: none given '
            "(subject, site, operator, note).</p></section>"
        )
    items = "".join(
        f'<dt>{_e(k.capitalize())}</dt><dd data-field="{_e(k)}">'
        + (_e(v).replace("\n", "<br>") if v else '<span class="v-unknown">not given</span>')
        + "</dd>"
        for k, v in metadata.items()
    )
    return f'<section id="metadata"><dl class="meta">{items}</dl></section>'


def recovery_models_html(view: RecoveryModelsView | None, absence: str | None = None) -> str:
    """The "Recovery models" section: the table, the rejection line and the rules; or the
    one line saying why the session has none."""
    if view is None:
        return (
            '<section id="recovery-models"><p class="missing">'
            f"{_e(absence or 'Recovery models: none recorded.')}</p></section>"
        )
    head = "".join(f"<th>{_e(c)}</th>" for c in ("Model", *MODEL_COLUMNS, "τ means", "Flags"))
    body = []
    for row in view.rows:
        cells = row_cells(row)
        numbers = "".join(f'<td class="num">{_e(c)}</td>' for c in cells[:3])
        quantities = "".join(
            f'<td class="num">{_e(row.values[k])}<span class="ci">{_e(row.intervals[k])}</span>'
            "</td>"
            for k in INTERVAL_QUANTITIES
        )
        cls, best = (' class="best"', " — best") if row.best else ("", "")
        body.append(
            f'<tr data-model="{_e(row.name)}"{cls}>'
            f"<td>{_e(row.title)}{best}<br><code>{_e(row.name)}</code>"
            f"</td>{numbers}{quantities}<td>{_e(row.tau_meaning)}</td>"
            f"<td>{_flags_html(row.flags)}</td></tr>"
        )
    flag = (
        f'<p id="kv-flag"><span class="flag">kelvin_voigt_rejected</span> {_e(view.flag_text)}</p>'
        if view.flag_text
        else ""
    )
    return (
        '<section id="recovery-models"><h2>Recovery models</h2>'
        "<p>Every model fitted to the same recovery frames. Each quantity: the value and its "
        "95 % interval [low, high] below it. The QAICc weight decides the best model and the "
        "Kelvin-Voigt rejection (the Akaike weight, by plain AICc, is shown beside it); the "
        "best model is marked.</p>"
        f'<div class="scroll"><table id="recovery-models-table"><tr>{head}</tr>'
        + "".join(body)
        + "</table></div>"
        f'<p id="kv-rejection">{_e(view.rejection_line)}</p>{flag}'
        f"<p>Selection: {_e(view.selection)}. Intervals: {_e(view.intervals)}. "
        f"Fitted: {_e(view.window_text)}.</p></section>"
    )


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
    metadata: Mapping[str, str | None] | None = None,
    metadata_problem: str | None = None,
    source: str = "",
    recovery_models: str = "",
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
    metadata : mapping or None
        Subject, site, operator and note (None: recorded before metadata was kept).
    metadata_problem : str or None
        Why the metadata could not be read.
    source : str
        Where the results come from when they are not the recorded ones.
    recovery_models : str
        The "Recovery models" section (:func:`recovery_models_html`), placed after the
        recovery figures.
    """
    body = [
        f"<h1>STIP-I session report: {_e(session_id)}</h1>",
        verdict_html(verdict, key_results, source),
        metadata_html(metadata, metadata_problem),
        '<dl class="meta">'
        + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta)
        + "</dl>",
        "<nav><p>Figures: "
        + ", ".join(f'<a href="#fig-{_e(f.name)}">{_e(f.title)}</a>' for f in figures)
        + ', <a href="#table">parameters</a>.</p></nav>',
    ]
    names = [f.name for f in figures]
    after = next((n for n in ("recovery_models", "recovery_fit") if n in names), None)
    for f in figures:
        body.append(_figure_html(f))
        if f.name == after:
            body.append(recovery_models)
    if after is None:
        body.append(recovery_models)
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
    note = (
        f'<span class="not-valid">{s.n_excluded} not valid, left out</span>' if s.n_excluded else ""
    )
    if s.mean is None:
        return f'<td class="num" data-key="{_e(key)}">-{note}</td>'
    if s.sd is None:
        text = value_text(s.mean) + " (n = 1)"
    else:
        mean, sd = value_with_uncertainty(s.mean, s.sd)
        cv = "" if s.cv_percent is None else f" ({percent_text(s.cv_percent)} %)"
        text = f"{mean} ± {sd}{cv}"
    return f'<td class="num" data-key="{_e(key)}">{_e(text)}{note}</td>'


def _session_value_cell(v: SessionValue) -> str:
    """One session's value: "—" (value greyed, not valid) when invalid; flags named."""
    text = value_text(v.value)
    if v.value is not None and v.status == "invalid":
        return (
            f'<td class="num" data-validity="invalid">—'
            f'<span class="not-valid">{_e(text)} not valid</span></td>'
        )
    mark = ""
    if v.value is not None and v.status != "valid":
        what = ", ".join(v.flags) if v.flags else v.status
        mark = f' <span class="v-{_e(v.status)}">({_e(what)})</span>'
    return f'<td class="num" data-validity="{_e(v.status)}">{_e(text)}{mark}</td>'


def _sessions_table(sessions: Sequence[CompareSession], by_label: bool) -> str:
    subjects = any(s.subject for s in sessions)
    head = [
        "Session",
        *(["Subject"] if subjects else []),
        "Label",
        *([] if by_label else ["Grade group"]),
        "Verdict",
        *[f"{sym} [{unit}]" for _, sym, unit, _ in COMPARE_PARAMETERS],
        "Severity",
        "Best recovery model; Kelvin-Voigt",
        "Flags",
    ]
    out = ['<div class="scroll"><table id="sessions"><thead><tr>']
    out += [f"<th>{_e(h)}</th>" for h in head]
    out.append("</tr></thead><tbody>")
    for s in sessions:
        v = s.verdict
        problems = "".join(
            f"<br>{_e(p.symbol)} {_e(p.status)}" + (f": {_e(p.reason)}" if p.reason else "")
            for p in v.problems
        )
        cells = [
            f"<td>{_e(s.session_id)}</td>",
            *([f"<td>{_e(s.subject or '-')}</td>"] if subjects else []),
            f"<td>{_e(s.label)}</td>",
            *([] if by_label else [f"<td>{_e(s.group or '-')}</td>"]),
            f'<td class="verdict-cell"><span class="badge badge-{_e(v.status)}">'
            f"{_e(v.status)}</span>{problems}</td>",
        ]
        cells += [_session_value_cell(s.values[key]) for key, _, _, _ in COMPARE_PARAMETERS]
        cells.append(f"<td>{_e(s.severity or '-')}</td>")
        cells.append(f'<td data-recovery-model="{_e(s.session_id)}">{_e(s.recovery_model)}</td>')
        cells.append(f'<td data-flags="{_e(s.session_id)}">{_flags_html(s.flags) or "-"}</td>')
        out.append(f'<tr data-session="{_e(s.session_id)}">' + "".join(cells) + "</tr>")
    out.append("</tbody></table></div>")
    return "".join(out)


def _statistics_table(table: CompareTable) -> str:
    groups = table.groups
    out = ['<table id="statistics"><thead><tr><th>Parameter</th>']
    out += [
        f'<th data-group="{_e(g.label)}">{_e(g.label)} (n = {len(g.session_ids)})</th>'
        for g in groups
    ]
    out.append("</tr></thead><tbody>")
    for key, sym, unit, _ in COMPARE_PARAMETERS:
        row = [f"<th>{_e(sym)} [{_e(unit)}]</th>"]
        row += [_stat_cell(g, key) for g in groups]
        out.append("<tr>" + "".join(row) + "</tr>")
    row = ["<th>severe (paper estimator)</th>"]
    row += [f'<td class="num">{g.severe_count} of {g.classified_count}</td>' for g in groups]
    out.append("<tr>" + "".join(row) + "</tr>")
    out.append("</tbody></table>")
    return "".join(out)


def _left_out_html(table: CompareTable) -> str:
    """Every session that enters no mean, and why."""
    items = [
        f'<li data-left-out="{_e(sid)}">{_e(g.label)}: {_e(sid)}: {_e(why)}</li>'
        for g in table.groups
        for sid, why in g.left_out
    ]
    items += [
        f'<li data-left-out="{_e(sid)}">{_e(sid)}: {_e(why)}</li>' for sid, why in table.ungrouped
    ]
    if not items:
        return '<p id="left-out">Every session enters the means of its grade.</p>'
    return (
        "<p>Left out of every mean (shown one by one in the table below):</p>"
        f'<ul id="left-out">{"".join(items)}</ul>'
    )


def compare_page(
    *,
    table: CompareTable,
    figures: Sequence[EmbeddedFigure],
    meta: Sequence[tuple[str, str]],
) -> str:
    """The HTML page comparing several sessions (Tables I and II style)."""
    grouping = (
        "the labels given (--labels), one group per grade"
        if table.grouped_by == "label"
        else "the nearest grade each session's analysis found (give --labels to group by "
        "the known grade)"
    )
    body = [
        f"<h1>STIP-I comparison of {len(table.session_ids)} sessions</h1>",
        '<dl class="meta">'
        + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in meta)
        + "</dl>",
        "<h2>Mean and spread per grade</h2>",
        f"<p>Sessions are grouped by {_e(grouping)}. Sessions of different grades are never "
        "averaged together, and there is no mean over all sessions. Within a grade only "
        "sessions whose verdict is complete are averaged, and of them only valid values; "
        "flagged, invalid and incomplete sessions and those of unknown validity are listed "
        "below, one by one, never averaged. Cells: mean ± SD (CV), n the sessions averaged; "
        "SD is the sample standard deviation (n - 1), CV = SD / |mean|, and mean and SD are "
        "rounded together (SD to 2 significant figures).</p>",
        _statistics_table(table) if table.groups else "<p>No group to average.</p>",
        _left_out_html(table),
        "<h2>Each session</h2>",
        _sessions_table(table.sessions, table.grouped_by == "label"),
    ]
    body += [_figure_html(f) for f in figures]
    return _page(f"STIP-I comparison of {len(table.session_ids)} sessions", body)
