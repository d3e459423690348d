"""Tests of stipi_daemon.analysis.severity: reference file, window search, classification."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from stipi_daemon.analysis.flags import Flag
from stipi_daemon.analysis.recovery_fit import fit_recovery, settling_time_from_time_constant
from stipi_daemon.analysis.severity import (
    SeverityReference,
    WindowSearch,
    classify_decay_rate,
    classify_fit,
    classify_vpr,
    find_severity_window,
    load_reference,
    normalised_depth,
)
from stipi_daemon.analysis.vpr import VPRModel
from stipi_daemon.errors import AnalysisError, ConfigError
from tests.analysis.synthetic import kv_series


@pytest.fixture(scope="module")
def reference() -> SeverityReference:
    return load_reference()


def _write(tmp_path: Path, data: object) -> Path:
    path = tmp_path / "ref.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


def _raw() -> dict[str, object]:
    text = (
        Path(__file__).resolve().parents[2] / "stipi_daemon" / "data" / "severity_reference.yaml"
    ).read_text(encoding="utf-8")
    data = yaml.safe_load(text)
    assert isinstance(data, dict)
    return data


def test_default_reference_holds_the_four_grades(reference: SeverityReference) -> None:
    assert [g.name for g in reference.grades] == ["I", "II", "III", "IV"]
    assert [g.severe for g in reference.grades] == [False, False, True, True]
    assert reference.schema_version == 1
    assert reference.window == WindowSearch()


def test_reference_file_round_trips_through_a_path(tmp_path: Path) -> None:
    assert load_reference(_write(tmp_path, _raw())) == load_reference()


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d["grades"][1].update(viscosity_n_s_per_mm2=-2.0), r"grades\.1\.viscosity"),
        (lambda d: d["grades"][2].update(elasticity_kpa=float("nan")), r"grades\.2\.elasticity"),
        (lambda d: d.update(schema_version=2), r"field schema_version"),
        (lambda d: d["grades"][0].update(colour="red"), r"grades\.0\.colour"),
        (lambda d: d["grades"].reverse(), r"mildest to most severe"),
        (lambda d: d["window"].update(mild_grade="V"), r"window\.mild_grade names no grade"),
        (lambda d: d["window"].update(length_s=2.5, step_s=1.0), r"whole number of step_s"),
        (lambda d: d.pop("grades"), r"field grades: Field required"),
    ],
)
def test_invalid_reference_names_file_and_field(tmp_path: Path, edit: object, match: str) -> None:
    data = _raw()
    edit(data)  # type: ignore[operator]
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError, match=match) as info:
        load_reference(path)
    assert str(path) in str(info.value)


def test_unreadable_or_malformed_reference_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read"):
        load_reference(missing)
    bad = tmp_path / "bad.yaml"
    bad.write_text("grades: [unclosed\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML"):
        load_reference(bad)
    bad.write_text("- a list\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_reference(bad)


def test_window_is_a_closed_set_of_whole_second_samples(reference: SeverityReference) -> None:
    w = find_severity_window(reference)
    assert len(w.sample_times_s) == 10
    assert w.sample_times_s == tuple(float(v) for v in range(int(w.start_s), int(w.end_s) + 1))
    assert w.candidate_starts_s[0] == 1.0
    assert w.candidate_starts_s[-1] == 41.0  # last window 41..50 s
    assert len(w.candidate_differences) == 41
    assert w.mean_difference == max(w.candidate_differences)
    mild = reference.grade("II").decay_rate_per_s
    assert w.mild_mean_depth == pytest.approx(
        float(np.mean(np.exp(-mild * np.asarray(w.sample_times_s))))
    )
    assert w.threshold_recovered_percent == pytest.approx(100 * (1 - w.threshold_depth_fraction))


def test_finer_step_gives_a_nearby_window(reference: SeverityReference) -> None:
    w = find_severity_window(reference, WindowSearch(step_s=0.25))
    assert len(w.sample_times_s) == 40
    assert 9.0 <= w.start_s <= 12.0
    assert w.threshold_recovered_percent == pytest.approx(62.0, abs=1.0)


def test_window_search_between_other_grades(reference: SeverityReference) -> None:
    w = find_severity_window(reference, WindowSearch(mild_grade="III", severe_grade="IV"))
    assert w.severe_mean_depth > w.mild_mean_depth
    with pytest.raises(AnalysisError, match="no reference grade 'V'"):
        find_severity_window(reference, WindowSearch(mild_grade="V"))


def test_each_reference_grade_is_nearest_to_itself(reference: SeverityReference) -> None:
    for g in reference.grades:
        r = classify_decay_rate(g.decay_rate_per_s, reference)
        assert r.nearest_grade == g.name
        assert r.severity == ("severe" if g.severe else "mild")
        assert r.flags == frozenset()
        assert dict(r.grade_distances)[g.name] == 0.0


def test_threshold_separates_mild_from_severe(reference: SeverityReference) -> None:
    w = find_severity_window(reference)
    rates = np.geomspace(1e-3, 1e1, 400)
    means = [float(np.mean(normalised_depth(np.asarray(w.sample_times_s), r))) for r in rates]
    results = [classify_decay_rate(float(r), reference, w) for r in rates]
    for m, res in zip(means, results, strict=True):
        assert res.severity == ("severe" if m >= w.threshold_depth_fraction else "mild")
        assert res.recovered_percent == pytest.approx(100 * (1 - m))
    # Slower recovery is more severe: once severe, every slower rate is severe too.
    severe = [res.severity == "severe" for res in results]
    assert severe == sorted(severe, reverse=True)


def test_measurements_beyond_the_extremes_are_flagged(reference: SeverityReference) -> None:
    fast = classify_decay_rate(5.0, reference)
    slow = classify_decay_rate(1e-3, reference)
    assert (fast.nearest_grade, fast.severity) == ("I", "mild")
    assert (slow.nearest_grade, slow.severity) == ("IV", "severe")
    assert fast.flags == slow.flags == {Flag.OUTSIDE_REFERENCE_RANGE}


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_invalid_decay_rate_raises(reference: SeverityReference, bad: float) -> None:
    with pytest.raises(AnalysisError, match="decay_rate_per_s"):
        classify_decay_rate(bad, reference)


def test_classify_vpr_uses_e_over_eta_and_keeps_flags(reference: SeverityReference) -> None:
    m = VPRModel.from_values(
        6.79,
        27.5,
        applied_force_n=16.0,
        indenter_radius_mm=3.2467,
        flags=frozenset({Flag.EARLY_NOISY_CROSSING}),
    )
    r = classify_vpr(m, reference)
    assert r.decay_rate_per_s == pytest.approx(1 / 27.5)
    assert (r.nearest_grade, r.severity) == ("III", "severe")
    assert r.flags == {Flag.EARLY_NOISY_CROSSING}


def test_classify_fit_converts_tau_to_the_papers_settling_time(
    reference: SeverityReference,
) -> None:
    # A recovery whose 98 % settling time equals grade II's T_r (8.95 s).
    s0, s_inf = 3000.0, 13000.0
    tau = 8.95 / settling_time_from_time_constant(1.0, s0, s_inf)
    t, s = kv_series(tau_s=tau, s0_px=s0, s_inf_px=s_inf)
    f = fit_recovery(t, s, 15.0)
    r = classify_fit(f, reference)
    assert r.decay_rate_per_s == pytest.approx(1 / 8.95, rel=1e-5)
    assert r.nearest_grade == "II"
    raw = classify_fit(f, reference, time_base="time_constant")
    assert raw.decay_rate_per_s == pytest.approx(1 / tau, rel=1e-5)
    assert raw.nearest_grade == "I"  # 1/tau is ~3.7x faster than 1/T_r


def test_classify_fit_rejects_fits_without_time_constant(reference: SeverityReference) -> None:
    t = np.linspace(0.0, 10.0, 20)
    with pytest.raises(AnalysisError, match="no time constant"):
        classify_fit(fit_recovery(t, np.ones(20), 0.0), reference)
    falling = fit_recovery(t, 5.0 * np.exp(-t / 2.0), 0.0)
    with pytest.raises(AnalysisError, match="rising S_k fit"):
        classify_fit(falling, reference)


def test_range_tolerance_controls_the_outside_flag(reference: SeverityReference) -> None:
    slowest = reference.grades[-1].decay_rate_per_s
    assert classify_decay_rate(slowest * 0.995, reference).flags == frozenset()
    strict = classify_decay_rate(slowest * 0.995, reference, range_tolerance=0.0)
    assert strict.flags == {Flag.OUTSIDE_REFERENCE_RANGE}
    with pytest.raises(AnalysisError, match="range_tolerance"):
        classify_decay_rate(0.1, reference, range_tolerance=-1.0)
