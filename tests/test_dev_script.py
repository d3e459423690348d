"""``./dev`` says what its first-run setup does, one line per step, and later runs say nothing.

The real setup downloads and builds for about 90 s, so the script runs here in a copy of the
repository's top level with a stand-in interpreter: ``PYTHON`` names a script that plays
``python3 -m venv DIR`` (it writes ``DIR/bin/python``, the same script) and, as the venv's
python, records every ``-m pip install`` and ``uninstall`` it is asked for and answers the
script's questions (the dependency list, read by the real interpreter from the real
``pyproject.toml``; whether the S_k kernel imports; ``pip show``, whether a package is
installed, from ``FAKE_INSTALLED``). What is checked is the script's own
behaviour: its lines on stderr, the pip steps it runs, the stamp it keeps.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

FAKE_PYTHON = f"""#!/usr/bin/env bash
# Stand-in interpreter for the dev script's test (see the test module's docstring).
log="$FAKE_LOG"
if [ "$1" = "--version" ]; then echo "Python 3.11.99"; exit 0; fi
if [ "$1" = "-m" ] && [ "$2" = "venv" ]; then
  mkdir -p "$3/bin" && cp "$0" "$3/bin/python" && chmod +x "$3/bin/python"; exit 0
fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ] && [ "$3" = "show" ]; then
  # as pip: 1 for a package that is not installed (FAKE_INSTALLED lists those that are)
  [[ " $FAKE_INSTALLED " == *" ${{@: -1}} "* ]]; exit
fi
if [ "$1" = "-m" ] && [ "$2" = "pip" ]; then
  shift 2; echo "pip $*" >> "$log"
  echo "pip chatter that the script must keep out of sight"
  if [ -n "$FAKE_PIP_FAIL" ] && [[ "$*" == *"$FAKE_PIP_FAIL"* ]]; then
    echo "ERROR: no matching distribution" >&2; exit 1
  fi
  exit 0
fi
if [ "$1" = "-c" ]; then
  case "$2" in
    *_skcount*) exit "${{FAKE_KERNEL_MISSING:-0}}" ;;
    *) exec {sys.executable} "$@" ;;
  esac
fi
echo "unexpected: $*" >&2; exit 99
"""


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    """A copy of what ``./dev`` reads, and the stand-in interpreter."""
    root = tmp_path / "repo"
    (root / "stipi_daemon" / "analysis").mkdir(parents=True)
    for name in ("dev", "pyproject.toml", "setup.py", "stipi_daemon/analysis/_skcount.c"):
        shutil.copy2(REPO / name, root / name)
    fake = tmp_path / "python-stand-in"
    fake.write_text(FAKE_PYTHON)
    fake.chmod(0o755)
    return root


def _dev(root: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    full = {
        **os.environ,
        "PYTHON": str(root.parent / "python-stand-in"),
        "FAKE_LOG": str(root.parent / "pip.log"),
        **env,
    }
    return subprocess.run(
        [str(root / "dev"), *args], capture_output=True, text=True, env=full, timeout=60
    )


def _pip_calls(root: Path) -> list[str]:
    log = root.parent / "pip.log"
    return log.read_text().splitlines() if log.exists() else []


def test_first_run_says_each_step_and_later_runs_are_silent(tree: Path) -> None:
    first = _dev(tree, "help")
    assert first.returncode == 0, first.stderr
    lines = first.stderr.splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith("dev: creating .venv with Python 3.11.99 (first run")
    assert lines[1].startswith("dev: installing dependencies into .venv")
    assert lines[2].startswith("dev: building the S_k kernel (stipi_daemon/analysis/_skcount.c)")
    assert "pip chatter" not in first.stdout + first.stderr
    assert "./dev demo" in first.stdout  # the command itself still ran
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    calls = _pip_calls(tree)
    assert calls[0].startswith("pip install --disable-pip-version-check --upgrade pip")
    for requirement in project["dependencies"] + project["optional-dependencies"]["dev"]:
        assert requirement in calls[1].split(), requirement
    assert calls[2] == "pip install --disable-pip-version-check --no-deps -e .[dev]"
    assert (tree / ".venv" / ".stipi-installed").is_file()

    again = _dev(tree, "help")
    assert again.returncode == 0
    assert again.stderr == ""
    assert len(_pip_calls(tree)) == 3  # nothing reinstalled

    with (tree / "setup.py").open("a") as f:
        f.write("# changed\n")
    changed = _dev(tree, "help")
    assert changed.stderr.splitlines()[0] == (
        "dev: pyproject.toml, setup.py or the S_k kernel's source changed: updating .venv"
    )
    assert len(changed.stderr.splitlines()) == 3


def test_an_older_venvs_opencv_contrib_build_is_replaced_by_the_plain_one(tree: Path) -> None:
    """The project once depended on ``opencv-contrib-python-headless``; it and the plain
    build both install ``cv2/``, so an older .venv's contrib build (and any plain one over
    it) is removed before the dependencies are installed, never after."""
    _dev(tree, "help")
    (tree / ".venv" / ".stipi-installed").write_text("older\n")
    (tree.parent / "pip.log").unlink()
    run = _dev(tree, "help", FAKE_INSTALLED="opencv-contrib-python-headless")
    assert run.returncode == 0, run.stderr
    calls = _pip_calls(tree)
    both = "opencv-contrib-python-headless opencv-python-headless"
    assert calls[1] == f"pip uninstall -y {both}", calls
    assert "opencv-python-headless>=4.8" in calls[2].split(), calls
    assert "pip chatter" not in run.stdout + run.stderr
    # A .venv without the contrib build removes nothing.
    (tree / ".venv" / ".stipi-installed").write_text("older\n")
    (tree.parent / "pip.log").unlink()
    assert _dev(tree, "help").returncode == 0
    assert not [c for c in _pip_calls(tree) if "uninstall" in c]


def test_a_kernel_that_did_not_build_is_said(tree: Path) -> None:
    run = _dev(tree, "help", FAKE_KERNEL_MISSING="1")
    assert run.returncode == 0
    last = run.stderr.splitlines()[-1]
    assert last.startswith("dev: S_k kernel not built (no C compiler or Python headers?)")


def test_a_failing_step_shows_its_log_and_keeps_the_venv_marked_stale(tree: Path) -> None:
    run = _dev(tree, "help", FAKE_PIP_FAIL="numpy")
    assert run.returncode == 1
    assert "ERROR: no matching distribution" in run.stderr
    assert run.stderr.splitlines()[-1].startswith("dev: failed: ")
    assert not (tree / ".venv" / ".stipi-installed").exists()
    # Next run tries again.
    retry = _dev(tree, "help")
    assert retry.returncode == 0
    assert "installing dependencies" in retry.stderr


def test_an_old_python_is_refused_in_one_line(tree: Path, tmp_path: Path) -> None:
    old = tmp_path / "python3.9"
    old.write_text("#!/usr/bin/env bash\n[ \"$1\" = --version ] && echo 'Python 3.9.2'\nexit 1\n")
    old.chmod(0o755)
    run = _dev(tree, "help", PYTHON=str(old))
    assert run.returncode == 1
    assert run.stderr.splitlines() == [
        f"dev: {old} is not Python >= 3.11 (Python 3.9.2): give one as PYTHON=python3.11 ./dev"
    ]


def test_the_stand_in_answers_pip_show_as_pip_does() -> None:
    """The stand-in's ``pip show`` answers (0: installed, 1: not) are the real pip's, which
    ``./dev`` relies on to find an older .venv's OpenCV contrib build."""

    def status(name: str) -> int:
        cmd = [sys.executable, "-m", "pip", "show", "-q", name]
        return subprocess.run(cmd, capture_output=True, timeout=60).returncode

    assert status("pytest") == 0
    assert status("stipi-no-such-package") == 1
