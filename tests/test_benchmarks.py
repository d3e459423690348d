"""Smoke tests of the accuracy and throughput benchmarks in their --quick mode.

They run each benchmark as a separate process (the throughput benchmark pins itself to one
CPU) into a temporary directory and check that the Markdown report (and the plots) come
out with the expected content. The numbers themselves are not checked: timings belong in
docs/, not in tests.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from stipi_daemon.analysis.imaging import sk_kernel

ROOT = Path(__file__).resolve().parent.parent


def run_benchmark(
    script: str, *args: str, timeout_s: float = 110.0
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def test_throughput_quick_writes_its_section_and_keeps_others(tmp_path: Path) -> None:
    out = tmp_path / "performance.md"
    out.write_text(
        "# Performance\n\n## Live daemon latency\n\nkept text\n\n## S_k throughput\n\nold\n"
    )
    proc = run_benchmark("throughput.py", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert "## Live daemon latency\n\nkept text" in text
    assert text.count("## S_k throughput") == 1 and "\nold\n" not in text
    assert "| 640x480 | gray | count, whole frame |" in text
    assert "| 640x480 | gray | OpenCV route: count, circle ROI |" in text
    assert f"S_k kernel `{sk_kernel()}`" in text
    assert (
        "S_k (`count`) on raw gray frames within 2x of the read floor: 640x480 whole frame" in text
    )
    assert "MJPG pipeline (decode + `measure`, circle ROI) within 1.2x" in text


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_accuracy_vs_time_quick_writes_report_and_plots(tmp_path: Path) -> None:
    proc = run_benchmark(
        "accuracy_vs_time.py",
        "--out",
        str(tmp_path),
        "--jobs",
        "2",
        "--tissue-scenes",
        "tissue_power_law",
        timeout_s=280.0,
    )
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "accuracy-vs-time.md").read_text()
    for heading in (
        "## Cost per frame",
        "## Accuracy against compute time",
        "## Pareto front and recommended settings",
        "## Accuracy against recording time",
        "## Spread over seeds",
        "## Tissue models: accuracy against recording time",
    ):
        assert heading in text
    assert "| full, p fixed, binary, every 1 |" in text
    assert "| 1/4, p otsu, subpixel, every 8 |" in text
    for png in ("error_vs_compute.png", "error_vs_recording.png"):
        data = (tmp_path / "accuracy-vs-time" / png).read_bytes()
        assert data.startswith(b"\x89PNG") and len(data) > 10_000


@pytest.mark.timeout(200)
def test_accuracy_vs_time_quick_tissue_scene_writes_the_tissue_tables(tmp_path: Path) -> None:
    """--quick on one tissue scene (the Zener jump): every tissue-model table comes out,
    with a row per estimator and a cell for the scene's tissue model."""
    proc = run_benchmark(
        "accuracy_vs_time.py",
        "--out",
        str(tmp_path),
        "--jobs",
        "1",
        "--only",
        "tissue",
        "--tissue-scenes",
        "tissue_zener",
        timeout_s=180.0,
    )
    assert proc.returncode == 0, proc.stderr
    text = (tmp_path / "accuracy-vs-time.md").read_text()
    for heading in (
        "## Tissue models: accuracy against recording time",
        "### Shortest recording for eta",
        "### Shortest recording for F_r",
        "### Error at 30 s and at 105 s",
        "### Coverage of the 95 % intervals",
        "### Model selection",
        "### Compute per measurement",
        "### Where an estimator is biased, and whether the result says so",
        "### Recommendation (from the tissue-model tables)",
    ):
        assert heading in text, heading
    assert "## Accuracy against compute time" not in text  # --only tissue
    assert "| estimator | target | zener |" in text
    for est in ("paper", "kelvin_voigt", "two_exponential", "power_law", "best"):
        for target in ("2 %", "5 %", "10 %"):
            assert f"| {est} | {target} |" in text
        assert f"| zener | {est} |" in text
    for est in ("kelvin_voigt", "two_exponential", "power_law", "best"):
        for q in ("tau", "T_r", "F_r", "eta"):
            assert f"| {est} | {q} |" in text
    # The compute table has a measured number for every estimator.
    cost = text.split("### Compute per measurement", 1)[1].split("###", 1)[0]
    for est in ("paper", "kelvin_voigt", "two_exponential", "power_law", "best"):
        row = next(line for line in cost.splitlines() if line.startswith(f"| {est} | "))
        assert float(row.split("|")[2]) > 0.0
    assert "instantaneous recovery" in text  # the Zener jump is explained
    data = (tmp_path / "accuracy-vs-time" / "tissue_error_vs_recording.png").read_bytes()
    assert data.startswith(b"\x89PNG") and len(data) > 10_000


def test_a_benchmark_replaces_its_own_section_and_adds_a_new_one_where_asked(
    tmp_path: Path,
) -> None:
    sys.path.insert(0, str(ROOT))
    try:
        from benchmarks._doc import HEADER, write_section
    finally:
        sys.path.remove(str(ROOT))
    doc = tmp_path / "performance.md"
    write_section(doc, "## A", "## A\n\na\n")  # no file yet: the header, then the section
    write_section(doc, "## C", "## C\n\nc\n")  # appended
    write_section(doc, "## B", "## B\n\nb\n", after="## A")  # between A and C
    write_section(doc, "## A", "## A\n\nnew a\n")  # replaced, the others kept
    write_section(doc, "## D", "## D\n\nd\n", after="## none")  # no such anchor: appended
    assert doc.read_text() == HEADER + ("\n## A\n\nnew a\n\n## B\n\nb\n\n## C\n\nc\n\n## D\n\nd\n")


@pytest.mark.timeout(300)
def test_liveview_cost_quick_writes_its_section(tmp_path: Path) -> None:
    out = tmp_path / "performance.md"
    out.write_text("# Performance\n\n## Demo speed\n\nkept text\n")
    proc = run_benchmark("liveview_cost.py", "--out", str(out), timeout_s=280.0)
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert "## Demo speed\n\nkept text" in text
    assert text.count("## Live view cost") == 1
    for mode in ("off", "idle", "1 viewer", "20 viewers", "0 viewers"):
        assert f"\n| {mode} | " in text, mode
    assert "### The real daemon at 720p60" in text
    assert "One viewer, the real daemon: **" in text


@pytest.mark.timeout(200)
def test_lossless_codecs_quick_writes_its_section(tmp_path: Path) -> None:
    """A row per candidate; the session video's FFV1 as recorded and at level 1 decodes
    bit-exactly and reads back from Matroska (FFmpeg's behaviour, not a timing)."""
    out = tmp_path / "performance.md"
    out.write_text("# Performance\n\n## Demo speed\n\nkept text\n")
    proc = run_benchmark("lossless_codecs.py", "--out", str(out), timeout_s=180.0)
    assert proc.returncode == 0, proc.stderr
    text = out.read_text()
    assert "## Demo speed\n\nkept text" in text
    assert text.count("## Lossless video codecs") == 1
    rows = [line for line in text.splitlines() if line.startswith("| FFV1")]
    for label in ("FFV1 as recorded (`FFV1_OPTIONS`: level 3, slicecrc 1)", "FFV1 level 1 ("):
        (row,) = [r for r in rows if r.startswith(f"| {label}")]
        assert row.endswith("| yes, 8 of 8 | yes, 8 of 8 equal |"), row
    assert "| raw (rawvideo, no compression) | " in text
