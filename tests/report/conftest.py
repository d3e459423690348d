"""Recorded sessions for the report tests (see :mod:`tests._report_sessions`)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from tests._report_sessions import recorded_session
from tests.daemon._support import SCENES, SHORT_MEASUREMENT, write_config


@pytest.fixture(scope="session")
def demo_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete grade-I session with a shortened recovery."""
    return recorded_session(tmp_path_factory, "grade1")


@pytest.fixture(scope="session")
def second_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A complete grade-II session with a shortened recovery (for comparisons)."""
    return recorded_session(tmp_path_factory, "grade2")


@pytest.fixture(scope="session")
def prony_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A session recorded by the daemon on a tissue that is not Kelvin-Voigt: the
    two-time-constant scene (``configs/scenes/tissue_prony.yaml``) shortened, 160 x 120
    frames, 100 bootstrap replicates (as tests/daemon/test_recovery_models_run.py)."""
    directory = tmp_path_factory.mktemp("prony")
    doc = yaml.safe_load((SCENES / "tissue_prony.yaml").read_text())
    doc["name"] = "prony_report"
    doc["force_profile"].update({"approach_s": 1.0, "hold_s": 5.5, "recovery_s": 20.0})
    doc["camera"].update({"width": 160, "height": 120})
    scene = directory / "prony_report.yaml"
    scene.write_text(yaml.safe_dump(doc))
    config = write_config(
        directory,
        {
            "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
            "camera": {"kind": "simulator", "scene": str(scene)},
            "measurement": SHORT_MEASUREMENT,
            "analysis": {"bootstrap_replicates": 100},
            "run": {"speed": 0.0},
        },
    )
    session = run_measurement(load_config(config), quiet=True).session_dir
    summary = json.loads((session / "summary.json").read_text())
    assert summary["results"] is not None, summary.get("analysis_error")
    return Path(session)
