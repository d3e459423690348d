"""One rule for the session a command names (``sessions show``/``export``, ``analyze``,
``report``): :func:`stipi_daemon.app.config.find_session`."""

from __future__ import annotations

from pathlib import Path

import pytest

from stipi_daemon.app.config import find_session
from stipi_daemon.cli import main
from stipi_daemon.errors import SessionError


@pytest.fixture
def places(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Path, Path]:
    """A sessions root and a current directory elsewhere, each with a directory ``S``."""
    root, here = tmp_path / "sessions", tmp_path / "here"
    (root / "S").mkdir(parents=True)
    (here / "S").mkdir(parents=True)
    (here / "only-here").mkdir()
    monkeypatch.chdir(here)
    return root, here


def test_an_id_under_the_root_comes_before_a_directory_here(places: tuple[Path, Path]) -> None:
    root, _ = places
    assert find_session(root, "S") == root / "S"
    assert find_session(root, "only-here") == Path("only-here")
    assert find_session(root, "./S") == Path("./S")  # a path is taken as it is
    assert find_session(root, ".") == Path(".")  # not the root itself (root / ".")
    assert find_session(root, "..") == Path("..")


@pytest.mark.parametrize("text", ["nowhere", ""])
def test_a_name_in_neither_place_names_both(places: tuple[Path, Path], text: str) -> None:
    root, here = places
    with pytest.raises(SessionError) as raised:
        find_session(root, text)
    message = str(raised.value)
    assert message.startswith(f"{text}: no such session") and "\n" not in message
    assert f"({root / text})" in message and f"({here / text})" in message


@pytest.mark.parametrize(
    "argv",
    [
        ["sessions", "show", "nowhere"],
        ["sessions", "export", "nowhere"],
        ["analyze", "nowhere"],
        ["report", "nowhere"],
        ["report", "--compare", "S", "nowhere"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_every_command_says_the_same_line(
    places: tuple[Path, Path], argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    root, here = places
    assert main([*argv, "--root", str(root)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.strip() == (
        f"stipi-daemon: error: nowhere: no such session: neither a session id in the "
        f"sessions directory ({root / 'nowhere'}) nor a directory in the current one "
        f"({here / 'nowhere'}) (list them: stipi-daemon sessions list)"
    )
