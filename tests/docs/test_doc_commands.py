"""Every shell block of README.md and docs/*.md runs as written (issue 36, point 3).

The blocks are run in a temporary copy of the repository (the files ``git ls-files``
lists, tracked and untracked-but-not-ignored, as they are in the work tree), whose
``.venv`` is a symlink to this repository's: ``./dev`` in the copy finds it up to date
(its stamp hashes ``pyproject.toml``, ``setup.py`` and the S_k kernel's C source, the same
in the copy) and installs nothing; the fixture checks both. One copy serves the whole
module and its blocks run in document order (README.md, then docs/*.md by name), so a
block may use what an earlier one made (sessions, ``study/``, ``cal.json``), as a reader
who follows the documents in that order would have it.

Each block is a bash script run in the copy's root with the environment README gives a
user: ``. .venv/bin/activate`` done (``VIRTUAL_ENV`` set, ``.venv/bin`` first on
``PATH``), so ``stipi-daemon`` and ``./dev stipi-daemon`` both work. A script runs
with ``set -eo pipefail``: it fails when any command exits non-zero, and when anything
prints a Python traceback. (The venv's editable install imports ``stipi_daemon`` from this
work tree, which the copy equals; configs, scenes and outputs are the copy's.)

Which blocks: a fenced block whose language is ``sh``, ``bash``, ``shell`` or
``console`` is a shell block and is run. A fence without a language is an error (say
``sh`` for commands, ``text`` for diagrams, listings and output); a block of another
language (``text``, ``yaml``, ``sql``, ...) must not hold a command line (a line
starting with ``stipi-daemon``, ``./dev``, ``.venv/``, ``make`` or ``sqlite3``): commands
belong in shell blocks. ``python`` blocks are run by ``tests/test_docs.py``.

Markers. An HTML comment on the line right above a shell block's fence (invisible on
GitHub) says how the block is treated; without one the block is ``run``::

    <!-- doc-test: KIND [KEY=VALUE ...] -->

KIND is one of

``run``
    run the block as a script (the default).
``output``
    the block shows commands and their output: only the command lines (a line starting
    with ``stipi-daemon ``, ``./dev ``, ``.venv/``, ``make `` or ``sqlite3 ``, with its
    continuations: a trailing backslash or an open quote) are run, in one script; the
    output lines are not compared.
``hardware``
    each command needs the real probe, camera or radio: it is run on its own and must
    exit non-zero, print no traceback and exactly one line on stderr (``make``'s own
    ``make: ***`` lines aside) containing its ``error="..."`` fragment. Give one
    ``error`` for all commands or one per command, in order. ``calibration=PATH``
    writes a stand-in for the user's probe calibration (fitted from the shipped example
    pairs at 1280x720, as configs/probe.yaml's camera) at PATH before the commands run
    and removes it after, so the commands get as far as the hardware.
``two-terminals``
    two commands for two terminals: the first (a server, e.g. ``mock-peripheral``) is
    started in the background, the second (run once the first has printed its first
    line, as a user waits for it) must succeed as in ``run``, then the first
    is sent SIGINT (Ctrl-C) and must exit 0 or 130 without a traceback.
``skip``
    not run; ``reason="..."`` is required. Only for what cannot run here or is the suite
    itself; ``test_skipped_blocks_are_the_expected_ones`` lists them.

Other ``KEY=VALUE`` pairs (on ``run`` and ``output`` blocks) are placeholders: every
occurrence of KEY in the block (as a whole word when KEY is a word) is replaced before
running by VALUE, which is ``newest-session`` or ``oldest-session`` (the id of the newest or
oldest session in the copy's ``sessions/``, made by earlier blocks), or ``session:N``
(the N-th session by creation, from 1). A block whose text is identical to one already
run successfully in the copy (README.md and docs/bench.md show the same two-terminal
bench) is not run again.
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SHELL_LANGS = frozenset({"sh", "bash", "shell", "console"})
KINDS = frozenset({"run", "output", "hardware", "two-terminals", "skip"})
RESERVED_KEYS = frozenset({"reason", "error", "calibration"})
COMMAND_START = re.compile(r"^(stipi-daemon |\./dev |\.venv/|make |sqlite3 )")
MAKE_LINE = re.compile(r"^make(\[\d+\])?: ")
TRACEBACK = "Traceback (most recent call last)"
FENCE = re.compile(r"^```([^\n`]*)\n(.*?)^```[ \t]*$", re.S | re.M)
MARKER = re.compile(r"^<!--\s*doc-test:\s*(.*?)\s*-->\s*$")

#: The blocks not run, by document and a fragment of their text: each is the suite itself
#: or needs what a test machine does not have. A new skip must be added here too.
EXPECTED_SKIPS = frozenset(
    {
        ("README.md", "./dev test"),
        ("docs/calibration.md", "--depth-recording sessions/<depth-run-id>"),
        ("docs/firmware.md", "make -C firmware/feather32u4 host-test"),
        ("docs/reliability.md", "./dev pytest tests/reliability -m slow"),
        ("docs/reliability.md", ".venv/bin/python -m tests.faults.matrix"),
        ("docs/reliability.md", "tests.faults.matrix --laws --speed 0 --out"),
        ("docs/simavr_hil.md", "make -C firmware/feather32u4 && make -C"),
    }
)

BLOCK_TIMEOUT_S = 900
#: How long terminal 1 (a server) may take to print its first line [s].
SERVER_READY_TIMEOUT_S = 120.0
#: Attempts at starting terminal 1 while its fixed port is taken, and the wait between [s].
PORT_IN_USE_ATTEMPTS = 6
PORT_IN_USE_WAIT_S = 10.0
MODULE_TIMEOUT_S = 2400

pytestmark = [pytest.mark.xdist_group("docs")]


@dataclass(frozen=True)
class Block:
    """One fenced block of a document and the marker above it."""

    doc: str
    line: int
    lang: str
    text: str
    marker: str | None
    kind: str
    options: tuple[tuple[str, str], ...]

    @property
    def where(self) -> str:
        return f"{self.doc}:{self.line}"

    @property
    def first_line(self) -> str:
        return self.text.splitlines()[0].strip() if self.text.strip() else ""

    def values(self, key: str) -> list[str]:
        return [v for k, v in self.options if k == key]

    @property
    def placeholders(self) -> dict[str, str]:
        return {k: v for k, v in self.options if k not in RESERVED_KEYS}


def documents() -> list[str]:
    return ["README.md", *sorted(p.relative_to(REPO).as_posix() for p in REPO.glob("docs/*.md"))]


def parse_marker(text: str) -> tuple[str, tuple[tuple[str, str], ...]]:
    words = shlex.split(text)
    if not words:
        raise ValueError("empty doc-test marker")
    kind, options = words[0], []
    if kind == "placeholders":
        kind = "run"
    for word in words[1:]:
        key, eq, value = word.partition("=")
        if not eq:
            raise ValueError(f"doc-test marker: {word!r} is not KEY=VALUE")
        options.append((key, value))
    return kind, tuple(options)


def parse_blocks(doc: str) -> list[Block]:
    text = (REPO / doc).read_text(encoding="utf-8")
    blocks = []
    for m in FENCE.finditer(text):
        before = text[: m.start()].rstrip("\n").split("\n")
        above = before[-1] if before else ""
        found = MARKER.match(above.strip())
        marker = found.group(1) if found else None
        lang = m.group(1).strip()
        kind: str
        options: tuple[tuple[str, str], ...]
        if marker is None:
            kind, options = ("run" if lang in SHELL_LANGS else "none"), ()
        else:
            kind, options = parse_marker(marker)
        blocks.append(
            Block(
                doc=doc,
                line=text[: m.start()].count("\n") + 1,
                lang=lang,
                text=m.group(2),
                marker=marker,
                kind=kind,
                options=options,
            )
        )
    return blocks


ALL_BLOCKS = [b for doc in documents() for b in parse_blocks(doc)]
SHELL_BLOCKS = [b for b in ALL_BLOCKS if b.lang in SHELL_LANGS]


def logical_lines(text: str) -> list[str]:
    """Lines joined across trailing backslashes and open quotes; blank and comment lines dropped."""
    out: list[str] = []
    pending = ""
    for raw in text.splitlines():
        pending = f"{pending}\n{raw}" if pending else raw
        if pending.endswith("\\"):
            continue
        try:
            shlex.split(pending, comments=True)
        except ValueError:  # an open quote: the command goes on on the next line
            continue
        if pending.strip() and not pending.lstrip().startswith("#"):
            out.append(pending)
        pending = ""
    if pending.strip():
        out.append(pending)
    return out


def output_commands(text: str) -> list[str]:
    """The command lines of an ``output`` block, with their continuation lines."""
    out: list[str] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if not COMMAND_START.match(lines[i]):
            i += 1
            continue
        command = lines[i]
        i += 1
        while command.endswith("\\") or not _complete(command):
            if i >= len(lines):
                break
            command = f"{command}\n{lines[i]}"
            i += 1
        out.append(command)
    return out


def _complete(command: str) -> bool:
    try:
        shlex.split(command, comments=True)
    except ValueError:
        return False
    return True


def problems(block: Block) -> list[str]:
    """Why a block is not covered (empty: it is run, or skipped with a reason)."""
    where = block.where
    if block.lang == "":
        return [f"{where}: fence without a language: `sh` for commands, `text` otherwise"]
    if block.lang not in SHELL_LANGS:
        out = []
        if block.marker is not None:
            out.append(f"{where}: doc-test marker above a {block.lang!r} block")
        if block.lang != "python":
            out += [
                f"{where}: command line in a {block.lang!r} block (make it `sh`): {line}"
                for line in block.text.splitlines()
                if COMMAND_START.match(line)
            ]
        return out
    if block.kind not in KINDS:
        return [f"{where}: unknown doc-test kind {block.kind!r} (known: {sorted(KINDS)})"]
    out = []
    if block.kind == "skip" and not block.values("reason"):
        out.append(f"{where}: skip without reason=")
    if block.kind == "hardware":
        errors, commands = block.values("error"), logical_lines(block.text)
        if not errors or len(errors) not in (1, len(commands)):
            out.append(f"{where}: hardware needs one error= or one per command")
    if block.kind == "two-terminals" and len(logical_lines(block.text)) != 2:
        out.append(f"{where}: two-terminals needs exactly two commands")
    if block.kind == "output" and not output_commands(block.text):
        out.append(f"{where}: output block without a command: make it `text`")
    for key, value in block.placeholders.items():
        if not re.fullmatch(r"newest-session|oldest-session|session:[1-9]\d*", value):
            out.append(f"{where}: placeholder {key}={value!r}: unknown source")
        elif block.kind not in ("run", "output"):
            out.append(f"{where}: placeholders only on run and output blocks")
        elif key not in block.text:
            out.append(f"{where}: placeholder {key} does not occur in the block")
    return out


# --- the copy and the runs ------------------------------------------------------------


def venv_stamp_wanted(root: Path) -> str:
    data = b"".join(
        (root / p).read_bytes()
        for p in ("pyproject.toml", "setup.py", "stipi_daemon/analysis/_skcount.c")
    )
    return hashlib.sha256(data).hexdigest()


def make_copy(dest: Path) -> None:
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        check=True,
        capture_output=True,
    ).stdout.decode()
    for rel in sorted({p for p in listed.split("\0") if p}):
        src = REPO / rel
        if rel == ".venv" or rel.startswith(".venv/") or not os.path.lexists(src):
            continue  # deleted in the work tree, not yet in git
        if src.is_dir() and not src.is_symlink():
            continue  # a submodule
        target = dest / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target, follow_symlinks=False)
    (dest / ".venv").symlink_to(REPO / ".venv")


def user_env(root: Path) -> dict[str, str]:
    """The environment after README's `. .venv/bin/activate`, without pytest's own."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "COV_"))}
    env.pop("PYTHONPATH", None)
    env["VIRTUAL_ENV"] = str(root / ".venv")
    env["PATH"] = f"{root / '.venv' / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return env


@dataclass
class Outcome:
    ok: bool
    detail: str = ""


@dataclass
class Runner:
    """Runs the blocks in order, once each, in one copy; remembers every outcome."""

    root: Path
    env: dict[str, str]
    outcomes: list[Outcome] = field(default_factory=list)
    ran: dict[str, str] = field(default_factory=dict)
    log: list[tuple[str, float]] = field(default_factory=list)

    def upto(self, index: int) -> Outcome:
        while len(self.outcomes) <= index:
            block = SHELL_BLOCKS[len(self.outcomes)]
            start = time.monotonic()
            try:
                outcome = self.run(block)
            except subprocess.TimeoutExpired as e:
                outcome = Outcome(False, f"{block.where}: timed out after {e.timeout} s")
            self.log.append((block.where, time.monotonic() - start))
            self.outcomes.append(outcome)
        return self.outcomes[index]

    # -- one block

    def run(self, block: Block) -> Outcome:
        if problems(block):
            return Outcome(False, "\n".join(problems(block)))
        if block.kind == "skip":
            return Outcome(True, f"skipped: {block.values('reason')[0]}")
        key = f"{block.kind}\n{block.options}\n{block.text}"
        if key in self.ran:
            return Outcome(True, f"same block as {self.ran[key]}, run there")
        if block.kind == "hardware":
            outcome = self.run_hardware(block)
        elif block.kind == "two-terminals":
            outcome = self.run_two_terminals(block)
        else:
            text = self.fill(block)
            if block.kind == "output":
                text = "\n".join(output_commands(text)) + "\n"
            outcome = self.script(block, text)
        if outcome.ok:
            self.ran[key] = block.where
        return outcome

    def fill(self, block: Block) -> str:
        text = block.text
        sessions = sorted(
            p.name for p in (self.root / "sessions").glob("*") if (p / "manifest.json").is_file()
        )
        for key, source in block.placeholders.items():
            if not sessions:
                raise AssertionError(f"{block.where}: {key}: no session made before this block")
            if source == "newest-session":
                value = sessions[-1]
            elif source == "oldest-session":
                value = sessions[0]
            else:
                value = sessions[int(source.split(":")[1]) - 1]
            word = re.escape(key)
            if re.fullmatch(r"\w+", key):
                word = rf"(?<![\w-]){word}(?![\w-])"
            text = re.sub(word, value, text)
        return text

    def script(self, block: Block, text: str) -> Outcome:
        proc = subprocess.run(
            ["bash", "-c", f"set -eo pipefail\n{text}"],
            cwd=self.root,
            env=self.env,
            capture_output=True,
            text=True,
            timeout=BLOCK_TIMEOUT_S,
        )
        return self.judge(block, proc.returncode, proc.stdout, proc.stderr)

    @staticmethod
    def judge(block: Block, rc: int, stdout: str, stderr: str) -> Outcome:
        tail = f"--- stdout (end)\n{stdout[-3000:]}\n--- stderr (end)\n{stderr[-3000:]}"
        if rc != 0:
            return Outcome(False, f"{block.where}: exit status {rc}\n{tail}")
        if TRACEBACK in stdout or TRACEBACK in stderr:
            return Outcome(False, f"{block.where}: printed a traceback\n{tail}")
        return Outcome(True)

    def run_hardware(self, block: Block) -> Outcome:
        commands = logical_lines(block.text)
        errors = block.values("error")
        made = [self.root / p for p in block.values("calibration")]
        for path in made:
            if path.exists():
                return Outcome(False, f"{block.where}: {path} exists already")
            path.parent.mkdir(parents=True, exist_ok=True)
            fit = subprocess.run(
                [
                    "stipi-daemon",
                    "calibrate",
                    "--depth-pairs",
                    "configs/calibration/example_depth_pairs.csv",
                    "--force-pairs",
                    "configs/calibration/example_force_pairs.csv",
                    "--threshold",
                    "128",
                    "--frame-size",
                    "1280x720",
                    "--out",
                    str(path),
                ],
                cwd=self.root,
                env=self.env,
                capture_output=True,
                text=True,
                timeout=120,
            )
            if fit.returncode != 0:
                return Outcome(False, f"{block.where}: stand-in calibration: {fit.stderr}")
        try:
            for i, command in enumerate(commands):
                fragment = errors[i] if len(errors) > 1 else errors[0]
                proc = subprocess.run(
                    ["bash", "-c", command],
                    cwd=self.root,
                    env=self.env,
                    capture_output=True,
                    text=True,
                    timeout=180,
                )
                lines = [
                    line
                    for line in proc.stderr.splitlines()
                    if line.strip() and not MAKE_LINE.match(line)
                ]
                said = f"{command!r}: exit {proc.returncode}, stderr:\n{proc.stderr[-3000:]}"
                if proc.returncode == 0:
                    return Outcome(False, f"{block.where}: succeeded without hardware: {said}")
                if TRACEBACK in proc.stderr or TRACEBACK in proc.stdout:
                    return Outcome(False, f"{block.where}: traceback: {said}")
                if len(lines) != 1 or fragment not in lines[0]:
                    return Outcome(
                        False, f"{block.where}: want one stderr line with {fragment!r}: {said}"
                    )
        finally:
            for path in made:
                path.unlink(missing_ok=True)
        return Outcome(True)

    def _start(self, command: str, out_path: Path, err_path: Path) -> subprocess.Popen[bytes]:
        """Start ``command`` as terminal 1, its output to these files."""
        with out_path.open("w") as out, err_path.open("w") as err:
            return subprocess.Popen(
                ["bash", "-c", f"exec {command}"],
                cwd=self.root,
                env=self.env,
                stdout=out,
                stderr=err,
                start_new_session=True,
            )

    def run_two_terminals(self, block: Block) -> Outcome:
        first, second = logical_lines(block.text)
        out_path = self.root.parent / "terminal-1.out"
        err_path = self.root.parent / "terminal-1.err"
        for attempt in range(PORT_IN_USE_ATTEMPTS):
            server = self._start(first, out_path, err_path)
            # A user switches terminals once terminal 1 has said it is ready; on a loaded
            # machine that takes longer than the second a quiet one needs.
            ready = wait_for_output(server, out_path, SERVER_READY_TIMEOUT_S)
            # A fixed port another process on the machine holds for the moment: a user
            # tries again; the test does too, and says who held it if it stays taken.
            if ready or "the port is in use" not in err_path.read_text():
                break
            if attempt + 1 < PORT_IN_USE_ATTEMPTS:
                time.sleep(PORT_IN_USE_WAIT_S)
        try:
            if not ready:
                return Outcome(
                    False,
                    f"{block.where}: terminal 1 printed nothing within "
                    f"{SERVER_READY_TIMEOUT_S:.0f} s (exit {server.returncode}):\n"
                    + err_path.read_text()[-3000:]
                    + _listeners(),
                )
            if server.poll() is not None:
                return Outcome(
                    False,
                    f"{block.where}: terminal 1 exited {server.returncode}:\n"
                    + err_path.read_text()[-3000:],
                )
            outcome = self.script(block, second)
            if not outcome.ok:
                return outcome
            if server.poll() is not None:
                return Outcome(False, f"{block.where}: terminal 1 ended early")
            os.killpg(server.pid, signal.SIGINT)
            rc = server.wait(timeout=30)
            stderr = err_path.read_text()
            if rc not in (0, 130) or TRACEBACK in stderr:
                return Outcome(
                    False, f"{block.where}: terminal 1 after Ctrl-C: exit {rc}\n{stderr[-3000:]}"
                )
            return Outcome(True)
        finally:
            if server.poll() is None:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()


def _listeners() -> str:
    """The machine's listening TCP sockets and their processes (``ss -ltnp``), or ''."""
    try:
        done = subprocess.run(
            ["ss", "-ltnp"], capture_output=True, text=True, timeout=10, check=False
        )
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return "\nlistening sockets (ss -ltnp):\n" + done.stdout[-3000:]


def wait_for_output(proc: subprocess.Popen[bytes], path: Path, timeout_s: float) -> bool:
    """Wait until `proc` has written a whole line to `path` (True) or ended (False)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if "\n" in path.read_text(errors="replace"):
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.1)
    return False


@pytest.fixture(scope="module")
def runner(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Runner]:
    root = tmp_path_factory.mktemp("doc-commands") / "repo"
    root.mkdir()
    stamp = REPO / ".venv" / ".stipi-installed"
    if not stamp.is_file() or stamp.read_text().strip() != venv_stamp_wanted(REPO):
        pytest.fail(f"{REPO / '.venv'} is not up to date: run ./dev once in {REPO}")
    make_copy(root)
    assert venv_stamp_wanted(root) == venv_stamp_wanted(REPO)
    env = user_env(root)
    dev = subprocess.run(
        ["./dev", "true"], cwd=root, env=env, capture_output=True, text=True, timeout=60
    )
    assert (dev.returncode, dev.stderr) == (0, ""), f"./dev in the copy set .venv up:\n{dev}"
    yield Runner(root=root, env=env)


# --- the tests ------------------------------------------------------------------------


def test_every_block_is_covered() -> None:
    """Every block is run or marked; no fence without a language; no command outside sh."""
    found = [p for b in ALL_BLOCKS for p in problems(b)]
    assert not found, "\n".join(found)
    assert len(SHELL_BLOCKS) >= 20
    assert {b.doc for b in SHELL_BLOCKS} >= {"README.md", "docs/study.md", "docs/bench.md"}


def test_skipped_blocks_are_the_expected_ones() -> None:
    """Skips are few, each with its reason: exactly the blocks EXPECTED_SKIPS names."""
    skipped = [b for b in SHELL_BLOCKS if b.kind == "skip"]
    matched = {
        (doc, prefix)
        for b in skipped
        for doc, prefix in EXPECTED_SKIPS
        if b.doc == doc and prefix in b.text
    }
    unexpected = [
        f"{b.where}: {b.first_line}"
        for b in skipped
        if not any(b.doc == d and p in b.text for d, p in EXPECTED_SKIPS)
    ]
    assert not unexpected, "skipped blocks not in EXPECTED_SKIPS:\n" + "\n".join(unexpected)
    assert matched == EXPECTED_SKIPS, f"expected skips not found: {EXPECTED_SKIPS - matched}"
    assert len(skipped) == len(EXPECTED_SKIPS)
    assert all(b.values("reason") for b in skipped)


def test_harness_parses_markers_and_commands() -> None:
    """The parsing the other tests rely on: markers, continuations, output commands."""
    assert parse_marker('hardware error="a b" error=c calibration=x/y.json') == (
        "hardware",
        (("error", "a b"), ("error", "c"), ("calibration", "x/y.json")),
    )
    assert parse_marker("placeholders ID=newest-session") == (
        "run",
        (("ID", "newest-session"),),
    )
    text = 'a \\\n  b\n# note\n\nc "x\ny"\n'
    assert logical_lines(text) == ["a \\\n  b", 'c "x\ny"']
    shown = 'stipi-daemon q d/ "SELECT 1,\n  2"\ncol  col\nstipi-daemon: error: x\n'
    assert output_commands(shown) == ['stipi-daemon q d/ "SELECT 1,\n  2"']
    bad = Block("d.md", 1, "", "x\n", None, "none", ())
    assert problems(bad)
    hidden = Block("d.md", 1, "text", "stipi-daemon --help\n", None, "none", ())
    assert problems(hidden)
    unmarked_skip = Block("d.md", 1, "sh", "x\n", "skip", "skip", ())
    assert problems(unmarked_skip)


def test_harness_fails_failing_commands(tmp_path: Path) -> None:
    """A command that fails, anywhere in a block, or prints a traceback, fails the block."""
    runner = Runner(root=tmp_path, env=user_env(tmp_path))
    block = Block("d.md", 1, "sh", "", None, "run", ())
    assert runner.script(block, "true\n").ok
    assert not runner.script(block, "true\nfalse\ntrue\n").ok
    assert not runner.script(block, "false | true\n").ok
    assert not runner.script(block, "python3 -c 'raise SystemExit(2)'\n").ok
    assert not runner.script(block, f"echo '{TRACEBACK}' >&2\n").ok
    hardware = Block("d.md", 1, "sh", "true\n", None, "hardware", (("error", "x"),))
    assert not runner.run_hardware(hardware).ok  # it succeeded: no hardware needed?
    said = Block("d.md", 1, "sh", "echo x >&2; echo y >&2; false\n", None, "hardware", ())
    assert not runner.run_hardware(replace(said, options=(("error", "x"),))).ok
    one = replace(said, text="echo 'it: x here' >&2; false\n", options=(("error", "x"),))
    assert runner.run_hardware(one).ok


@pytest.mark.timeout(MODULE_TIMEOUT_S)
@pytest.mark.parametrize("index", range(len(SHELL_BLOCKS)), ids=[b.where for b in SHELL_BLOCKS])
def test_block_runs_as_written(runner: Runner, index: int) -> None:
    """The block (and every block before it, in order, once) runs as its marker says."""
    outcome = runner.upto(index)
    assert outcome.ok, outcome.detail
    if SHELL_BLOCKS[index].kind == "skip":
        pytest.skip(outcome.detail)
