"""The house rules, checked: layer contracts, function and command-module sizes.

The layers (docs/architecture.md) are import-linter contracts in ``pyproject.toml``
(``[tool.importlinter]``); :func:`test_layer_contracts_hold` runs ``lint-imports`` on
them. grimp, import-linter's graph builder, reads every import statement of the package,
including those inside functions and under ``TYPE_CHECKING``
(:func:`test_contracts_see_imports_inside_functions` shows it on a throw-away package). The
contracts list no allowed exceptions, and the two runtime contracts together cover every
module except the simulator and its two commands, so that a new module cannot slip out of
the "runtime imports no ``sim``" rule.

Sizes: no function in the package is over :data:`MAX_FUNCTION_LINES` lines (docstring
and decorators included) and no module of ``stipi_daemon/commands/`` is over
:data:`MAX_COMMAND_MODULE_LINES` lines (a command is argument parsing plus one call into
the library).
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grimp
import pytest

from tests.conftest import REPO_ROOT

PACKAGE = "stipi_daemon"
PACKAGE_DIR = REPO_ROOT / PACKAGE
PYPROJECT = REPO_ROOT / "pyproject.toml"

#: Longest function allowed in the package [lines, decorators and docstring included].
MAX_FUNCTION_LINES = 120
#: Longest module allowed in ``stipi_daemon/commands/`` [lines].
MAX_COMMAND_MODULE_LINES = 300

#: Contract ids that ``pyproject.toml`` must define (see docs/architecture.md).
CONTRACT_IDS = {"pure", "adapters", "runtime", "runtime-commands"}
#: The contracts that together say "runtime imports no sim except through the registry".
RUNTIME_CONTRACT_IDS = ("runtime", "runtime-commands")
#: Modules that may import the simulator: the simulator itself and its own commands.
SIMULATOR_SIDE = ("stipi_daemon.commands.simulate", "stipi_daemon.commands.mock_peripheral")


def _lint_imports() -> Path:
    """``lint-imports`` beside the running interpreter (installed by the ``dev`` extras)."""
    exe = Path(sys.executable).with_name("lint-imports")
    if not exe.exists():
        pytest.fail(f"{exe} is missing: install the dev extras (pip install -e '.[dev]')")
    return exe


def _contracts() -> list[dict[str, Any]]:
    config = tomllib.loads(PYPROJECT.read_text(encoding="utf-8"))
    contracts: list[dict[str, Any]] = config["tool"]["importlinter"]["contracts"]
    return contracts


def _run_lint_imports(cwd: Path, config: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(_lint_imports()), "--config", str(config), "--no-cache"],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


# ---------------------------------------------------------------------------------------
# Layers
# ---------------------------------------------------------------------------------------


def test_layer_contracts_hold() -> None:
    proc = _run_lint_imports(REPO_ROOT, PYPROJECT)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "0 broken" in proc.stdout, proc.stdout


def test_contracts_allow_no_exceptions() -> None:
    contracts = _contracts()
    assert {c["id"] for c in contracts} == CONTRACT_IDS
    for contract in contracts:
        assert not contract.get("ignore_imports"), f"contract {contract['id']!r} has exceptions"


def test_runtime_contracts_cover_every_module() -> None:
    by_id = {c["id"]: c for c in _contracts()}
    packages: list[str] = []  # sources checked with their descendants
    modules: set[str] = set()  # sources checked alone
    for contract_id in RUNTIME_CONTRACT_IDS:
        contract = by_id[contract_id]
        assert contract["type"] == "forbidden"
        assert "stipi_daemon.sim" in contract["forbidden_modules"]
        sources = contract["source_modules"]
        assert not any("*" in s for s in sources), "list runtime sources by name"
        if contract.get("as_packages", True):
            packages.extend(sources)
        else:
            modules.update(sources)
    graph = grimp.build_graph(PACKAGE, cache_dir=None)
    uncovered = sorted(
        m
        for m in graph.modules
        if not (m == "stipi_daemon.sim" or m.startswith("stipi_daemon.sim."))
        and m not in SIMULATOR_SIDE
        and m not in modules
        and not any(m == p or m.startswith(p + ".") for p in packages)
    )
    assert not uncovered, (
        "modules outside the runtime contracts (add them to a runtime contract in "
        f"pyproject.toml): {uncovered}"
    )


def test_contracts_see_imports_inside_functions(tmp_path: Path) -> None:
    """A forbidden import hidden in a function body breaks a contract like ours."""
    pkg = tmp_path / "house"
    (pkg / "sim").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sim" / "__init__.py").write_text("")
    (pkg / "runtime.py").write_text("def start() -> None:\n    from house import sim  # noqa\n")
    config = tmp_path / "contracts.toml"
    config.write_text(
        "[tool.importlinter]\n"
        'root_package = "house"\n'
        "[[tool.importlinter.contracts]]\n"
        'name = "runtime imports no sim"\n'
        'type = "forbidden"\n'
        'source_modules = ["house.runtime"]\n'
        'forbidden_modules = ["house.sim"]\n'
    )
    proc = _run_lint_imports(tmp_path, config)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "house.runtime -> house.sim (l.2)" in proc.stdout, proc.stdout


# ---------------------------------------------------------------------------------------
# Sizes
# ---------------------------------------------------------------------------------------


def _functions(path: Path) -> Iterator[tuple[str, int, int]]:
    """``(qualified name, first line, line count)`` of every function in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))

    def visit(node: ast.AST, prefix: str) -> Iterator[tuple[str, int, int]]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([child.lineno, *(d.lineno for d in child.decorator_list)])
                assert child.end_lineno is not None
                name = f"{prefix}{child.name}"
                yield name, first, child.end_lineno - first + 1
                yield from visit(child, name + ".")
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, f"{prefix}{child.name}.")
            else:
                yield from visit(child, prefix)

    yield from visit(tree, "")


def test_no_function_over_120_lines() -> None:
    long = [
        f"{path.relative_to(REPO_ROOT)}:{line} {name} ({count} lines)"
        for path in sorted(PACKAGE_DIR.rglob("*.py"))
        for name, line, count in _functions(path)
        if count > MAX_FUNCTION_LINES
    ]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def test_no_command_module_over_300_lines() -> None:
    lines = {
        path: len(path.read_text(encoding="utf-8").splitlines())
        for path in sorted((PACKAGE_DIR / "commands").glob("*.py"))
    }
    long = [
        f"{path.relative_to(REPO_ROOT)} ({n} lines)"
        for path, n in lines.items()
        if n > MAX_COMMAND_MODULE_LINES
    ]
    assert not long, f"command modules over {MAX_COMMAND_MODULE_LINES} lines: {long}"


def _wait_for_in_loops(path: Path) -> Iterator[int]:
    """Lines of ``asyncio.wait_for`` calls inside a ``for`` or ``while`` loop of ``path``."""

    def visit(node: ast.AST, in_loop: bool) -> Iterator[int]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                yield from visit(child, False)
                continue
            if (
                in_loop
                and isinstance(child, ast.Call)
                and isinstance(child.func, ast.Attribute)
                and child.func.attr == "wait_for"
            ):
                yield child.lineno
            yield from visit(child, in_loop or isinstance(child, (ast.For, ast.While)))

    yield from visit(ast.parse(path.read_text(encoding="utf-8")), False)


def test_no_wait_for_in_a_loop() -> None:
    """A waiting loop uses clock.wait_event or asyncio.timeout: Python 3.11's wait_for drops
    a cancel that comes in the same turn as the awaited result, and the loop then never
    ends (tests/test_clock.py shows both; an emulated probe hung a demo that way)."""
    found = [
        f"{path.relative_to(REPO_ROOT)}:{line}"
        for path in sorted(PACKAGE_DIR.rglob("*.py"))
        for line in _wait_for_in_loops(path)
    ]
    assert not found, "asyncio.wait_for in a loop: " + ", ".join(found)
