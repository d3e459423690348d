"""A daemon run on a tissue that is not Kelvin-Voigt (the two-time-constant scene,
shortened, small frames) carries every recovery model in summary.json - parameters, AICc,
Akaike weight, 95 % intervals on tau, T_r, F_r and eta - and the Kelvin-Voigt rejection
flag; ``analyze`` recomputes the same (seeded bootstrap)."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from stipi_daemon.app.config import load_config
from stipi_daemon.app.daemon import run_measurement
from stipi_daemon.cli import main
from tests.daemon._support import SCENES, SHORT_MEASUREMENT, write_config


def _prony_scene(directory: Path) -> Path:
    doc = yaml.safe_load((SCENES / "tissue_prony.yaml").read_text())
    doc["name"] = "prony_daemon_e2e"
    doc["force_profile"].update({"approach_s": 1.0, "hold_s": 5.5, "recovery_s": 20.0})
    doc["camera"].update({"width": 160, "height": 120})
    path = directory / "prony_daemon_e2e.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_non_kelvin_voigt_run_carries_model_comparison(tmp_path: Path) -> None:
    scene = _prony_scene(tmp_path)
    config = write_config(
        tmp_path,
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
    models = summary["results"]["recovery_models"]
    assert models["kelvin_voigt_rejected"] is True
    assert models["best_model"] == "two_exponential"
    assert "kelvin_voigt_rejected" in summary["results"]["flags"]
    assert "kelvin_voigt_rejected" in summary["validity"]["tau_s"]["flags"]
    assert set(models["models"]) == {"kelvin_voigt", "two_exponential", "power_law"}
    for name, entry in models["models"].items():
        assert any("aicc" in k for k in entry), name
        assert entry["aicc"] is not None and entry["akaike_weight"] is not None
        assert entry["parameters"] is not None
        ci = entry["ci95"]
        assert {"tau_s", "recovery_time_s", "rebound_force_n", "viscosity_n_s_per_mm2"} <= set(ci)
    best = models["models"]["two_exponential"]
    truth = summary["ground_truth"]
    for key, truth_key in (("tau_s", "time_constant_s"), ("recovery_time_s", "recovery_time_s")):
        low, high = best["ci95"][key]
        assert low <= best[key] <= high
        assert abs(best[key] / truth[truth_key] - 1.0) < 0.05, (key, best[key], truth[truth_key])
    # The paper's estimator and the Kelvin-Voigt fit are still there, unchanged in form.
    assert (
        summary["results"]["fitted_recovery"]["tau_s"]
        == models["models"]["kelvin_voigt"]["parameters"]["tau_s"]
    )
    out = tmp_path / "re.json"
    assert main(["analyze", str(session), "--out", str(out)]) == 0
    again = json.loads(out.read_text())["summary"]["results"]["recovery_models"]
    assert again == models
