"""Scene files: shipped scenes load; unknown keys and effects are errors naming file and path."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from stipi_daemon.errors import ConfigError
from stipi_daemon.sim.scene import GRADE_PRESETS, load_scene

SCENES = Path(__file__).resolve().parents[2] / "configs" / "scenes"


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.yaml")), ids=lambda p: p.stem)
def test_shipped_scenes_load(path: Path) -> None:
    scene = load_scene(path)
    assert scene.name == path.stem


def test_grade_presets_use_instron_moduli() -> None:
    assert {g: v[0] for g, v in GRADE_PRESETS.items()} == {
        "I": 355.59,
        "II": 266.37,
        "III": 221.35,
        "IV": 185.91,
    }


def _write(tmp_path: Path, data: dict[str, object], name: str = "s.yaml") -> Path:
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data), encoding="utf-8")
    return p


def _base() -> dict[str, object]:
    data = yaml.safe_load((SCENES / "grade3.yaml").read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def test_unknown_effect_names_file_path_and_known(tmp_path: Path) -> None:
    data = _base()
    data["effects"] = [{"name": "sensor_noise", "sigma_levels": 1.0}, {"name": "flickr"}]
    with pytest.raises(ConfigError) as exc:
        load_scene(_write(tmp_path, data, "grade3.yaml"))
    msg = str(exc.value)
    assert "grade3.yaml: effects[1].name: unknown effect 'flickr' (known: " in msg
    assert "led_flicker" in msg


def test_unknown_key_is_an_error(tmp_path: Path) -> None:
    data = _base()
    probe = data["probe"]
    assert isinstance(probe, dict)
    probe["treshold"] = 100
    with pytest.raises(ConfigError, match=r"s\.yaml: probe\.treshold: Extra inputs"):
        load_scene(_write(tmp_path, data))


def test_bad_effect_parameter_named(tmp_path: Path) -> None:
    data = _base()
    data["effects"] = [{"name": "sensor_noise", "sigma_levels": -1.0, "colour": 1}]
    with pytest.raises(ConfigError) as exc:
        load_scene(_write(tmp_path, data))
    assert "effects[0].sigma_levels" in str(exc.value)
    assert "effects[0].colour" in str(exc.value)


def test_tissue_needs_one_definition(tmp_path: Path) -> None:
    data = _base()
    data["tissue"] = {"e_kpa": 200.0}
    with pytest.raises(ConfigError, match="tissue"):
        load_scene(_write(tmp_path, data))
    data["tissue"] = {"e_kpa": 200.0, "tau_s": 3.0}
    assert load_scene(_write(tmp_path, data)).tissue.time_constant_s == 3.0
    data["tissue"] = {"e_kpa": 200.0, "eta_n_s_per_mm2": 0.6}
    assert load_scene(_write(tmp_path, data)).tissue.time_constant_s == pytest.approx(3.0)


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read"):
        load_scene(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.yaml: not valid YAML"):
        load_scene(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="must be a mapping"):
        load_scene(lst)


def test_exposure_longer_than_frame_period(tmp_path: Path) -> None:
    data = _base()
    cam = data["camera"]
    assert isinstance(cam, dict)
    cam["exposure_s"] = 0.05
    with pytest.raises(ConfigError, match="camera: exposure_s"):
        load_scene(_write(tmp_path, data))
