"""Writing reports: one session's page and PNGs, or a comparison of several sessions.

This module is the report's shell: it reads sessions (:mod:`.load`), asks
:mod:`.figures`, :mod:`.panels`, :mod:`.parameter_table` and :mod:`.compare` for the
arrays and tables, :mod:`.render` for the figures and :mod:`.html` for the page,
and writes ``report.html`` (self-contained) with the same figures as PNG files next to it.
A figure whose data the session lacks (no results, no stored frame) is listed as not drawn
with the reason, on the page and in :attr:`WrittenReport.missing`. Files are replaced
atomically (written to ``*.tmp``, then renamed) so a reader never sees half a page.
"""

from __future__ import annotations

import contextlib
import gc
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
from matplotlib.figure import Figure

from stipi_daemon.analysis.severity import SeverityReference, load_reference
from stipi_daemon.errors import AnalysisError, SessionError, StipiError
from stipi_daemon.report import render as r
from stipi_daemon.report.compare import compare_table, overlay_force, overlay_s_k
from stipi_daemon.report.figures import (
    fit_figure,
    force_figure,
    measurement_curves,
    s_k_figure,
    vpr_figure,
    window_search_figure,
)
from stipi_daemon.report.html import (
    EmbeddedFigure,
    compare_page,
    format_number,
    recovery_models_html,
    session_page,
)
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.panels import frame_panels
from stipi_daemon.report.parameter_table import ParameterRow, flag_descriptions, parameter_table
from stipi_daemon.report.recovery_models import (
    absence_line,
    recovery_models_figure,
    recovery_models_text,
    recovery_models_view,
)
from stipi_daemon.report.series import gap_facts
from stipi_daemon.report.verdict import VerdictView, read_validity, session_verdict

__all__ = [
    "COMPARE_FIGURES",
    "REPORT_DIR",
    "REPORT_ERROR",
    "REPORT_HTML",
    "SESSION_FIGURES",
    "WrittenReport",
    "record_report_failure",
    "render_session_report",
    "verdict_text",
    "write_compare_report",
    "write_session_report",
]

#: Sub-directory of a session directory that holds its report.
REPORT_DIR: Final = "report"
#: File name of the page.
REPORT_HTML: Final = "report.html"
#: File written instead of a page when the daemon could not render the report.
REPORT_ERROR: Final = "report_error.txt"
#: Figures of a session report, in page order: name -> title.
SESSION_FIGURES: Final[dict[str, str]] = {
    "force": "Force over time",
    "s_k": "S_k over time",
    "recovery_fit": "Recovery fit and residuals",
    "recovery_models": "Recovery models",
    "vpr": "VPR model (Fig. 10)",
    "window_search": "Severity window search (Fig. 11)",
    "vpr_normalised": "Severity classification (Fig. 12)",
    "frames": "Representative frames",
}
#: Figures of a comparison report, in page order: name -> title.
COMPARE_FIGURES: Final[dict[str, str]] = {
    "overlay_s_k": "S_k of every session",
    "overlay_force": "Force of every session",
    "compare_vpr": "VPR model of every session (Fig. 10)",
    "compare_vpr_normalised": "Normalised VPR curves and threshold (Fig. 12)",
}


@dataclass(frozen=True)
class WrittenReport:
    """What a report wrote.

    Attributes
    ----------
    html_path : Path
        The self-contained page.
    figures : dict of str to Path
        Figure name -> its PNG, for every figure drawn.
    missing : dict of str to str
        Figure name -> why it was not drawn.
    verdict : str
        The verdict the page shows, as text (:func:`verdict_text`: the status, then one
        line per flagged or invalid quantity); empty for a comparison.
    recovery_models : str
        The page's "Recovery models" table as plain text
        (:func:`~.recovery_models.recovery_models_text`), or the one line saying why the
        session has none; empty for a comparison.
    """

    html_path: Path
    figures: dict[str, Path] = field(default_factory=dict)
    missing: dict[str, str] = field(default_factory=dict)
    verdict: str = ""
    recovery_models: str = ""


def _write_atomic(path: Path, payload: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_bytes(payload)
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)  # a full disk leaves no partial file behind
        raise SessionError(f"{path}: cannot write: {exc}") from exc


FigureMaker = Callable[[], "Figure | str"]


def _make_figures(
    makers: Sequence[tuple[str, str, str, FigureMaker]], out_dir: Path
) -> tuple[list[EmbeddedFigure], dict[str, Path], dict[str, str]]:
    """Draw each figure (a maker returns a Figure, or a string: why it cannot)."""
    embedded: list[EmbeddedFigure] = []
    written: dict[str, Path] = {}
    missing: dict[str, str] = {}
    for name, title, caption, make in makers:
        try:
            result = make()
        except StipiError as exc:
            result = str(exc)
        if isinstance(result, str):
            missing[name] = result
            embedded.append(EmbeddedFigure(name, title, caption, None, result))
            # A figure of an earlier report in this directory would no longer match.
            (out_dir / f"{name}.png").unlink(missing_ok=True)
            continue
        png = r.png_bytes(result)
        # A figure's artists refer to each other: only the cyclic collector frees them, and
        # the figures of a report piled up until it ran (20 MB of the demo's peak RSS).
        result.clear()
        del result
        gc.collect()
        path = out_dir / f"{name}.png"
        _write_atomic(path, png)
        written[name] = path
        embedded.append(EmbeddedFigure(name, title, caption, png))
    return embedded, written, missing


def _unique(items: Sequence[str]) -> list[str]:
    return list(dict.fromkeys(i for i in items if i))


def _notes(inp: ReportInput) -> list[str]:
    s = inp.summary or {}
    out = [str(n) for n in s.get("notes") or []]
    res = inp.results or {}
    out += [str(n) for n in res.get("notes") or []]
    if s.get("analysis_error"):
        out.append(f"analysis error: {s['analysis_error']}")
    flags = s.get("measurement_flags") or []
    if flags:
        out.append("measurement flags: " + ", ".join(str(f) for f in flags))
    if inp.summary is None:
        out.append("the session has no summary.json (it was not finished)")
    return _unique(out)


#: Rows of the parameter table summarised next to the verdict (the primary results).
_KEY_ROWS: Final = (
    "depth_mm",
    "rebound_force_n",
    "recovery_time_s",
    "elasticity_kpa",
    "viscosity_n_s_per_mm2",
    "severity_paper_estimator",
)


def _key_results(rows: Sequence[ParameterRow]) -> list[tuple[str, str, str]]:
    """(symbol, value text, validity status) of each primary result; "—" when not valid."""
    by_key = {r.key: r for r in rows}
    out: list[tuple[str, str, str]] = []
    for key in _KEY_ROWS:
        row = by_key.get(key)
        if row is None:
            continue
        status = "unknown" if row.validity is None else row.validity.status
        if not row.shown_as_result:
            text = "— (not valid)"
        elif isinstance(row.value, str):
            text = row.value
        else:
            text = format_number(row.value, row.unit)
        out.append(("severity" if key.startswith("severity") else row.symbol, text, status))
    return out


def _meta(inp: ReportInput, results_from: str) -> list[tuple[str, str]]:
    s = inp.summary or {}
    run = s.get("run") or {}
    cam = ((run.get("camera") or {}).get("source") or {}).get("name")
    cal = inp.calibration
    meta = [
        ("Created (UTC)", inp.created_utc or "-"),
        ("Session ended", inp.status),
        ("Results from", results_from),
        ("Phase / end", f"{s.get('phase', '-')} / {s.get('end_reason') or '-'}"),
        (
            "Recorded",
            f"{inp.frame_times_s.size} frames, {inp.force_times_s.size} force samples over "
            f"{format_number(inp.t_end_s - inp.t_start_s, 's')}",
        ),
        ("Gaps", gap_facts(inp)),
        ("Camera", str(cam or "-")),
        ("Probe", str(((inp.config.get("probe") or {}).get("transport") or {}).get("kind", "-"))),
        ("Calibration", f"{cal.get('source', '-')}; threshold p = {cal.get('threshold_p', '-')}"),
    ]
    if s.get("ground_truth"):
        gt = s["ground_truth"]
        meta.append(("Simulated scene", f"{gt.get('scene')} (seed {gt.get('seed')})"))
    return meta


def _models_figure(inp: ReportInput) -> Figure | str:
    """``recovery_models.png``, or why it cannot be drawn."""
    data = recovery_models_figure(inp)
    if data is None:
        return "no recovery models or no T_0 in the results"
    return r.draw_recovery_models(data)


def _session_makers(
    inp: ReportInput, ref: SeverityReference
) -> list[tuple[str, str, str, FigureMaker]]:
    """The figures of :data:`SESSION_FIGURES` for ``inp``: name, title, caption, maker."""
    vpr = vpr_figure(inp.results, ref, validity=read_validity(inp.summary))
    no_results = "the session has no results" + (
        f" ({inp.summary['analysis_error']})"
        if inp.summary and inp.summary.get("analysis_error")
        else ""
    )

    def force() -> Figure | str:
        if inp.force_times_s.size == 0:
            return "the session holds no force sample"
        return r.draw_force(force_figure(inp))

    def s_k() -> Figure | str:
        if inp.frame_times_s.size == 0:
            return "the session holds no frame"
        return r.draw_s_k(s_k_figure(inp))

    def fit() -> Figure | str:
        data = fit_figure(inp)
        if data is None:
            return "no fitted recovery" if inp.results is not None else no_results
        return r.draw_fit(data)

    def frames() -> Figure | str:
        panels = frame_panels(inp)
        if not panels and inp.status == "recording":
            return "the session is still recording: its representative frames are stored as it ends"
        if not panels:
            return (
                "the session stores no representative frame (frames/representative.json): "
                "it was recorded before they were kept, or no frame arrived in the pitting "
                "or recovery phase"
            )
        return r.draw_frames(panels)

    if vpr.omitted:
        vpr_note = " Not drawn, as not valid: " + "; ".join(vpr.omitted) + "."
    elif not vpr.measurements:
        vpr_note = f" This session's curves are missing: {no_results}."
    else:
        vpr_note = ""
    return [
        (
            "force",
            SESSION_FIGURES["force"],
            "Load-cell force as recorded, with the measurement phases shaded, the pitting "
            "force band, the release threshold, F_a (mean force over the pitting hold, Eq. 7) "
            "and T_0.",
            force,
        ),
        (
            "s_k",
            SESSION_FIGURES["s_k"],
            "Occluded pixel count S_k of every frame (Eq. 2) with the phases, T_0, T_s, S_0 "
            "and the 98 % of S_max line that defines T_s (Eq. 6).",
            s_k,
        ),
        (
            "recovery_fit",
            SESSION_FIGURES["recovery_fit"],
            "Kelvin-Voigt recovery S_inf - A exp(-(t - T_0)/tau) fitted to S_k over the "
            "recovery window (top) and the residuals data - fit (bottom).",
            fit,
        ),
        (
            "recovery_models",
            SESSION_FIGURES["recovery_models"],
            "S_k over the recovery window with every recovery model fitted to the same frames "
            "(Kelvin-Voigt solid red, two exponentials dashed blue, power law dash-dotted "
            "green; the best model, highest QAICc weight, widest and underneath), each curve "
            "offset - amplitude g(t - T_0) from its recorded parameters; the legend gives each "
            "model's Akaike and QAICc weights; below, data - model.",
            lambda: _models_figure(inp),
        ),
        (
            "vpr",
            SESSION_FIGURES["vpr"],
            "Pitting depth D(t) = D_p exp(-(E/eta) t), Eq. (10), of the reference grades "
            "(Table II, STIP-I columns; depths from Table I; dashed, drawn on top) and of this "
            "session with eta from Eq. (8), E T_r (decaying at 1/T_r, as the grades), and "
            "from the fitted time constant, E tau (decaying at 1/tau: tau is a time constant, "
            "shorter than the 98 % settling time T_r). The grade is matched on the normalised "
            "shape (Fig. 12), not on the depth: a session may start below the depth of its "
            "own grade." + vpr_note,
            lambda: r.draw_vpr(vpr),
        ),
        (
            "window_search",
            SESSION_FIGURES["window_search"],
            "Mean distance between the normalised curves of adjacent grades for every 10 s "
            "window; the severity window maximises it between the mild and severe grades.",
            lambda: r.draw_window_search(window_search_figure(ref)),
        ),
        (
            "vpr_normalised",
            SESSION_FIGURES["vpr_normalised"],
            "Normalised VPR curves D(t)/D_p with the severity window and the mild/severe "
            "threshold (dotted grey: mid-point of the two grades' window means). This "
            "session's curves are drawn as classified, under the reference grades: the paper "
            "estimator at 1/T_r, the fit at 1/T_r(tau), the 98 % settling time its tau implies "
            "(not at 1/tau as in Fig. 10: the grades' rates are 1/T_r); a diamond marks each "
            "curve's mean over the window." + vpr_note,
            lambda: r.draw_normalised(vpr),
        ),
        (
            "frames",
            SESSION_FIGURES["frames"],
            "Raw frames read from the session's video (left; each title names its source, "
            "and a frame the video cannot give is the stored PNG, with the reason) and their "
            "binary-inverted thresholding, Eq. (1), with the ROI (right): occluded pixels in "
            "the ROI, counted in S_k, are white; where the video holds only the ROI's "
            "bounding box, the hatched pixels are not stored.",
            frames,
        ),
    ]


def _with_rescued_results(inp: ReportInput) -> tuple[ReportInput, str]:
    """The session as the page shows it, and a sentence on where its results come from.

    A session without recorded results (it ended early, or its analysis failed) is shown
    with the results of the newest ``stipi-daemon analyze`` of its recording written beside
    it (:attr:`ReportInput.rescued`), never mixed with the recorded summary (only the run's
    statistics and a simulator's ground truth are kept from it). Without one, the sentence
    says how to compute what the recording allows.
    """
    if inp.results is not None:
        return inp, ""
    rescued = inp.rescued
    if rescued is None or not isinstance(rescued.get("results"), Mapping):
        return inp, (
            "No results were recorded; stipi-daemon analyze computes what the recording "
            "allows (written beside the session)."
        )
    kept = {k: v for k, v in (inp.summary or {}).items() if k in ("run", "ground_truth")}
    shown = ReportInput(**{**inp.__dict__, "summary": {**rescued, **kept}})
    return shown, (
        f"Results computed from the recording by stipi-daemon analyze ({inp.rescued_file}); "
        "the recorded session is unchanged."
    )


def render_session_report(
    inp: ReportInput, out_dir: Path, reference: SeverityReference | None = None
) -> WrittenReport:
    """Write the report of ``inp`` into ``out_dir`` (created if needed).

    Raises
    ------
    SessionError
        ``out_dir`` or a file in it cannot be written.
    """
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SessionError(f"{out_dir}: cannot create report directory: {exc}") from exc
    ref = reference if reference is not None else load_reference()
    recorded = inp
    inp, source = _with_rescued_results(recorded)
    makers = _session_makers(inp, ref)
    notes = _notes(inp)
    absence = absence_line(inp.results, notes)
    if absence is not None:  # no section: one line says why (an older summary...)
        makers = [m for m in makers if m[0] != "recovery_models"]
        (out_dir / "recovery_models.png").unlink(missing_ok=True)
    embedded, written, missing = _make_figures(makers, out_dir)
    models_view = recovery_models_view(inp.results)
    rows = parameter_table(inp.summary)
    verdict = session_verdict(inp.summary, recorded.status)
    page = session_page(
        session_id=inp.session_id,
        verdict=verdict,
        key_results=_key_results(rows),
        meta=_meta(
            inp,
            "summary.json (recorded)"
            if inp is recorded
            else f"{inp.rescued_file} (stipi-daemon analyze of the recording)",
        ),
        figures=embedded,
        rows=rows,
        flag_descriptions=flag_descriptions(),
        notes=notes,
        metadata=recorded.metadata,
        metadata_problem=recorded.metadata_problem,
        source=source,
        recovery_models=recovery_models_html(models_view, absence),
    )
    html_path = out_dir / REPORT_HTML
    _write_atomic(html_path, page.encode("utf-8"))
    return WrittenReport(
        html_path,
        written,
        missing,
        verdict_text(verdict),
        recovery_models_text(models_view, absence),
    )


def verdict_text(verdict: VerdictView) -> str:
    """The verdict as plain text: the status and its line, then one line per flagged or
    invalid quantity (``  D_p: invalid: <reason>``)."""
    lines = [f"{verdict.status} ({verdict.line})"]
    for p in verdict.problems:
        flags = f" [{', '.join(p.flags)}]" if p.flags else ""
        lines.append(f"  {p.symbol}: {p.status}" + (f": {p.reason}" if p.reason else "") + flags)
    return "\n".join(lines)


def write_session_report(
    session_dir: str | Path,
    out_dir: str | Path | None = None,
    *,
    reference: SeverityReference | None = None,
) -> WrittenReport:
    """Read the session in ``session_dir`` and write its report.

    Parameters
    ----------
    session_dir : str or Path
        The session directory.
    out_dir : str or Path, optional
        Where to write; default ``<session_dir>/report``.
    reference : SeverityReference, optional
        Reference grade curves; default the package's.

    Raises
    ------
    SessionError
        The session cannot be read or the report cannot be written, or it is still
        recording and ``out_dir`` is not given (its directory is the live writer's).
    """
    inp = load_report_input(session_dir)
    if out_dir is None and inp.status == "recording":
        # The directory is the live writer's, and its own report goes there at the end.
        raise SessionError(
            f"{session_dir}: the session is still recording, and the daemon writes its report "
            "into it when the measurement ends; give --out DIR for a report of what is "
            "recorded so far"
        )
    out = Path(out_dir) if out_dir is not None else Path(session_dir) / REPORT_DIR
    return render_session_report(inp, out, reference)


def record_report_failure(session_dir: str | Path, error: BaseException) -> Path | None:
    """Leave ``report/report_error.txt`` saying why the report was not written.

    Returns its path, or None when even that cannot be written (the session itself is
    never touched).
    """
    directory = Path(session_dir) / REPORT_DIR
    path = directory / REPORT_ERROR
    try:
        directory.mkdir(exist_ok=True)
        path.write_text(
            f"The report of this session could not be written: {type(error).__name__}: "
            f"{error}\nWrite it again with: stipi-daemon report {Path(session_dir)}\n",
            encoding="utf-8",
        )
    except OSError:
        return None
    return path


def write_compare_report(
    session_dirs: Sequence[str | Path],
    out_dir: str | Path,
    labels: Sequence[str] | None = None,
    *,
    reference: SeverityReference | None = None,
) -> WrittenReport:
    """Overlay several sessions and tabulate mean and spread per parameter.

    Parameters
    ----------
    session_dirs : sequence of str or Path
        The sessions (at least two).
    out_dir : str or Path
        Where to write ``report.html`` and the PNGs.
    labels : sequence of str, optional
        One label per session (e.g. the grade); equal labels form a group of repeated
        trials. Default: the session ids.
    reference : SeverityReference, optional
        Reference grade curves; default the package's.

    Raises
    ------
    AnalysisError
        Fewer than two sessions, or a label count that differs from the session count.
    SessionError
        A session cannot be read or the report cannot be written.
    """
    if len(session_dirs) < 2:
        raise AnalysisError(f"a comparison needs at least two sessions, got {len(session_dirs)}")
    if labels is not None and len(labels) != len(session_dirs):
        raise AnalysisError(f"{len(labels)} labels for {len(session_dirs)} sessions")
    inputs = [load_report_input(p) for p in session_dirs]
    table = compare_table(inputs, labels)
    # Legend and colour per grade group (a session in none keeps its own label).
    names = [s.group or s.label for s in table.sessions]
    averaged = [s.left_out is None and bool(s.group) for s in table.sessions]
    ref = reference if reference is not None else load_reference()
    vpr = vpr_figure(None, ref)
    t = vpr.t_s
    wt = np.asarray(vpr.window_sample_times_s, dtype=np.float64)
    curves = [
        (name, avg, measurement_curves(inp.results, t, wt, name, read_validity(inp.summary)))
        for name, avg, inp in zip(names, averaged, inputs, strict=True)
    ]
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SessionError(f"{out}: cannot create report directory: {exc}") from exc

    def overlay(which: str) -> Figure | str:
        series = (
            overlay_s_k(inputs, names, averaged)
            if which == "s_k"
            else overlay_force(inputs, names, averaged)
        )
        if not series:
            return "no session has a T_0 to align on"
        if which == "s_k":
            return r.draw_overlay(series, "$S_k$ [px]", "$S_k$ of every session", "overlay_s_k")
        return r.draw_overlay(series, "force [N]", "Force of every session", "overlay_force")

    grouping = (
        "Sessions sharing a label share a colour and a legend entry; those left out of the "
        "means (flagged, invalid, incomplete, validity unknown) are dash-dotted."
    )
    makers: list[tuple[str, str, str, FigureMaker]] = [
        (
            "overlay_s_k",
            COMPARE_FIGURES["overlay_s_k"],
            "S_k of each session against the time since its own T_0. " + grouping,
            lambda: overlay("s_k"),
        ),
        (
            "overlay_force",
            COMPARE_FIGURES["overlay_force"],
            "Force of each session against the time since its own T_0. " + grouping,
            lambda: overlay("force"),
        ),
        (
            "compare_vpr",
            COMPARE_FIGURES["compare_vpr"],
            "D(t), Eq. (10), of each session (paper estimator, eta = E T_r) under the reference "
            "grades (dashed). Grades are matched on the normalised shape, not on the depth. "
            + grouping,
            lambda: r.draw_compare_vpr(vpr, curves, normalised=False),
        ),
        (
            "compare_vpr_normalised",
            COMPARE_FIGURES["compare_vpr_normalised"],
            "Normalised curves of each session under the reference grades (dashed), with the "
            "severity window and the threshold (dotted grey). " + grouping,
            lambda: r.draw_compare_vpr(vpr, curves, normalised=True),
        ),
    ]
    embedded, written, missing = _make_figures(makers, out)
    meta = [
        (
            inp.session_id,
            f"label {s.label}; ended {inp.status}; verdict {s.verdict.status}"
            + ("" if s.left_out is None else "; not averaged"),
        )
        for inp, s in zip(inputs, table.sessions, strict=True)
    ]
    page = compare_page(table=table, figures=embedded, meta=meta)
    html_path = out / REPORT_HTML
    _write_atomic(html_path, page.encode("utf-8"))
    return WrittenReport(html_path, written, missing)
