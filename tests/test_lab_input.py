"""What a lab user types: config overrides, sessions found by the config, and bad input.

Every case runs the real command line (``stipi_daemon.cli.main``, or the installed entry
point in a subprocess where the output of C libraries on file descriptor 2 matters) and
checks the exit status and the one line it prints. Sessions are recorded by the real
daemon (emulated Feather on a pty, simulator camera, accelerated).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from stipi_daemon.analysis.calibration import Calibration
from stipi_daemon.analysis.calibration_procedure import (
    depth_domain_problem,
    fit_domain_warnings,
    force_domain_problem,
)
from stipi_daemon.cli import main
from tests._offline import SCENES, record_session, short_scene

REPO = Path(__file__).resolve().parent.parent
CALIBRATION_DIR = REPO / "configs" / "calibration"


def _one_error(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI expecting exit status 2 and exactly one line on stderr; that line."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("stipi-daemon: error: ")
    return err.strip().removeprefix("stipi-daemon: error: ")


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "stipi_daemon", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=120,
    )


def _daemon_scene(directory: Path, name: str) -> Path:
    """A grade scene whose operator follows the daemon's prompts (a 16.5 s hold), rendered
    small (160x120 at 20 fps) so that an accelerated run keeps up on a loaded machine."""
    doc = yaml.safe_load((SCENES / f"{name}.yaml").read_text())
    doc["force_profile"]["hold_s"] = 16.5
    doc["camera"].update({"width": 160, "height": 120, "fps": 20.0})
    doc["name"] = f"{name}_daemon"
    path = directory / f"{name}_daemon.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


@pytest.fixture(scope="module")
def session_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_session(tmp_path_factory.mktemp("lab-input-session"))


@pytest.fixture(scope="module")
def calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("lab-input-cal") / "cal.json"
    argv = [
        "calibrate",
        "--depth-pairs",
        str(CALIBRATION_DIR / "example_depth_pairs.csv"),
        "--force-pairs",
        str(CALIBRATION_DIR / "example_force_pairs.csv"),
        "--threshold",
        "128",
        "--out",
        str(out),
    ]
    assert main(argv) == 0
    return out


# --------------------------------------------------------------------------------------------
# --scene and --set
# --------------------------------------------------------------------------------------------


def _config(directory: Path, scene: Path, **sections: object) -> Path:
    doc: dict[str, object] = {
        "probe": {"transport": {"kind": "emulated", "scene": str(scene)}},
        "camera": {"kind": "simulator", "scene": str(scene)},
        "storage": {"root": "sessions", "min_free_mb": 0, "video": "off"},
        "run": {"speed": 0.0},
        **sections,
    }
    path = directory / "config.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_scene_and_set_change_one_run_without_copying_the_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = _config(tmp_path, _daemon_scene(tmp_path, "grade1"))
    other = _daemon_scene(tmp_path, "grade2")
    before = cfg.read_bytes()
    monkeypatch.chdir(tmp_path)
    argv = [
        "--config",
        str(cfg),
        "--scene",
        other.name,  # relative to the working directory
        "--set",
        "measurement.stop_when_settled=true",
        "--set",
        "run.max_lag_s=4",
        "--quiet",
    ]
    assert main(argv) == 0
    session = Path(capsys.readouterr().out.strip())
    assert session.parent == tmp_path / "sessions"  # storage.root relative to the file
    manifest = json.loads((session / "manifest.json").read_text())
    config = manifest["config"]
    assert config["camera"]["scene"] == str(other)
    assert config["probe"]["transport"]["scene"] == str(other)
    assert config["measurement"]["stop_when_settled"] is True
    assert config["run"]["max_lag_s"] == 4.0
    summary = json.loads((session / "summary.json").read_text())
    assert summary["ground_truth"]["scene"] == "grade2_daemon"
    assert cfg.read_bytes() == before


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        (
            "measurement.stop_when_settlde=true",
            "--set measurement.stop_when_settlde=true: unknown key "
            "(did you mean 'stop_when_settled'?)",
        ),
        (
            "measurement.stop_when_settled=maybe",
            "--set measurement.stop_when_settled=maybe: Input should be a valid boolean",
        ),
        ("run.speed=-1", "--set run.speed=-1: Input should be greater than or equal to 0"),
        ("imaging.threshold_p=300", "--set imaging.threshold_p=300: Input should be less than"),
        ("nosuch.key=1", "--set nosuch.key=1: field 'nosuch': unknown key"),
        ("run.speed.x=1", "--set run.speed.x=1: 'run.speed' is a value, not a section"),
        ("stop_when_settled", "--set 'stop_when_settled': expected KEY=VALUE"),
        ("imaging.roi={kind: circle}", "--set imaging.roi={kind: circle}: the value must be a"),
    ],
)
def test_a_bad_set_names_the_key(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], override: str, expected: str
) -> None:
    cfg = _config(tmp_path, SCENES / "grade1.yaml")
    line = _one_error(capsys, ["--config", str(cfg), "--set", override])
    assert line.startswith(expected), line
    assert not (tmp_path / "sessions").exists()


def test_scene_needs_a_simulated_device_and_an_existing_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    line = _one_error(
        capsys,
        ["--config", str(REPO / "configs" / "probe.yaml"), "--scene", str(SCENES / "grade1.yaml")],
    )
    assert line.startswith("--scene: ") and "has no simulated device" in line
    cfg = _config(tmp_path, SCENES / "grade1.yaml")
    line = _one_error(capsys, ["--config", str(cfg), "--scene", str(tmp_path / "nope.yaml")])
    assert line == f"--scene {tmp_path / 'nope.yaml'}: no such scene file"
    line = _one_error(capsys, ["--set", "run.speed=2", "sessions", "list"])
    assert line.startswith("--scene/--set change the config of a measurement")


# --------------------------------------------------------------------------------------------
# the sessions root: --root, else the config's storage.root, else ./sessions
# --------------------------------------------------------------------------------------------


def test_sessions_report_and_analyze_find_the_root_through_the_config(
    session_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The layout of configs/demo.yaml: the config in configs/, sessions in ../sessions.
    lab = tmp_path / "lab"
    (lab / "configs").mkdir(parents=True)
    shutil.copytree(session_dir, lab / "sessions" / session_dir.name)
    cfg = lab / "configs" / "probe.yaml"
    doc = yaml.safe_load((REPO / "configs" / "probe.yaml").read_text())
    doc["storage"]["root"] = "../sessions"
    doc.pop("calibration")  # analyze: the session's own calibration
    cfg.write_text(yaml.safe_dump(doc))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    sid = session_dir.name
    line = _one_error(capsys, ["sessions", "show", sid])  # ./sessions: not here
    assert line.startswith(f"{sid}: no such session")
    assert f"({Path('sessions') / sid})" in line  # both places looked in are named
    assert f"({elsewhere / sid})" in line

    assert main(["sessions", "list", "--config", str(cfg)]) == 0
    assert sid in capsys.readouterr().out
    assert main(["--config", str(cfg), "sessions", "list"]) == 0  # before the command too
    assert sid in capsys.readouterr().out
    assert main(["sessions", "show", sid, "--config", str(cfg)]) == 0
    assert str(lab / "sessions" / sid) in capsys.readouterr().out
    out = tmp_path / "a.json"
    # (Exit 1 or 0: the lab config's settings replace the recorded ones; what matters here
    # is that the session was found.)
    assert main(["analyze", sid, "--config", str(cfg), "--out", str(out), "--quiet"]) in (0, 1)
    assert json.loads(out.read_text())["input"]["session_id"] == sid
    capsys.readouterr()
    assert main(["report", sid, "--config", str(cfg), "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "report.html").is_file()
    capsys.readouterr()
    # --root still wins.
    line = _one_error(capsys, ["sessions", "show", sid, "--config", str(cfg), "--root", "x"])
    assert line.startswith(f"{sid}: no such session") and f"({Path('x') / sid})" in line


# --------------------------------------------------------------------------------------------
# duplicate keys
# --------------------------------------------------------------------------------------------


def test_a_config_key_given_twice_is_refused_with_its_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "dup.yaml"
    cfg.write_text(
        "probe: {transport: {kind: emulated, scene: s.yaml}}\n"
        "camera: {kind: simulator, scene: s.yaml}\n"
        "measurement:\n"
        "  stop_when_settled: true\n"
        "  target_force_n: 16\n"
        "  stop_when_settled: false\n"
    )
    line = _one_error(capsys, ["--config", str(cfg)])
    assert line == (
        f"{cfg}: line 6: duplicate key 'stop_when_settled' (already given at line 4; "
        "only one may stay)"
    )
    # The same key in two sections is fine, and a YAML merge key still overrides.
    ok = tmp_path / "ok.yaml"
    ok.write_text(
        "probe: {transport: {kind: emulated, scene: s.yaml}}\n"
        "camera: {kind: simulator, scene: s.yaml}\n"
        "measurement: {settle_fraction: 0.98}\n"
        "analysis: {settle_fraction: 0.98}\n"
    )
    assert main(["sessions", "list", "--config", str(ok), "--root", str(tmp_path)]) == 0


def test_a_scene_key_given_twice_is_refused_with_its_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = (SCENES / "grade1.yaml").read_text()
    scene = tmp_path / "dup_scene.yaml"
    scene.write_text(text + "name: again\n")
    first = next(i for i, s in enumerate(text.splitlines(), 1) if s.startswith("name:"))
    line = _one_error(capsys, ["simulate", str(scene), "--out", str(tmp_path / "out")])
    n = len(text.splitlines()) + 1
    assert line == (
        f"dup_scene.yaml: line {n}: duplicate key 'name' (already given at line {first}; "
        "only one may stay)"
    )
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------
# analyze's options
# --------------------------------------------------------------------------------------------


def test_analyze_refuses_a_threshold_it_cannot_use(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "a.json"
    for bad in ("300", "-1"):
        line = _one_error(capsys, ["analyze", str(session_dir), "--threshold", bad])
        assert line == (
            f"--threshold {bad}: out of range, threshold p of Eq. (1) is a gray level 0..255"
        )
    # In range, but a stored session's S_k was counted live: the value would be ignored.
    line = _one_error(capsys, ["analyze", str(session_dir), "--threshold", "100"])
    assert line.startswith("--threshold applies where S_k is counted")
    assert not out.exists()
    assert not list(session_dir.glob("analysis-*.json"))


def test_analyze_out_is_never_overwritten_silently(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "a.json"
    out.write_text("earlier results")
    line = _one_error(capsys, ["analyze", str(session_dir), "--out", str(out)])
    assert line == f"--out {out}: exists already (give --overwrite to replace it)"
    assert out.read_text() == "earlier results"
    line = _one_error(capsys, ["analyze", str(session_dir), "--out", str(tmp_path / "no" / "a")])
    assert line.startswith(f"--out {tmp_path / 'no' / 'a'}: directory ")
    # (1: results flagged, e.g. the recording fell behind on a loaded machine; still written.)
    assert main(["analyze", str(session_dir), "--out", str(out), "--overwrite", "--quiet"]) in (
        0,
        1,
    )
    assert json.loads(out.read_text())["input"]["kind"] == "session"
    line = _one_error(capsys, ["analyze", str(session_dir), "--overwrite"])
    assert line.startswith("--overwrite applies to --out")


def test_analyze_roi_errors_name_the_field(
    session_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["analyze", str(session_dir), "--recompute-sk", "--roi"]
    line = _one_error(capsys, [*argv, "circle:10,10,-3"])
    assert line == "--roi 'circle:10,10,-3': radius_px: Input should be greater than 0"


# --------------------------------------------------------------------------------------------
# --overwrite everywhere, --force a deprecated alias
# --------------------------------------------------------------------------------------------


def test_export_takes_overwrite_and_still_the_old_force(
    session_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "export"
    args = ["sessions", "export", str(session_dir), "--format", "csv", "--out", str(out)]
    assert main(args) == 0
    line = _one_error(capsys, args)
    assert "exists already (use --overwrite to replace it)" in line
    assert main([*args, "--overwrite"]) == 0
    assert capsys.readouterr().err == ""
    assert main([*args, "--force"]) == 0
    assert capsys.readouterr().err == "stipi-daemon: note: --force is deprecated, use --overwrite\n"
    helps = [
        _cli("sessions", "export", "--help").stdout,
        _cli("calibrate", "--help").stdout,
        _cli("analyze", "--help").stdout,
    ]
    assert all("--overwrite" in h for h in helps)
    assert "--force" not in helps[0]  # hidden


# --------------------------------------------------------------------------------------------
# free space
# --------------------------------------------------------------------------------------------


def test_free_space_error_names_the_config_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _config(tmp_path, SCENES / "grade1.yaml")
    line = _one_error(capsys, ["--config", str(cfg), "--set", "storage.min_free_mb=1e12"])
    assert line.startswith(f"not enough free disk space for a new session in {tmp_path}")
    assert line.endswith("(config field storage.min_free_mb = 1e+12 MB)")
    assert not any((tmp_path / "sessions").iterdir())


# --------------------------------------------------------------------------------------------
# a file that is not a video: our one line, nothing from OpenCV or FFmpeg
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "content", [b"this is not a video\n" * 100, bytes(range(256)) * 80, b""], ids=str
)
def test_not_a_video_gives_exactly_one_line(
    tmp_path: Path, calibration: Path, content: bytes
) -> None:
    for name in ("clip.avi", "clip.mp4"):
        video = tmp_path / name
        video.write_bytes(content)
        force = tmp_path / "force.csv"
        force.write_text("t_s,force_n\n0,0\n0.01,0\n")
        run = _cli(
            "analyze", "--video", str(video), "--force", str(force),
            "--calibration", str(calibration),
        )  # fmt: skip
        assert run.returncode == 2
        assert run.stderr.splitlines() == [
            f"stipi-daemon: error: {video}: OpenCV cannot open this video (Invalid data found "
            "when processing input)"
        ], run.stderr
        cfg = _config(tmp_path, SCENES / "grade1.yaml", camera={"kind": "file", "path": name})
        run = _cli("--config", str(cfg), "--quiet", "--set", f"calibration={calibration}")
        assert run.returncode == 2
        assert run.stderr.splitlines() == [
            f"stipi-daemon: error: video file {video}: not a video OpenCV/FFmpeg can read "
            "(Invalid data found when processing input)"
        ], run.stderr


# --------------------------------------------------------------------------------------------
# a killed session on read-only media
# --------------------------------------------------------------------------------------------


def _killed_daemon_session(directory: Path) -> Path:
    """Start the real daemon, SIGKILL it mid-measurement; its session directory."""
    directory.mkdir()
    cfg = _config(directory, _daemon_scene(directory, "grade1"), run={"speed": 1.0})
    proc = subprocess.Popen(
        [sys.executable, "-m", "stipi_daemon", "--config", str(cfg), "--quiet"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            wal = list((directory / "sessions").glob("*/session.sqlite-wal"))
            if wal and wal[0].stat().st_size > 64 * 1024:
                break
            time.sleep(0.2)
        else:
            pytest.fail("the daemon wrote no WAL within 60 s")
        time.sleep(0.5)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)
    return wal[0].parent


def _sqlite_rows(db: Path, *, immutable: bool = False) -> dict[str, int]:
    """Row counts as SQLite reads them: a writable copy (recovering its WAL), or the
    database file alone (``immutable``: the WAL ignored; tables it does not hold yet are
    left out)."""
    uri = db.as_uri() + ("?immutable=1" if immutable else "")
    conn = sqlite3.connect(uri, uri=True)
    try:
        names = {r[0] for r in conn.execute("SELECT name FROM sqlite_master")}
        return {
            t: conn.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
            for t in ("force_samples", "frames", "events")
            if t in names
        }
    finally:
        conn.close()


def _read_only_run(directory: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run the CLI with ``directory`` on a read-only file system (bind mount, own namespace).

    ``unshare --user --map-root-user --mount`` gives the command a private mount namespace
    in which ``directory`` is remounted read-only (EROFS even for root); nothing outside
    the command sees the mount. Without it, a non-root user gets a read-only directory.
    """
    command = [sys.executable, "-m", "stipi_daemon", *args]
    probe = subprocess.run(
        ["unshare", "-rm", "sh", "-c", f"mount --bind {directory} {directory}"],
        capture_output=True,
    )
    if probe.returncode == 0:
        script = (
            f'mount --bind "{directory}" "{directory}" && '
            f'mount -o remount,ro,bind "{directory}" && exec "$@"'
        )
        argv = ["unshare", "-rm", "sh", "-c", script, "sh", *command]
        return subprocess.run(argv, capture_output=True, text=True, timeout=120)
    if os.geteuid() == 0:
        pytest.skip("no mount namespace for a read-only mount, and root ignores permissions")
    for p in [directory, *directory.iterdir()]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def test_a_killed_session_on_read_only_media_reads_fine(tmp_path: Path) -> None:
    killed = _killed_daemon_session(tmp_path / "run")
    assert (killed / "session.sqlite-wal").stat().st_size > 0
    # As copied to a USB stick, without the -shm: (1) with the -wal the killed recorder
    # left; (2) after SQLite checkpointed it elsewhere (the database file alone, still in
    # WAL mode). The oracle is SQLite's own recovery of a writable copy.
    oracle = tmp_path / "oracle"
    oracle.mkdir()
    for name in ("session.sqlite", "session.sqlite-wal"):
        shutil.copy2(killed / name, oracle / name)
    in_db_file_alone = _sqlite_rows(oracle / "session.sqlite", immutable=True)
    expected = _sqlite_rows(oracle / "session.sqlite")  # recovers, checkpoints on close
    assert expected["force_samples"] > in_db_file_alone.get("force_samples", 0)
    assert not (oracle / "session.sqlite-wal").exists()
    media_files = {
        "with_wal": {n: killed / n for n in ("session.sqlite", "session.sqlite-wal")},
        "checkpointed": {"session.sqlite": oracle / "session.sqlite"},
    }
    for case, files in media_files.items():
        media = tmp_path / case / killed.name
        media.mkdir(parents=True)
        shutil.copy2(killed / "manifest.json", media / "manifest.json")
        for name, source in files.items():
            shutil.copy2(source, media / name)
        run = _read_only_run(media, "sessions", "show", str(media))
        assert "truncated or corrupt" not in run.stdout + run.stderr, run.stderr
        assert run.stderr == "", run.stderr
        assert "status     interrupted" in run.stdout
        listed = run.stdout.split("rows:\n")[1].split("manifest:")[0].splitlines()
        rows = dict(line.split() for line in listed)
        for table, n in expected.items():
            assert int(rows[table]) == n, (case, table)
        assert sorted(p.name for p in media.iterdir()) == sorted(["manifest.json", *files])
    # Damage is still called damage.
    broken = tmp_path / "broken" / "s"
    broken.mkdir(parents=True)
    shutil.copy2(killed / "manifest.json", broken / "manifest.json")
    (broken / "session.sqlite").write_bytes(b"garbage" * 1000)
    run = _read_only_run(broken, "sessions", "show", str(broken))
    assert run.returncode == 4  # damaged stored data (stipi_daemon.errors.EXIT_DAMAGED)
    assert run.stderr.splitlines() == [
        f"stipi-daemon: error: {broken / 'session.sqlite'}: not a readable SQLite database, "
        "truncated or corrupt (file is not a database)"
    ]


# --------------------------------------------------------------------------------------------
# calibrate: the domain of Eqs. (3)-(5)
# --------------------------------------------------------------------------------------------


def test_depth_domain_edges() -> None:
    assert depth_domain_problem([0.0, 6.0, 12.0], 12.0) is None  # both ends belong to it
    assert depth_domain_problem([0.0, 12.000001], 12.0) == (
        1,
        "d_s = 12 mm is above l = 12 mm: Eq. (3) needs 0 <= d_s <= l "
        "(D_p = l - d_s would be -1e-06 mm)",
    )
    index, why = depth_domain_problem([1.0, -0.5], 12.0) or (None, "")
    assert index == 1 and why.startswith("d_s = -0.5 mm is below 0")
    assert depth_domain_problem([float("nan")], 12.0) is not None
    assert force_domain_problem([0.0, 5.0]) is None
    assert force_domain_problem([1.0, -0.1]) == (
        1,
        "F = -0.1 N is negative: Eq. (5) needs a pressing force F >= 0",
    )


def test_fit_leaving_the_domain_inside_its_range_is_flagged() -> None:
    inside = Calibration(2e-7, 3e-3, 100.0, 200.0, 12.0, s0_valid_range_px=(500.0, 5000.0))
    assert fit_domain_warnings(inside) == []
    # Linear Eq. (4) (alpha1 = 0) of 2e-3 mm/px: d_s = 14 mm at the top of its range.
    steep = Calibration(0.0, 2e-3, 100.0, 200.0, 12.0, s0_valid_range_px=(500.0, 7000.0))
    (line,) = fit_domain_warnings(steep)
    assert line.startswith("Eq. (4) reaches d_s = 14 mm > l = 12 mm at S0 = 7000 px")


def test_calibrate_refuses_depth_changes_outside_eq3(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # d_s up to 31 mm with l = 12 mm (D_p down to -19 mm): a smooth Eq. (4) whose points
    # leave [0, l] from S0 = 4000 px on (d_s = 14.8 mm, line 5).
    pairs = tmp_path / "depth.csv"
    rows = [(s, round(-1e-7 * s * s + 4.1e-3 * s, 6)) for s in range(1000, 10001, 1000)]
    assert rows[-1][1] == 31.0
    pairs.write_text("s0_px,depth_change_mm\n" + "".join(f"{s},{d}\n" for s, d in rows))
    out = tmp_path / "cal.json"
    force = str(CALIBRATION_DIR / "example_force_pairs.csv")
    argv = ["calibrate", "--depth-pairs", str(pairs), "--force-pairs", force, "--out", str(out)]
    line = _one_error(capsys, argv)
    assert line == (
        f"{pairs}: line 5: d_s = 14.8 mm is above l = 12 mm: Eq. (3) needs 0 <= d_s <= l "
        "(D_p = l - d_s would be -2.8 mm); check the column's unit, or --indenter-length"
    )
    assert not out.exists()
    # A longer indenter takes them.
    assert main([*argv, "--indenter-length", "40"]) == 0
    assert out.exists()
    capsys.readouterr()
    bad_force = tmp_path / "force.csv"
    bad_force.write_text("s_px,force_n\n100,1\n200,-2\n300,3\n")
    line = _one_error(
        capsys,
        ["calibrate", "--depth-pairs", str(CALIBRATION_DIR / "example_depth_pairs.csv"),
         "--force-pairs", str(bad_force), "--out", str(tmp_path / "c2.json")],
    )  # fmt: skip
    assert line.startswith(f"{bad_force}: line 3: F = -2 N is negative")


@pytest.mark.parametrize(
    ("option", "value", "expected"),
    [
        ("--indenter-length", "0", "--indenter-length 0: must be > 0 mm"),
        ("--indenter-length", "nan", "--indenter-length nan: must be > 0 mm"),
        ("--plateau-tolerance", "-1", "--plateau-tolerance -1: must be > 0 N"),
        ("--plateau-min", "0", "--plateau-min 0: must be > 0 s"),
        ("--min-force", "-1", "--min-force -1: must be >= 0 N"),
        ("--trim", "-0.5", "--trim -0.5: must be >= 0 s"),
        ("--threshold", "256", "--threshold 256: out of range"),
    ],
)
def test_calibrate_option_values_name_the_option(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, value: str, expected: str
) -> None:
    argv = [
        "calibrate",
        "--depth-pairs",
        str(CALIBRATION_DIR / "example_depth_pairs.csv"),
        "--force-pairs",
        str(CALIBRATION_DIR / "example_force_pairs.csv"),
        "--out",
        str(tmp_path / "cal.json"),
        option,
        value,
    ]
    assert _one_error(capsys, argv).startswith(expected)


def test_short_scene_helper_still_loads(tmp_path: Path) -> None:
    # The strict loader reads what yaml.safe_dump writes (the tests' own scenes).
    from stipi_daemon.sim import load_scene

    assert load_scene(short_scene(tmp_path)).name == "grade1_short"


def test_video_off_unquoted_means_off(tmp_path: Path) -> None:
    # YAML 1.1 reads an unquoted `off` as false: in the file and in --set alike
    from stipi_daemon.app.config import load_config

    cfg = _config(tmp_path, SCENES / "grade1.yaml")
    text = cfg.read_text().replace("video: 'off'", "video: off")
    assert "video: off" in text
    cfg.write_text(text)
    assert load_config(cfg).storage.video == "off"
    cfg.write_text(text.replace("video: off", "video: lossless"))
    assert load_config(cfg, overrides=["storage.video=off"]).storage.video == "off"
