"""Code in the documentation runs: every ```python block of the analysis guide executes."""

from __future__ import annotations

import re

import pytest

from tests.conftest import REPO_ROOT

DOCS = ["docs/analysis.md"]


def _blocks(path: str) -> list[tuple[str, str]]:
    text = (REPO_ROOT / path).read_text(encoding="utf-8")
    return [
        (f"{path}#{i}", m.group(1))
        for i, m in enumerate(re.finditer(r"```python\n(.*?)```", text, re.S))
    ]


def _is_signature_listing(code: str) -> bool:
    # Blocks that list signatures ("f(x) -> T", ".method(...)") are not runnable examples.
    return bool(re.search(r"^\s*\w[\w.]*\(.*\)\s*->", code, re.M)) or code.lstrip().startswith(".")


BLOCKS = [b for d in DOCS for b in _blocks(d) if not _is_signature_listing(b[1])]


@pytest.mark.parametrize(("where", "code"), BLOCKS, ids=[w for w, _ in BLOCKS])
def test_doc_block_runs(where: str, code: str) -> None:
    exec(compile(code, where, "exec"), {"__name__": "__doc_example__"})


def test_docs_have_examples() -> None:
    assert len(BLOCKS) >= 2
