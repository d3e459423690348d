"""Daemon config loading: valid files load; every error names the file and the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from stipi_daemon.app.config import load_config
from stipi_daemon.errors import ConfigError
from tests.conftest import REPO_ROOT

DEMO = REPO_ROOT / "configs" / "demo.yaml"


def test_demo_config_loads_and_resolves_paths() -> None:
    cfg = load_config(DEMO)
    scene = (REPO_ROOT / "configs" / "scenes" / "demo_grade3.yaml").resolve()
    assert cfg.probe.transport.kind == "emulated"
    assert cfg.probe.transport.scene == scene  # type: ignore[union-attr]
    assert cfg.camera.kind == "simulator"
    assert cfg.camera.scene == scene  # type: ignore[union-attr]
    assert scene.is_file()
    # every device simulated in the daemon's process: the clock waits for the daemon, and
    # the demo runs unpaced (run.speed 0, which the config allows only for such a world)
    assert cfg.simulated_world and cfg.run.speed == 0.0
    assert cfg.storage.root.is_absolute()
    assert cfg.measurement.target_force_n == 16.0


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "probe.yaml"
    p.write_text(text, encoding="utf-8")
    return p


MINIMAL = (
    "probe: {transport: {kind: emulated, scene: s.yaml}}\n"
    "camera: {kind: simulator, scene: s.yaml}\n"
)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (MINIMAL + "bogus: 1\n", "field 'bogus': unknown key"),
        (
            "probe: {transport: {kind: emulated, scene: s.yaml}}\ncamera: {kind: simulator}\n",
            "field 'camera.scene': Field required",
        ),
        (
            "probe: {transport: {kind: emulated, scene: s.yaml}}\ncamera: {kind: v4l3}\n",
            "field 'camera'",
        ),
        (MINIMAL.replace("emulated", "serail"), "field 'probe.transport'"),
        ("camera: {kind: simulator, scene: s.yaml}\n", "field 'probe': Field required"),
        (
            MINIMAL + "probe: {rate_hz: 5}\n",
            "line 3: duplicate key 'probe' (already given at line 1",
        ),
        (MINIMAL + "run: {speed: -1}\n", "field 'run.speed'"),
        (MINIMAL + "measurement: {target_force_n: -1}\n", "field 'measurement.target_force_n'"),
        (MINIMAL + "imaging: {threshold_p: 300}\n", "field 'imaging.threshold_p'"),
        (MINIMAL + "storage: {commit_interval_s: 2}\n", "field 'storage.commit_interval_s'"),
        (MINIMAL + "version: 2\n", "field 'version'"),
        (MINIMAL + "analysis: {indenter_radius_mm: 0}\n", "field 'analysis.indenter_radius_mm'"),
        ("probe: [1, 2\n", "not valid YAML at line"),
        ("- 1\n- 2\n", "the config must be a mapping"),
    ],
)
def test_bad_config_names_file_and_field(tmp_path: Path, text: str, needle: str) -> None:
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    msg = str(info.value)
    assert str(p) in msg
    assert needle in msg
    assert "\n" not in msg


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config file"):
        load_config(tmp_path / "nope.yaml")


def test_nested_scene_paths_resolve(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        "probe: {transport: {kind: ble, name: STIPI-01, emulate: {scene: sc/a.yaml}}}\n"
        "camera: {kind: file, path: v/x.avi}\n",
    )
    cfg = load_config(p)
    assert cfg.probe.transport.emulate.scene == tmp_path / "sc" / "a.yaml"  # type: ignore[union-attr]
    assert cfg.camera.path == tmp_path / "v" / "x.avi"  # type: ignore[union-attr]


@pytest.mark.parametrize("name", ["probe.yaml", "probe-ble.yaml", "demo.yaml"])
def test_shipped_configs_load(name: str) -> None:
    cfg = load_config(REPO_ROOT / "configs" / name)
    assert cfg.storage.root.is_absolute()
    if name.startswith("probe"):
        assert cfg.camera.kind == "v4l2"
        assert cfg.run.speed == 1.0
        assert cfg.calibration == (REPO_ROOT / "configs" / "calibration" / "probe.json")


def test_speed_0_runs_a_simulated_world_as_fast_as_the_daemon_goes(tmp_path: Path) -> None:
    ok = tmp_path / "sim.yaml"
    ok.write_text(MINIMAL + "run: {speed: 0}\n")
    assert load_config(ok).run.speed == 0.0
    real = tmp_path / "real.yaml"
    real.write_text(
        "probe: {transport: {kind: serial, port: /dev/ttyACM0}}\n"
        "camera: {kind: simulator, scene: s.yaml}\nrun: {speed: 0}\n"
    )
    with pytest.raises(ConfigError, match=r"run.speed 0 \(as fast as the daemon goes\) needs"):
        load_config(real)
    wall = tmp_path / "wall.yaml"
    wall.write_text(MINIMAL + "run: {speed: 0, clock: wall}\n")
    with pytest.raises(ConfigError, match=r"run\.clock auto"):
        load_config(wall)
