"""Drawing the report's figures with matplotlib (Agg canvas, no display, no pyplot state).

One function per figure turns the arrays of :mod:`.figures`, :mod:`.panels` and
:mod:`.compare` into a :class:`matplotlib.figure.Figure`; :func:`png_bytes` encodes it.
Every data-bearing artist carries a ``gid`` (``"force"``, ``"s_k"``, ``"fit_model"``,
``"vpr_paper"``...) so that a test can read back exactly what was plotted. This module
chooses looks only (colours, labels with units, legends); it computes nothing about the
measurement.
"""

from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Sequence
from typing import Any, Final

import numpy as np
import numpy.typing as npt
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle, Patch, Rectangle
from matplotlib.patheffects import Normal, Stroke

from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.report.compare import OverlaySeries
from stipi_daemon.report.figures import (
    GRADE_MATCH_NOTE,
    FitFigure,
    ForceFigure,
    NormalisedCurve,
    PhaseSpan,
    SkFigure,
    VprFigure,
    WindowSearchFigure,
)
from stipi_daemon.report.frames import FrameImage
from stipi_daemon.report.inputs import FloatArray
from stipi_daemon.report.numbers import value_text, value_with_uncertainty
from stipi_daemon.report.panels import FramePanel
from stipi_daemon.report.recovery_models import RecoveryModelsFigure
from stipi_daemon.report.series import TimeGap

__all__ = [
    "DPI",
    "MEASUREMENT_ZORDER",
    "MODEL_STYLES",
    "PHASE_COLOURS",
    "REFERENCE_DASHES",
    "REFERENCE_ZORDER",
    "THRESHOLD_COLOUR",
    "THRESHOLD_DASHES",
    "draw_fit",
    "draw_force",
    "draw_frames",
    "draw_normalised",
    "draw_overlay",
    "draw_recovery_models",
    "draw_s_k",
    "draw_vpr",
    "draw_window_search",
    "png_bytes",
    "unique_legend",
]

#: Resolution of the PNGs [dots per inch]; figures are 10 in wide (1000 px).
DPI: Final = 100
#: Shading colour of each measurement phase (faults in red).
PHASE_COLOURS: Final[dict[str, str]] = {
    "idle": "#f0f0f0",
    "armed": "#dddddd",
    "pitting": "#f7c58b",
    "release": "#fff2a8",
    "recovery": "#bfe5bf",
    "analysis": "#b9d7f0",
    "link_lost": "#f4a6a6",
    "camera_stalled": "#f4a6a6",
    "force_out_of_band": "#f4a6a6",
    "aborted": "#f4a6a6",
}
#: Line colour of each reference grade (mildest first), then of further curves.
_GRADE_COLOURS: Final = ("#1f77b4", "#2ca02c", "#ff7f0e", "#d62728", "#9467bd", "#8c564b")
#: Bar colours of the adjacent-grade pairs in Fig. 11, as in the paper (blue, orange, yellow).
_PAIR_COLOURS: Final = ("#0072bd", "#d95319", "#edb120", "#7e2f8e", "#77ac30")
#: Line colours of the sessions (or grades of sessions) in a comparison: none is a grade's.
_SESSION_COLOURS: Final = (
    "#17becf",
    "#bcbd22",
    "#e377c2",
    "#5b3a8c",
    "#a6761d",
    "#1b9e77",
    "#7f7f7f",
    "#000000",
)
#: Reference grades in Figs. 10 and 12: dashed, drawn above every session curve with a white
#: halo, so that a session curve lying on its own grade's never hides it.
REFERENCE_DASHES: Final = (0.0, (5.0, 2.0))
REFERENCE_ZORDER: Final = 4.0
#: This session's curves lie below the references (wide, half transparent).
MEASUREMENT_ZORDER: Final = 2.0
#: The mild/severe threshold: a dark grey dotted line, a colour and pattern no curve uses.
THRESHOLD_COLOUR: Final = "#3a3a3a"
THRESHOLD_DASHES: Final = (0.0, (1.0, 1.5))


def _figure(
    height_in: float, rows: int = 1, height_ratios: Sequence[float] | None = None
) -> Figure:
    fig = Figure(figsize=(10.0, height_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    if rows > 1:
        fig.subplots(rows, 1, sharex=True, height_ratios=height_ratios)
    else:
        fig.add_subplot()
    return fig


def unique_legend(ax: Axes, extra: Sequence[Artist] = (), **kwargs: Any) -> None:
    """The axes' legend with each label once (the first artist drawn under it), then
    ``extra`` handles (phases, gaps) not already named."""
    handles, labels = ax.get_legend_handles_labels()
    seen: dict[str, Artist] = {}
    for h, lb in zip(handles, labels, strict=True):
        seen.setdefault(lb, h)
    for h in extra:
        lb = h.get_label()
        if isinstance(lb, str) and lb and not lb.startswith("_"):
            seen.setdefault(lb, h)
    ax.legend(list(seen.values()), list(seen), **kwargs)


def png_bytes(fig: Figure) -> bytes:
    """``fig`` encoded as a PNG at :data:`DPI`."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _shade_phases(ax: Axes, phases: Sequence[PhaseSpan]) -> list[Patch]:
    """Shade each phase; returns one legend handle per phase shown."""
    seen: dict[str, Patch] = {}
    for span in phases:
        if span.phase in _UNSHADED:
            continue
        colour = PHASE_COLOURS.get(span.phase, "#eeeeee")
        ax.axvspan(span.start_s, span.end_s, color=colour, alpha=0.7, lw=0, zorder=0)
        seen.setdefault(span.phase, Patch(facecolor=colour, alpha=0.7, label=span.phase))
    return list(seen.values())


#: Phases not shaded: before arming, and the bookkeeping after the recovery.
_UNSHADED: Final = frozenset({"idle", "analysis", "done"})


#: Gaps labelled with their length on a figure (the longest ones; all are shaded).
_GAP_LABELS: Final = 6
_GAP_COLOUR: Final = "#6a6a6a"


def _shade_gaps(ax: Axes, gaps: Sequence[TimeGap], what: str, gid: str) -> list[Patch]:
    """Hatch each gap's span (gid ``gid``) and label the longest; returns a legend handle."""
    if not gaps:
        return []
    for g in gaps:
        span = ax.axvspan(
            g.start_s,
            g.end_s,
            facecolor="#d9d9d9",
            edgecolor=_GAP_COLOUR,
            hatch="///",
            alpha=0.8,
            lw=0.6,
            zorder=2,
        )
        span.set_gid(gid)
    for g in sorted(gaps, key=lambda g: g.duration_s, reverse=True)[:_GAP_LABELS]:
        ax.text(
            0.5 * (g.start_s + g.end_s),
            0.98,
            f"{what} gap {g.duration_s:.2f} s",
            transform=ax.get_xaxis_transform(),
            rotation=90,
            ha="center",
            va="top",
            fontsize=7,
            color="#333333",
            zorder=6,
            bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.7, "pad": 1.0},
        )
    longest = max(g.duration_s for g in gaps)
    label = f"{what} gaps: {len(gaps)} (longest {longest:.2f} s), line broken"
    return [Patch(facecolor="#d9d9d9", edgecolor=_GAP_COLOUR, hatch="///", label=label)]


def _vline(ax: Axes, x: float | None, label: str, colour: str, style: str = "--") -> None:
    if x is not None and math.isfinite(x):
        ax.axvline(x, color=colour, ls=style, lw=1.2, label=label, zorder=3)


def draw_force(data: ForceFigure, title: str = "") -> Figure:
    """Force over time with the phases shaded, the force band, F_a and T_0."""
    fig = _figure(4.2)
    ax = fig.axes[0]
    handles = _shade_phases(ax, data.phases)
    handles += _shade_gaps(ax, data.gaps, "force", "force_gap")
    (line,) = ax.plot(
        data.line_t_s, data.line_force_n, color="#1f3b73", lw=0.9, label="load cell force"
    )
    line.set_gid("force")
    if data.target_n is not None and data.tolerance_n is not None:
        band = ax.axhspan(
            data.target_n - data.tolerance_n,
            data.target_n + data.tolerance_n,
            color="#9ecae1",
            alpha=0.35,
            lw=0,
            label=f"pitting band {data.target_n:g} ± {data.tolerance_n:g} N",
            zorder=1,
        )
        band.set_gid("force_band")
    if data.release_n is not None:
        ax.axhline(
            data.release_n,
            color="#555555",
            ls=":",
            lw=1.0,
            label=f"release threshold {data.release_n:g} N",
        )
    if data.applied_force_n is not None and data.hold_s is not None:
        (fa,) = ax.plot(
            data.hold_s,
            [data.applied_force_n] * 2,
            color="#d62728",
            lw=2.0,
            label=f"$F_a$ = {value_text(data.applied_force_n, 'N')} (mean over the hold)",
        )
        fa.set_gid("applied_force")
    _vline(ax, data.release_s, "release detected", "#ff7f0e", ":")
    _vline(ax, data.t0_s, "$T_0$ (start of recovery)", "#2ca02c")
    ax.set_xlabel("time [s] (session clock)")
    ax.set_ylabel("force [N]")
    ax.set_title(title or "Applied force over time")
    unique_legend(ax, handles, loc="upper right", fontsize=8, ncols=2)
    ax.grid(True, alpha=0.3)
    return fig


def _within_line_range(ax: Axes, line: FloatArray, markers: FloatArray) -> FloatArray:
    """Scale the y axis to ``line`` and return ``markers`` clipped to it.

    An outlier frame far off the series (a dark frame counts the whole ROI) would otherwise
    squash the series it does not belong to; it is drawn at the axis edge instead.
    """
    finite = line[np.isfinite(line)]
    if finite.size == 0 or markers.size == 0:
        return markers
    lo, hi = float(finite.min()), float(finite.max())
    pad = 0.08 * (hi - lo) if hi > lo else max(1.0, 0.08 * abs(hi))
    lo, hi = lo - pad, hi + pad
    ax.set_ylim(lo, hi)
    return np.clip(markers, lo, hi)


def _mark_frames(ax: Axes, data: SkFigure) -> None:
    """Outlier frames (red crosses), frames without a finite S_k (ticks at the bottom) and
    the span around T_0 without frames when the release was not observed (red hatch)."""
    if data.outlier_t_s.size:
        who = "left out by the analysis" if data.outlier_source == "analysis" else "isolated"
        (mk,) = ax.plot(
            data.outlier_t_s,
            _within_line_range(ax, data.line_s_k_px, data.outlier_s_k_px),
            "X",
            color="#d62728",
            ms=8,
            ls="none",
            clip_on=False,
            label=f"outlier frames, {who} ({data.outlier_t_s.size}; at the edge if off scale)",
            zorder=5,
        )
        mk.set_gid("outliers")
    if data.release_gap_s is not None:
        lo, hi = data.release_gap_s
        hi = hi if math.isfinite(hi) else float(np.max(data.t_s, initial=lo))
        span = ax.axvspan(
            lo,
            hi,
            facecolor="none",
            edgecolor="#d62728",
            hatch="xx",
            lw=1.0,
            zorder=2,
            label="release not observed (no frame around $T_0$)",
        )
        span.set_gid("release_gap")
    if data.nan_frame_t_s.size:
        (nan,) = ax.plot(
            data.nan_frame_t_s,
            np.full(data.nan_frame_t_s.size, 0.03),
            "|",
            color="#d62728",
            ms=12,
            mew=1.5,
            ls="none",
            transform=ax.get_xaxis_transform(),
            label=f"frames without S_k (NaN, dropped: {data.nan_frame_t_s.size})",
            zorder=5,
        )
        nan.set_gid("nan_frames")


def draw_s_k(data: SkFigure, title: str = "") -> Figure:
    """S_k over time with the phases, T_0, T_s, S_0, S_max and the settling line (Eq. 6).

    The line breaks at gaps (hatched, labelled with their length); the detected release,
    isolated outlier frames and frames without S_k are marked.
    """
    fig = _figure(4.2)
    ax = fig.axes[0]
    handles = _shade_phases(ax, data.phases)
    handles += _shade_gaps(ax, data.gaps, "frame", "frame_gap")
    (line,) = ax.plot(
        data.line_t_s, data.line_s_k_px, color="#222222", lw=0.9, label="$S_k$ (Eq. 2)"
    )
    line.set_gid("s_k")
    _mark_frames(ax, data)
    _vline(ax, data.release_s, "release detected", "#ff7f0e", ":")
    _vline(ax, data.t0_s, "$T_0$ (start of recovery)", "#2ca02c")
    _vline(ax, data.ts_s, "$T_s$ (settled)", "#9467bd")
    if data.settle_level_px is not None:
        level = ax.axhline(
            data.settle_level_px,
            color="#d62728",
            ls="--",
            lw=1.0,
            label=(
                f"{100 * data.settle_fraction:g} % of $S_{{max}}$ = "
                f"{value_text(data.settle_level_px, 'px')}"
            ),
        )
        level.set_gid("settle_level")
    if data.s0_px is not None and data.t0_s is not None:
        ax.plot(
            [data.t0_s],
            [data.s0_px],
            "o",
            color="#2ca02c",
            ms=6,
            label=f"$S_0$ = {value_text(data.s0_px, 'px')}",
        )
    if data.recovery_time_s is not None and data.t0_s is not None and data.ts_s is not None:
        y = data.settle_level_px if data.settle_level_px is not None else 0.0
        ax.annotate(
            "",
            xy=(data.ts_s, y),
            xytext=(data.t0_s, y),
            arrowprops={"arrowstyle": "<->", "color": "#9467bd"},
        )
        ax.text(
            0.5 * (data.t0_s + data.ts_s),
            y,
            f"$T_r$ = {value_text(data.recovery_time_s, 's')}"
            + ("" if data.recovery_time_invalid is None else " (not valid)"),
            ha="center",
            va="bottom",
            fontsize=9,
            color="#9467bd",
        )
    ax.set_xlabel("time [s] (session clock)")
    ax.set_ylabel("$S_k$ [px]")
    flags = f" — flags: {', '.join(data.flags)}" if data.flags else ""
    ax.set_title((title or "Occluded pixel count $S_k$ over time") + flags)
    unique_legend(ax, handles, loc="best", fontsize=8, ncols=2)
    ax.grid(True, alpha=0.3)
    return fig


def _frames_and_outliers(
    ax: Axes,
    frames: tuple[FloatArray, FloatArray],
    rejected: tuple[FloatArray, FloatArray],
    style: tuple[str, str, str],
    outlier_label: str,
) -> None:
    """The recovery frames (times since T_0 [s], S_k [px]) as dots and the outlier frames
    left out as red crosses (kept at the axis edge when off scale); ``style`` is the dots'
    colour and the two artists' gids."""
    colour, gid, rejected_gid = style
    (pts,) = ax.plot(
        frames[0],
        frames[1],
        ".",
        color=colour,
        ms=2.5,
        label=f"$S_k$ data ({frames[0].size} frames)",
    )
    pts.set_gid(gid)
    if rejected[0].size:
        (rej,) = ax.plot(
            rejected[0],
            _within_line_range(ax, frames[1], rejected[1]),
            "X",
            color="#d62728",
            ms=7,
            ls="none",
            clip_on=False,
            label=outlier_label,
        )
        rej.set_gid(rejected_gid)


def draw_fit(data: FitFigure, title: str = "") -> Figure:
    """The fitted Kelvin-Voigt recovery against the data (top) and the residuals (bottom)."""
    fig = _figure(5.6, rows=2, height_ratios=(3.0, 1.4))
    ax, axr = fig.axes
    _frames_and_outliers(
        ax,
        (data.t_since_t0_s, data.s_k_px),
        (data.rejected_t_since_t0_s, data.rejected_s_k_px),
        ("#7f7f7f", "fit_data", "fit_rejected"),
        f"outlier frames left out of the fit ({data.rejected_t_since_t0_s.size}; "
        "at the edge if off scale)",
    )
    tau, tau_se = value_with_uncertainty(data.tau_s, data.tau_se_s)
    se = "" if data.tau_se_s is None else f" ± {tau_se}"
    (model,) = ax.plot(
        data.t_since_t0_s,
        data.model_px,
        color="#d62728",
        lw=1.5,
        label=(
            f"fit $S_\\infty - A\\,e^{{-(t-T_0)/\\tau}}$: τ = {tau}{se} s, "
            f"A = {value_text(data.amplitude_px, 'px')}, "
            f"$S_\\infty$ = {value_text(data.offset_px, 'px')}"
        ),
    )
    model.set_gid("fit_model")
    ax.set_ylabel("$S_k$ [px]")
    stats = []
    if data.r_squared is not None:
        stats.append(f"R² = {value_text(data.r_squared)}")
    if data.rmse_px is not None:
        stats.append(f"RMSE = {value_text(data.rmse_px, 'px')}")
    if data.flags:
        stats.append("flags: " + ", ".join(data.flags))
    if data.tau_invalid is not None:
        stats.append(f"τ not valid: {data.tau_invalid}")
    ax.set_title(
        (title or "Kelvin-Voigt recovery fitted to $S_k$")
        + (f" ({'; '.join(stats)})" if stats else "")
    )
    unique_legend(ax, loc="lower right", fontsize=8)
    ax.grid(True, alpha=0.3)
    (res,) = axr.plot(
        data.t_since_t0_s, data.residual_px, ".", color="#1f77b4", ms=2.0, label="data − fit"
    )
    res.set_gid("fit_residual")
    axr.axhline(0.0, color="#d62728", lw=1.0)
    axr.set_ylabel("residual [px]")
    axr.set_xlabel("time since $T_0$ [s]")
    axr.grid(True, alpha=0.3)
    return fig


#: Colour and dash pattern of each recovery model's curve (a model not listed: grey dotted).
MODEL_STYLES: Final[dict[str, tuple[str, Any]]] = {
    "kelvin_voigt": ("#d62728", "-"),
    "two_exponential": ("#1f77b4", (0.0, (6.0, 2.0))),
    "power_law": ("#2ca02c", (0.0, (6.0, 2.0, 1.5, 2.0))),
}


def draw_recovery_models(data: RecoveryModelsFigure, title: str = "") -> Figure:
    """The recovery S_k frames with every recovery model's curve (top) and each model's
    residuals (bottom); the best model drawn widest and underneath the others (which then
    stay visible on it), the legend naming each model's weights. Gids: ``models_data``,
    ``model_<name>``, ``model_residual_<name>``."""
    fig = _figure(5.8, rows=2, height_ratios=(3.0, 1.4))
    ax, axr = fig.axes
    _frames_and_outliers(
        ax,
        (data.t_since_t0_s, data.s_k_px),
        (data.rejected_t_since_t0_s, data.rejected_s_k_px),
        ("#9a9a9a", "models_data", "models_rejected"),
        f"outlier frames left out ({data.rejected_t_since_t0_s.size})",
    )
    for c in data.curves:
        colour, dashes = MODEL_STYLES.get(c.name, ("#555555", ":"))
        (line,) = ax.plot(
            c.t_since_t0_s,
            c.model_px,
            color=colour,
            ls=dashes,
            lw=2.6 if c.best else 1.5,
            label=c.label,
            zorder=2.5 if c.best else 3.0,  # the best widest, underneath: none hidden
        )
        line.set_gid(f"model_{c.name}")
        if c.model_px.size:
            (res,) = axr.plot(
                c.t_since_t0_s,
                data.s_k_px - c.model_px,
                color=colour,
                ls=dashes,
                lw=1.0,
            )
            res.set_gid(f"model_residual_{c.name}")
    ax.set_ylabel("$S_k$ [px]")
    ax.set_title(
        (title or "Recovery models fitted to $S_k$") + "\n" + data.rejection_line, fontsize=9.5
    )
    unique_legend(ax, loc="lower right", fontsize=8)
    ax.grid(True, alpha=0.3)
    axr.axhline(0.0, color="#555555", lw=0.8)
    axr.set_ylabel("data − model [px]")
    axr.set_xlabel("time since $T_0$ [s]")
    axr.grid(True, alpha=0.3)
    return fig


def _window_shade(ax: Axes, data: VprFigure) -> None:
    span = ax.axvspan(
        data.window_start_s,
        data.window_end_s,
        color="#ffd92f",
        alpha=0.3,
        lw=0,
        label=(
            f"severity window {data.window_start_s:g}-{data.window_end_s:g} s "
            f"(grades {data.mild_grade}/{data.severe_grade})"
        ),
        zorder=0,
    )
    span.set_gid("severity_window")


def _measurement_style(c: NormalisedCurve) -> tuple[str, str, float, float]:
    """Colour, line style, width and opacity of one of this session's curves."""
    if c.kind == "paper":
        return "#000000", "-", 3.2, 0.55
    return "#7f3fbf", "-.", 2.2, 0.85


#: White halo under a reference curve, so it stays visible on top of a session's curve.
_HALO: Final = (Stroke(linewidth=3.4, foreground="white", alpha=0.9), Normal())


def _reference_line(ax: Axes, x: FloatArray, y: FloatArray, i: int, label: str) -> Line2D:
    """One reference grade's curve: dashed, in the grade's colour, above the sessions'."""
    (ln,) = ax.plot(
        x,
        y,
        color=_GRADE_COLOURS[i % len(_GRADE_COLOURS)],
        lw=1.5,
        ls=REFERENCE_DASHES,
        label=label,
        zorder=REFERENCE_ZORDER,
    )
    ln.set_path_effects(list(_HALO))
    return ln


def _threshold_line(ax: Axes, data: VprFigure, label: str) -> Line2D:
    """The mild/severe threshold: dotted dark grey (no reference or session curve is)."""
    line = ax.axhline(
        data.threshold_depth_fraction,
        color=THRESHOLD_COLOUR,
        ls=THRESHOLD_DASHES,
        lw=2.0,
        label=label,
        zorder=3.0,
    )
    line.set_gid("threshold")
    return line


def _titled(ax: Axes, title: str, note: str) -> None:
    """The axes' title, with ``note`` (if any) as a smaller line between it and the plot."""
    ax.set_title(title, pad=16.0 if note else 6.0)
    if note:
        ax.text(
            0.5,
            1.01,
            note[0].upper() + note[1:] + ".",
            transform=ax.transAxes,
            ha="center",
            va="bottom",
            fontsize=8.5,
            color="#333333",
        ).set_gid("grade_note")


def draw_vpr(data: VprFigure, title: str = "") -> Figure:
    """Fig. 10: D(t) = D_p exp(-(E/eta) t) of the reference grades and of this session.

    The fit's curve decays at 1/tau (eta_tau = E tau), the paper estimator's and the grades'
    at 1/T_r (Eq. 8); the legend names each one's time. A note says that the nearest grade
    is matched on the normalised shape (Fig. 12), not on the depth.
    """
    fig = _figure(4.6)
    ax = fig.axes[0]
    _window_shade(ax, data)
    for i, c in enumerate(data.references):
        if c.depth_curve_mm is None:
            continue
        _reference_line(ax, data.t_s, c.depth_curve_mm, i, c.label).set_gid(f"vpr_reference_{i}")
    for c in data.measurements:
        if c.depth_curve_mm is None:
            continue
        colour, style, width, alpha = _measurement_style(c)
        grade = f"; nearest grade {c.nearest_grade}" if c.nearest_grade else ""
        (ln,) = ax.plot(
            data.t_s,
            c.depth_curve_mm,
            color=colour,
            ls=style,
            lw=width,
            alpha=alpha,
            label=c.label + grade,
            zorder=MEASUREMENT_ZORDER,
        )
        ln.set_gid(f"vpr_{c.kind}")
    ax.set_xlabel("time since $T_0$ [s]")
    ax.set_ylabel("pitting depth $D(t)$ [mm]")
    _titled(
        ax,
        title or "VPR model, Eq. (10): reference grades (Table II) and this session",
        data.grade_note,
    )
    ax.set_xlim(float(data.t_s[0]), float(data.t_s[-1]))
    ax.set_ylim(bottom=0.0)
    unique_legend(ax, loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    return fig


def draw_normalised(data: VprFigure, title: str = "") -> Figure:
    """Fig. 12: normalised VPR curves with the severity window and the mild/severe threshold.

    This session's curves are drawn as classified (the fit at 1/T_r(tau)), under the
    reference grades; the threshold is a dotted grey line.
    """
    fig = _figure(4.6)
    ax = fig.axes[0]
    _window_shade(ax, data)
    for i, c in enumerate(data.references):
        _reference_line(ax, data.t_s, c.normalised, i, c.normalised_label).set_gid(
            f"normalised_reference_{i}"
        )
    _threshold_line(
        ax,
        data,
        f"threshold: depth {value_text(data.threshold_depth_fraction)} of $D_p$ "
        f"(severe if recovered < {value_text(data.threshold_recovered_percent)} %)",
    )
    mid = 0.5 * (data.window_start_s + data.window_end_s)
    for c in data.measurements:
        colour, style, width, alpha = _measurement_style(c)
        cls = "" if c.severe is None else (" → severe" if c.severe else " → mild")
        grade = f" (nearest grade {c.nearest_grade})" if c.nearest_grade else ""
        (ln,) = ax.plot(
            data.t_s,
            c.normalised,
            color=colour,
            ls=style,
            lw=width,
            alpha=alpha,
            label=c.normalised_label + cls + grade,
            zorder=MEASUREMENT_ZORDER,
        )
        ln.set_gid(f"normalised_{c.kind}")
        what = "η = E·T_r" if c.kind == "paper" else "fit"
        (mk,) = ax.plot(
            [mid],
            [c.window_mean_depth_fraction],
            "D",
            color=colour,
            ms=8 if c.kind == "paper" else 5,  # the fit's inside the paper's when they agree
            mec="white",
            label=f"window mean ({what}): {value_text(c.window_mean_depth_fraction)}",
            zorder=REFERENCE_ZORDER + 1,
        )
        mk.set_gid(f"window_mean_{c.kind}")
    ax.set_xlabel("time since $T_0$ [s]")
    ax.set_ylabel("normalised depth $D(t)/D_p$ [-]")
    ax.set_title(title or "Edema severity from normalised VPR curves (Fig. 12)")
    ax.set_xlim(float(data.t_s[0]), float(data.t_s[-1]))
    ax.set_ylim(0.0, 1.05)
    unique_legend(ax, loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    return fig


def draw_window_search(data: WindowSearchFigure, title: str = "") -> Figure:
    """Fig. 11: mean distance between adjacent grades for each window start."""
    fig = _figure(3.8)
    ax = fig.axes[0]
    width = 0.8 / max(len(data.pairs), 1)
    for i, (label, starts, diffs) in enumerate(data.pairs):
        bars = ax.bar(
            starts + (i - (len(data.pairs) - 1) / 2) * width,
            diffs,
            width=width,
            color=_PAIR_COLOURS[i % len(_PAIR_COLOURS)],
            label=f"grades {label}",
        )
        for bar in bars.patches:
            bar.set_gid(f"window_search_{i}")
    ax.axvline(
        data.window_start_s,
        color="#d62728",
        ls="--",
        lw=1.2,
        label=f"chosen window starts at {data.window_start_s:g} s "
        f"({data.window_start_s:g}-{data.window_end_s:g} s)",
    )
    ax.set_xlabel(f"window start [s since $T_0$] ({data.length_s:g} s windows)")
    ax.set_ylabel("mean |difference| of $D(t)/D_p$ [-]")
    ax.set_title(title or "Window search between adjacent reference grades (Fig. 11)")
    unique_legend(ax, loc="upper right", fontsize=8)
    ax.grid(True, axis="y", alpha=0.3)
    return fig


def _roi_patch(roi: RectROI | CircleROI) -> Circle | Rectangle:
    if isinstance(roi, CircleROI):
        return Circle((roi.cx_px, roi.cy_px), roi.radius_px, fill=False, ec="#00e5ff", lw=1.5)
    return Rectangle(
        (roi.x_px - 0.5, roi.y_px - 0.5),
        roi.width_px,
        roi.height_px,
        fill=False,
        ec="#00e5ff",
        lw=1.5,
    )


def _rgba(image: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """A gray ``(H, W)`` or BGR ``(H, W, 3)`` uint8 image as opaque 8-bit RGBA."""
    out = np.full((*image.shape[:2], 4), 255, dtype=np.uint8)
    out[:, :, :3] = image[:, :, None] if image.ndim == 2 else image[:, :, 2::-1]
    return out


#: The two colours of the stripes marking pixels a cropped video does not store (RGB).
_NOT_STORED_RGB: Final = ((205, 205, 220), (150, 150, 170))


def _mark_not_stored(rgba: npt.NDArray[np.uint8], box: tuple[int, int, int, int]) -> None:
    """Paint the pixels of ``rgba`` outside ``box`` (x0, y0, x1, y1 [px]) as diagonal
    stripes: the video does not store them, so they are no camera data."""
    x0, y0, x1, y1 = box
    h, w = rgba.shape[:2]
    outside = np.ones((h, w), dtype=np.bool_)
    outside[y0:y1, x0:x1] = False
    stripe = (np.add.outer(np.arange(h, dtype=np.int32), np.arange(w, dtype=np.int32)) // 8) % 2
    for k, rgb in enumerate(_NOT_STORED_RGB):
        rgba[outside & (stripe == k), :3] = rgb


def _stored_note(panels: Sequence[FramePanel]) -> str:
    """The figure's line on a cropped video (empty when every frame is whole)."""
    for p in panels:
        if isinstance(p.raw, FrameImage) and p.raw.stored_box is not None:
            x0, y0, x1, y1 = p.raw.stored_box
            gray = ", as gray" if p.raw.ndim == 2 else ""
            return (
                f"\nThe video holds only the ROI's bounding box (x {x0}-{x1}, y {y0}-{y1} px of "
                f"the {p.raw.shape[1]}x{p.raw.shape[0]} frame{gray}):\nhatched pixels are "
                "not stored"
            )
    return ""


def draw_frames(panels: Sequence[FramePanel], title: str = "") -> Figure:
    """Each representative frame: raw (left) and Eq. (1) thresholded with the ROI (right).

    In the thresholded image, occluded pixels inside the ROI (counted in S_k) are white,
    occluded pixels outside it grey, the rest black. Each raw frame's title says where its
    pixels come from (:class:`~.frames.FrameImage`: the video, or the PNG and why); the
    pixels a cropped video does not store are striped in both images.
    """
    rows = max(len(panels), 1)
    fig = Figure(figsize=(10.0, 3.8 * rows), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 2, squeeze=False)
    for (ax_raw, ax_bin), p in zip(axes, panels, strict=False):
        source = p.raw.source if isinstance(p.raw, FrameImage) else ""
        box = p.raw.stored_box if isinstance(p.raw, FrameImage) else None
        # 8-bit RGBA, which matplotlib resamples in float32, where a colour-mapped or RGB
        # image is float64 (tens of MB for six frames: the report's peak memory); a gray
        # frame is drawn within one level of the gray colour map's picture
        raw = _rgba(p.raw)
        shown = _rgba(np.where(p.binary > 0, np.where(p.roi_mask, 255, 110), 0).astype(np.uint8))
        if box is not None:
            _mark_not_stored(raw, box)
            _mark_not_stored(shown, box)
        im = ax_raw.imshow(raw, interpolation="nearest")
        im.set_gid(f"raw_{p.kind}")
        when = "" if p.t_since_t0_s is None else f", {p.t_since_t0_s:+.2f} s from $T_0$"
        ax_raw.set_title(
            "\n".join([f"raw frame {p.seq} ({p.caption}{when})", *textwrap.wrap(source, 80)]),
            fontsize=9,
        )
        bim = ax_bin.imshow(shown, interpolation="nearest")
        bim.set_gid(f"binary_{p.kind}")
        if p.roi is not None:
            ax_raw.add_patch(_roi_patch(p.roi))
            ax_bin.add_patch(_roi_patch(p.roi))
        ax_bin.set_title(
            f"Eq. (1), p = {p.threshold_p}: $S_k$ = {p.s_k_recount_px} px in the ROI "
            f"(recorded {p.s_k_live_px} px)",
            fontsize=9,
        )
        for a in (ax_raw, ax_bin):
            a.set_xlabel("x [px]")
            a.set_ylabel("y [px]")
    if not panels:
        axes[0][0].text(0.5, 0.5, "no representative frame stored", ha="center")
    fig.suptitle(
        (title or "Representative frames: raw and thresholded (ROI in cyan)") + _stored_note(panels)
    )
    return fig


def _session_styles(labels: Sequence[tuple[str, bool]]) -> dict[tuple[str, bool], tuple[str, str]]:
    """Colour (one per label) and line style (solid: averaged; dash-dot: not) of each
    (label, averaged) pair, in first-appearance order."""
    colours: dict[str, str] = {}
    for label, _ in labels:
        colours.setdefault(label, _SESSION_COLOURS[len(colours) % len(_SESSION_COLOURS)])
    return {(lb, avg): (colours[lb], "-" if avg else "-.") for lb, avg in labels}


def _legend_text(label: str, averaged: bool, n: int) -> str:
    what = f"{n} session" + ("s" if n != 1 else "")
    return f"{label} ({what})" if averaged else f"{label}, not averaged ({what})"


def draw_overlay(
    series: Sequence[OverlaySeries], ylabel: str, title: str, gid_prefix: str
) -> Figure:
    """Several sessions' series against time since their own T_0.

    Sessions sharing a label share a colour and one legend entry (with their count);
    sessions left out of the means are dash-dotted.
    """
    fig = _figure(4.2)
    ax = fig.axes[0]
    keys = [(s.label, s.averaged) for s in series]
    styles = _session_styles(keys)
    for i, s in enumerate(series):
        colour, style = styles[(s.label, s.averaged)]
        (ln,) = ax.plot(
            s.t_since_t0_s,
            s.values,
            lw=1.0,
            color=colour,
            ls=style,
            label=_legend_text(s.label, s.averaged, keys.count((s.label, s.averaged))),
        )
        ln.set_gid(f"{gid_prefix}_{i}")
    ax.axvline(0.0, color="#2ca02c", ls="--", lw=1.0, label="$T_0$")
    ax.set_xlabel("time since $T_0$ [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    unique_legend(ax, loc="best", fontsize=8)
    ax.grid(True, alpha=0.3)
    return fig


def draw_compare_vpr(
    data: VprFigure,
    sessions: Sequence[tuple[str, bool, Sequence[NormalisedCurve]]],
    *,
    normalised: bool,
) -> Figure:
    """Figs. 10/12 for several sessions: reference grades and each session's paper curve.

    ``sessions`` holds (label, averaged, curves) per session; sessions sharing a label share
    a colour and one legend entry. The references are drawn above the sessions' curves.
    """
    fig = _figure(4.6)
    ax = fig.axes[0]
    _window_shade(ax, data)
    for i, c in enumerate(data.references):
        y = c.normalised if normalised else c.depth_curve_mm
        if y is None:
            continue
        _reference_line(ax, data.t_s, y, i, c.normalised_label).set_gid(f"reference_{i}")
    if normalised:
        _threshold_line(
            ax,
            data,
            f"threshold {value_text(data.threshold_depth_fraction)} "
            f"({value_text(data.threshold_recovered_percent)} % recovered)",
        )
    drawn = [
        (label, avg) for label, avg, curves in sessions if any(c.kind == "paper" for c in curves)
    ]
    styles = _session_styles(drawn)
    for i, (label, avg, curves) in enumerate(sessions):
        for c in curves:
            y = c.normalised if normalised else c.depth_curve_mm
            if c.kind != "paper" or y is None:
                continue
            colour, style = styles[(label, avg)]
            (ln,) = ax.plot(
                data.t_s,
                y,
                lw=2.6,
                alpha=0.6,
                ls=style,
                color=colour,
                label=_legend_text(label, avg, drawn.count((label, avg))) + ", η = E·T_r",
                zorder=MEASUREMENT_ZORDER,
            )
            ln.set_gid(f"session_{i}")
    ax.set_xlabel("time since $T_0$ [s]")
    if normalised:
        ax.set_ylabel("normalised depth $D(t)/D_p$ [-]")
        ax.set_ylim(0.0, 1.05)
        ax.set_title("Normalised VPR curves with the severity threshold (Fig. 12)")
    else:
        ax.set_ylabel("pitting depth $D(t)$ [mm]")
        ax.set_ylim(bottom=0.0)
        _titled(
            ax,
            "VPR model, Eq. (10), of each session and the reference grades (Fig. 10)",
            GRADE_MATCH_NOTE,
        )
    ax.set_xlim(float(data.t_s[0]), float(data.t_s[-1]))
    unique_legend(ax, loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    return fig
