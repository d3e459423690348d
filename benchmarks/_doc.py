"""Where the benchmarks write their results: one section each of docs/performance.md."""

from __future__ import annotations

from pathlib import Path

HEADER = "# Performance\n\nMeasured figures of stipi-daemon; each section names its command.\n"


def write_section(doc: Path, section: str, text: str, *, after: str | None = None) -> None:
    """Replace the section headed ``section`` of ``doc`` by ``text``, keeping the others.

    A section not yet there is added at the end, or before the section that follows the
    one headed ``after`` when that is given and present; a missing ``doc`` is created.
    """
    old = doc.read_text() if doc.exists() else HEADER
    start = old.find(section)
    if start >= 0:
        nxt = old.find("\n## ", start + len(section))
        new = old[:start] + text + ("" if nxt < 0 else old[nxt:])
    else:
        anchor = old.find("\n## ", old.find(after) + 1) if after and after in old else -1
        if anchor >= 0:
            new = old[:anchor] + "\n\n" + text.rstrip("\n") + "\n" + old[anchor:]
        else:
            new = old.rstrip("\n") + "\n\n" + text
    doc.write_text(new.rstrip("\n") + "\n")
