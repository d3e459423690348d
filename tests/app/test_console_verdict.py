"""The console's final lines: the verdict first, reasons one per line, invalid values hidden."""

from __future__ import annotations

import io
from typing import Any

from stipi_daemon.app.console import OperatorConsole, format_results, verdict_lines
from stipi_daemon.measurement.state_machine import MeasurementConfig


def _results() -> dict[str, Any]:
    sev = {
        "severity": "mild",
        "nearest_grade": "1+",
        "recovered_percent": 90.0,
        "window_s": [0.0, 10.0],
        "threshold_recovered_percent": 80.0,
    }
    return {
        "pitting": {"depth_mm": 0.58, "rebound_force_n": 7.25, "recovery_time_s": 27.5},
        "paper_estimator": {"elasticity_kpa": 1097.0, "viscosity_n_s_per_mm2": 0.0302},
        "fitted_recovery": {"tau_s": 12.0, "tau_se_s": 0.1, "model": {}},
        "applied_force_n": 16.0,
        "severity": {"paper_estimator": sev, "fitted_model": None},
        "flags": ["release_not_observed"],
    }


def _validity(**status: tuple[str, str | None]) -> dict[str, Any]:
    names = [
        "depth_mm",
        "rebound_force_n",
        "recovery_time_s",
        "elasticity_kpa",
        "viscosity_n_s_per_mm2",
        "severity",
        "tau_s",
        "applied_force_n",
    ]
    out: dict[str, Any] = {}
    for q in names:
        st, reason = status.get(q, ("valid", None))
        flags = [] if st == "valid" else ["release_not_observed"]
        out[q] = {"status": st, "flags": flags, "reason": reason}
    return out


def test_an_invalid_depth_is_never_shown_as_a_result() -> None:
    summary = {
        "results": _results(),
        "validity": _validity(
            depth_mm=("invalid", "no frame between 18.8 and 20.0 s: the release was not seen"),
            elasticity_kpa=("invalid", "D_p is invalid"),
            viscosity_n_s_per_mm2=("invalid", "E is invalid"),
            severity=("invalid", "eta is invalid"),
            recovery_time_s=("flagged", "a gap beside the settling crossing"),
        ),
        "verdict": {"status": "invalid", "line": "Not valid: D_p, E, eta, severity (gap)."},
    }
    lines = format_results(summary)
    text = "\n".join(lines)
    assert "verdict: INVALID: Not valid: D_p, E, eta, severity (gap)." in lines
    assert "  D_p invalid: no frame between 18.8 and 20.0 s: the release was not seen" in text
    assert "  T_r flagged: a gap beside the settling crossing [release_not_observed]" in text
    assert "0.58" not in text and "1097" not in text and "MILD" not in text
    assert "D_p = invalid" in text and "T_r = 27.5 s (flagged)" in text
    assert "severity (paper estimator): invalid" in text


def test_complete_only_when_every_primary_quantity_is_valid() -> None:
    summary = {
        "results": _results(),
        "validity": _validity(),
        "verdict": {"status": "complete", "line": "Complete: every result is valid."},
    }
    assert verdict_lines(summary) == ["verdict: COMPLETE: Complete: every result is valid."]
    assert "D_p = 0.58 mm" in "\n".join(format_results(summary))


def test_old_summary_reads_unknown_and_no_results_keeps_the_verdict() -> None:
    assert verdict_lines({"results": _results()})[0].startswith("verdict: UNKNOWN: validity not")
    lines = format_results(
        {
            "results": None,
            "analysis_error": "no recovery",
            "verdict": {"status": "incomplete", "line": "Session incomplete (aborted)."},
        }
    )
    assert lines == [
        "verdict: INCOMPLETE: Session incomplete (aborted).",
        "no results: no recovery",
    ]


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_verdict_is_green_only_on_a_terminal() -> None:
    tty = _Tty()
    console = OperatorConsole(MeasurementConfig(), tty, live=False)
    console.line("verdict: COMPLETE: ok", "bold green")
    assert "\x1b[" in tty.getvalue() and "verdict: COMPLETE: ok" in tty.getvalue()
    plain = io.StringIO()
    OperatorConsole(MeasurementConfig(), plain, live=False).line("verdict: X", "bold green")
    assert plain.getvalue() == "verdict: X\n"


def test_the_fitted_viscosity_takes_the_worst_status_of_e_and_tau() -> None:
    """eta = E tau has no validity entry of its own: it is shown as its inputs allow, never
    plain beside a flagged or invalid E or tau."""
    results = _results()
    results["fitted_recovery"]["model"] = {"viscosity_n_s_per_mm2": 13.16}

    def shown(**status: tuple[str, str | None]) -> str:
        summary = {"results": results, "validity": _validity(**status), "verdict": {}}
        (line,) = [x for x in format_results(summary) if "viscosity (fit)" in x]
        return line

    assert shown().endswith("eta_tau = 13.16 N*s/mm^2 (E*tau)")
    assert "13.16 N*s/mm^2 (flagged)" in shown(elasticity_kpa=("flagged", "extrapolated"))
    assert "13.16 N*s/mm^2 (flagged)" in shown(tau_s=("flagged", "poor fit"))
    no_tau = shown(tau_s=("invalid", "no fit"), elasticity_kpa=("flagged", "extrapolated"))
    assert "eta_tau = invalid (E*tau)" in no_tau and "13.16" not in no_tau
