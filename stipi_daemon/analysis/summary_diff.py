"""Differences between a stored and a recomputed summary, one line per differing leaf.

Pure: ``analyze SESSION`` (:mod:`stipi_daemon.app.analyze`) compares the summary it
recomputes with the session's ``summary.json`` (both as JSON stores them) with
:func:`diff_results`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

__all__ = ["diff_results"]


def diff_results(stored: Any, recomputed: Any, path: str = "results") -> list[str]:
    """Differences between two JSON-like values, one line per differing leaf.

    Numbers are compared exactly (floats as stored in JSON round-trip exactly); ``None``
    only equals ``None``. Lists of different lengths and keys present on one side only are
    differences.
    """
    out: list[str] = []
    if isinstance(stored, Mapping) and isinstance(recomputed, Mapping):
        for key in sorted(set(stored) | set(recomputed)):
            if key not in stored:
                out.append(f"{path}.{key}: only in the recomputed results")
            elif key not in recomputed:
                out.append(f"{path}.{key}: only in the stored results")
            else:
                out.extend(diff_results(stored[key], recomputed[key], f"{path}.{key}"))
        return out
    if isinstance(stored, list | tuple) and isinstance(recomputed, list | tuple):
        if len(stored) != len(recomputed):
            return [f"{path}: {len(stored)} items stored, {len(recomputed)} recomputed"]
        for i, (a, b) in enumerate(zip(stored, recomputed, strict=True)):
            out.extend(diff_results(a, b, f"{path}[{i}]"))
        return out
    if stored != recomputed:
        out.append(f"{path}: stored {stored!r}, recomputed {recomputed!r}")
    return out
