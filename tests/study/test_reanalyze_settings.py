"""The settings file of ``study reanalyze`` and the command's one-line refusals.

Cheap: the dataset is a few synthetic sessions (``_synthetic``: 5 samples, 3 frames each,
no video), re-analysed serially; what they give is whatever the replay of so little
data gives, checked here only for being a row (no error) of the right provenance.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from stipi_daemon.errors import ConfigError
from stipi_daemon.study.dataset import StudyError
from stipi_daemon.study.index import index_sessions
from stipi_daemon.study.reanalyze import reanalyze, version_name
from stipi_daemon.study.settings import load_settings, parse_settings, settings_hash
from tests.study._synthetic import write_session


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    rng = random.Random(7)
    for i in range(3):
        write_session(tmp_path / "sessions", i, rng)
    out = tmp_path / "study"
    index_sessions([tmp_path / "sessions"], out)
    return out


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (
            "analysis: {bootstrap_replicatez: 1}\n",
            "field 'analysis.bootstrap_replicatez': unknown key",
        ),
        (
            "analysis: {bootstrap_replicates: -1}\n",
            "field 'analysis.bootstrap_replicates': Input should be greater",
        ),
        (
            "measurement: {target_force_n: fast}\n",
            "field 'measurement.target_force_n': Input should be a valid number",
        ),
        (
            "imaging: {threshold_p: 300}\n",
            "field 'imaging.threshold_p': Input should be less than or equal to 255",
        ),
        ("imaging: {threshold_p: null}\n", "field 'imaging.threshold_p': give 0..255"),
        (
            "imaging: {roi: {kind: circle, cx_px: 1, cy_px: 2}}\n",
            "field 'imaging.roi.radius_px': Field required",
        ),
        ("estimator: paper\n", "field 'estimator': unknown key"),
        ("version: 2\n", "field 'version'"),
        ("calibration: missing.json\n", "field 'calibration': "),
        ("- a list\n", "the settings must be a mapping"),
        ("analysis: {a: 1\n", "S.yaml"),
    ],
)
def test_a_bad_settings_file_is_one_line_naming_the_field(
    tmp_path: Path, text: str, message: str
) -> None:
    path = _write(tmp_path / "S.yaml", text)
    with pytest.raises(ConfigError) as err:
        load_settings(path)
    line = str(err.value)
    assert "\n" not in line and message in line and str(path) in line


def test_the_settings_hash_is_of_what_the_settings_say(tmp_path: Path) -> None:
    a = parse_settings(
        {"analysis": {"settle_fraction": 0.05, "bootstrap_replicates": 0}}, "a", tmp_path
    )
    b = parse_settings(
        {"analysis": {"bootstrap_replicates": 0.0, "settle_fraction": 5e-2}}, "b", tmp_path
    )
    c = parse_settings({"analysis": {"bootstrap_replicates": 1}}, "c", tmp_path)
    assert settings_hash(a, False) == settings_hash(b, False)
    assert settings_hash(a, False) != settings_hash(c, False)
    assert settings_hash(a, False) != settings_hash(a, True)  # --recompute-sk is part of it
    assert version_name(None, settings_hash(a, False)) == "s-" + settings_hash(a, False)[7:19]


def test_imaging_settings_need_recompute_sk(dataset: Path, tmp_path: Path) -> None:
    path = _write(tmp_path / "S.yaml", "imaging: {threshold_p: 90}\n")
    with pytest.raises(ConfigError, match=r"field 'imaging\.threshold_p' acts on the S_k count"):
        reanalyze(dataset, path, scheduler="synchronous")
    assert not (dataset / "analyses").exists()


def test_serial_run_rows_carry_provenance_and_a_version_is_bound_to_its_settings(
    dataset: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path / "S.yaml", "analysis: {bootstrap_replicates: 0}\n")
    argv = ["study", "reanalyze", str(dataset), "--settings", str(path), "--serial"]
    assert main([*argv, "--name", "v1"]) == 0
    out = capsys.readouterr()
    # The synthetic sessions record no calibration: each one's error is its row's.
    assert "analysis v1: 3 analysed, 0 already done, 3 with errors, 0 failed, of 3" in out.out
    assert "analysis v1: 3/3 sessions, 3 errors" in out.err  # plain lines: not a terminal
    assert "stipi-daemon: error S00001: " in out.err and "calibration lacks" in out.err
    record = json.loads((dataset / "analyses" / "v1.json").read_text())
    assert record["settings"] == {"analysis": {"bootstrap_replicates": 0}}
    assert record["counts"] == {"sessions": 3, "done": 3, "errors": 3, "failed": 0}
    sql = (
        "SELECT count(*) AS n, count(DISTINCT settings_hash) AS hashes, "
        "min(package_version) = max(package_version) AS one_version FROM results "
        "WHERE analysis = 'v1' AND error LIKE '%calibration%' AND verdict = 'unknown'"
    )
    assert main(["study", "query", str(dataset), sql]) == 0
    assert capsys.readouterr().out.splitlines()[1].split() == ["3", "1", "True"]
    # The same version with other settings is refused before anything is written.
    other = _write(tmp_path / "T.yaml", "analysis: {bootstrap_replicates: 5}\n")
    assert main([*argv[:4], str(other), "--serial", "--name", "v1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "analysis v1 was made with other settings" in err and "\n" not in err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--name", "recorded"], "'recorded' is the daemon's own analysis"),
        (["--name", "../x"], "--name '../x': use 1-100 letters"),
        (["--workers", "0"], "--workers 0: give 1 or more"),
        (["--workers", "2", "--scheduler", "tcp://127.0.0.1:1"], "--workers sizes the embedded"),
    ],
)
def test_bad_options_are_refused_in_one_line(
    dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    extra: list[str],
    message: str,
) -> None:
    path = _write(tmp_path / "S.yaml", "{}\n")
    assert main(["study", "reanalyze", str(dataset), "--settings", str(path), *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not list((dataset / "results").glob("analysis=*[!d]"))  # only 'recorded'


def test_not_a_dataset_and_no_scheduler_are_one_line(
    tmp_path: Path, dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scheduler is tried for SCHEDULER_CONNECT_TIMEOUT_S (30 s; 2 s here), then the
    run is refused in one line."""
    from stipi_daemon.study import reanalyze as module

    monkeypatch.setattr(module, "SCHEDULER_CONNECT_TIMEOUT_S", 2.0)
    path = _write(tmp_path / "S.yaml", "{}\n")
    with pytest.raises(StudyError, match="not a study dataset") as not_dataset:
        reanalyze(tmp_path / "nothing", path)
    before = sorted(p.relative_to(dataset) for p in dataset.rglob("*"))
    with pytest.raises(StudyError, match=r"--scheduler tcp://127.0.0.1:9: cannot connect") as no:
        reanalyze(dataset, path, scheduler="tcp://127.0.0.1:9")
    assert "\n" not in str(not_dataset.value) and "\n" not in str(no.value)
    # refused before anything is recorded: no analyses/ record, lock or directory left
    assert sorted(p.relative_to(dataset) for p in dataset.rglob("*")) == before
