"""The drawn figures plot exactly the session's samples (read back from the artists)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from stipi_daemon.analysis.severity import load_reference
from stipi_daemon.report import render as r
from stipi_daemon.report.figures import (
    fit_figure,
    force_figure,
    s_k_figure,
    vpr_figure,
    window_search_figure,
)
from stipi_daemon.report.inputs import ReportInput
from stipi_daemon.report.load import load_report_input
from stipi_daemon.report.numbers import value_text
from stipi_daemon.report.panels import frame_panels
from stipi_daemon.storage import SessionReader


@pytest.fixture(scope="module")
def inp(demo_session: Path) -> ReportInput:
    return load_report_input(demo_session)


def _line(fig: Figure, gid: str) -> Line2D:
    found = [a for ax in fig.axes for a in ax.get_lines() if a.get_gid() == gid]
    assert len(found) == 1, f"{gid}: {len(found)} lines"
    return found[0]


def _xy(line: Line2D) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(line.get_xdata(), dtype=float), np.asarray(line.get_ydata(), dtype=float)


def _labels(fig: Figure) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.get_legend().get_texts()]


def test_force_and_s_k_figures_plot_every_stored_sample(
    demo_session: Path, inp: ReportInput
) -> None:
    with SessionReader(demo_session) as reader:
        frames = reader.frames()
        force = reader.force_samples()
    fig = r.draw_force(force_figure(inp))
    x, y = _xy(_line(fig, "force"))
    np.testing.assert_array_equal(x, force["t_host_s"])
    np.testing.assert_array_equal(y, force["force_n"])
    assert fig.axes[0].get_ylabel() == "force [N]"
    assert "[s]" in fig.axes[0].get_xlabel()
    labels = _labels(fig)
    assert {"pitting", "recovery"} <= set(labels)  # shaded phases are in the legend
    fig = r.draw_s_k(s_k_figure(inp))
    x, y = _xy(_line(fig, "s_k"))
    np.testing.assert_array_equal(x, frames["t_capture_host_s"])
    np.testing.assert_array_equal(y, frames["s_k"])
    assert inp.summary is not None
    s_max = inp.summary["results"]["pitting"]["s_max_px"]
    _, level = _xy(_line(fig, "settle_level"))
    assert level[0] == pytest.approx(0.98 * s_max)
    assert any("98 % of" in t for t in _labels(fig))
    assert any("$T_0$" in t for t in _labels(fig)) and any("$T_s$" in t for t in _labels(fig))


def test_fit_figure_plots_data_model_and_residuals(inp: ReportInput) -> None:
    data = fit_figure(inp)
    assert data is not None
    fig = r.draw_fit(data)
    for gid, want in (
        ("fit_data", data.s_k_px),
        ("fit_model", data.model_px),
        ("fit_residual", data.residual_px),
    ):
        x, y = _xy(_line(fig, gid))
        np.testing.assert_array_equal(x, data.t_since_t0_s)
        np.testing.assert_array_equal(y, want)
    assert fig.axes[1].get_ylabel() == "residual [px]"


def test_vpr_figures_plot_the_curves_window_and_threshold(inp: ReportInput) -> None:
    vpr = vpr_figure(inp.results, load_reference())
    fig10 = r.draw_vpr(vpr)
    for i, c in enumerate(vpr.references):
        _, y = _xy(_line(fig10, f"vpr_reference_{i}"))
        assert c.depth_curve_mm is not None
        np.testing.assert_array_equal(y, c.depth_curve_mm)
    paper = next(c for c in vpr.measurements if c.kind == "paper")
    x, y = _xy(_line(fig10, "vpr_paper"))
    np.testing.assert_array_equal(x, vpr.t_s)
    assert paper.depth_curve_mm is not None
    np.testing.assert_array_equal(y, paper.depth_curve_mm)
    assert fig10.axes[0].get_ylabel() == "pitting depth $D(t)$ [mm]"
    fig12 = r.draw_normalised(vpr)
    _, thr = _xy(_line(fig12, "threshold"))
    assert thr[0] == vpr.threshold_depth_fraction
    _, fitted = _xy(_line(fig12, "normalised_fitted"))
    np.testing.assert_array_equal(fitted, vpr.measurements[1].normalised)
    _, mean = _xy(_line(fig12, "window_mean_paper"))
    assert mean[0] == paper.window_mean_depth_fraction
    window = [p for p in fig12.axes[0].patches if p.get_gid() == "severity_window"]
    assert len(window) == 1
    x0, x1 = window[0].get_x(), window[0].get_x() + window[0].get_width()
    assert (x0, x1) == (11.0, 20.0)
    assert any(
        f"severe if recovered < {value_text(vpr.threshold_recovered_percent)} %" in t
        for t in _labels(fig12)
    )


def test_window_search_figure_plots_every_pair() -> None:
    ws = window_search_figure(load_reference())
    fig = r.draw_window_search(ws)
    for i, (_, _, diffs) in enumerate(ws.pairs):
        heights = [
            p.get_height() for p in fig.axes[0].patches if p.get_gid() == f"window_search_{i}"
        ]
        np.testing.assert_array_equal(heights, diffs)


def test_frames_figure_shows_raw_and_thresholded(inp: ReportInput) -> None:
    panels = frame_panels(inp)
    fig = r.draw_frames(panels)
    images = {im.get_gid(): im for ax in fig.axes for im in ax.get_images()}
    for p in panels:
        raw = np.asarray(images[f"raw_{p.kind}"].get_array())
        # shown as RGB(A): a BGR frame reversed, a gray one (the video's ROI box) in each;
        # where the video holds only the ROI's box, the pixels outside it are hatched
        rgb = p.raw[:, :, ::-1] if p.raw.ndim == 3 else np.repeat(p.raw[:, :, None], 3, axis=2)
        box = getattr(p.raw, "stored_box", None)
        x0, y0, x1, y1 = box if box is not None else (0, 0, rgb.shape[1], rgb.shape[0])
        np.testing.assert_array_equal(raw[y0:y1, x0:x1, :3], rgb[y0:y1, x0:x1])
        assert raw.shape[2] == 4 and (raw[:, :, 3] == 255).all()
        shown = np.asarray(images[f"binary_{p.kind}"].get_array())
        # White = occluded inside the ROI: exactly the S_k pixels.
        assert int(np.count_nonzero(shown[:, :, 0] == 255)) == p.s_k_recount_px
    titles = [ax.get_title() for ax in fig.axes]
    assert any("recorded" in t for t in titles)
    # The ROI is drawn on both images of each row.
    assert sum(len(ax.patches) for ax in fig.axes) == 2 * len(panels)
