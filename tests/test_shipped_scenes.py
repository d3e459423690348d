"""Every shipped scene runs through the daemon with ``configs/demo.yaml`` to a result.

Each scene of ``configs/scenes`` is given to the demo config on the command line, as
README shows it (``stipi-daemon --config configs/demo.yaml --scene SCENE``), and must end
in a measurement that was made (exit 0, phase done, results computed), the same on
every machine (the runs are on the clock that waits for the daemon). The session
video is left off (``storage.video off``): it is not what this checks, and its encoder is
most of a run's cost. The runs are simulated on the clock that waits for the daemon, so
they end the same on any machine.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from stipi_daemon.cli import main
from tests.conftest import REPO_ROOT

SCENES = sorted((REPO_ROOT / "configs" / "scenes").glob("*.yaml"))


def test_every_scene_is_checked() -> None:
    assert len(SCENES) >= 17, [s.name for s in SCENES]


@pytest.mark.timeout(900)
@pytest.mark.parametrize("scene", SCENES, ids=[s.stem for s in SCENES])
def test_scene_measures_with_the_demo_config(
    scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [
        "--config",
        str(REPO_ROOT / "configs" / "demo.yaml"),
        "--scene",
        str(scene),
        "--set",
        "storage.video=off",
        "--set",
        "storage.video_roi_only=false",
        "--set",
        f"storage.root={tmp_path / 'sessions'}",
        "--quiet",
    ]
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 0, err
    session = Path(out.strip().splitlines()[-1])
    summary = json.loads((session / "summary.json").read_text())
    assert summary["phase"] == "done", summary["end_reason"]
    assert summary["results"]["pitting"]["depth_mm"] is not None
    assert summary["run"]["clock"] == "simulated"
