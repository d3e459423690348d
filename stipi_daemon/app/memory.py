"""The daemon's heap: frames as memory the C library returns, and returning what is free.

A measurement allocates and frees a frame buffer (hundreds of kB to MB) tens to hundreds of
times a second on several threads. glibc's allocator raises its mmap threshold to the size
of the largest freed block and gives each thread an arena of its own, so after the first
frames every frame buffer comes from an arena heap, and what those heaps once held stays
resident: the demo's peak RSS was 352 MB, 314 MB with the threshold held at 128 kB, 311 MB
with two arenas besides (``/usr/bin/time``, configs/demo.yaml; docs/performance.md, "Demo
speed"). :func:`hold_heap` sets both (``mallopt``); :func:`return_free_memory` gives the
heaps' free pages back (``malloc_trim``) once the acquisition ends, before the analysis and
the report. Both do nothing where the C library is not glibc. No result depends on them.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Final

__all__ = ["MMAP_THRESHOLD_B", "hold_heap", "return_free_memory"]

#: Allocations at least this large are mmapped and unmapped when freed [B] (glibc's default
#: starting value, held instead of raised to the largest block freed).
MMAP_THRESHOLD_B: Final = 128 * 1024
#: Arenas of the allocator at most [-] (glibc's default: 8 per CPU).
ARENAS: Final = 2
_M_MMAP_THRESHOLD: Final = -3
_M_ARENA_MAX: Final = -8


@functools.cache
def _glibc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.mallopt  # noqa: B018 - only glibc has mallopt and malloc_trim
        libc.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


def hold_heap() -> bool:
    """Hold the mmap threshold at :data:`MMAP_THRESHOLD_B` and the arenas at
    :data:`ARENAS` for the rest of the process; False where that is not possible."""
    libc = _glibc()
    if libc is None:
        return False
    ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_B) == 1
    return bool(libc.mallopt(_M_ARENA_MAX, ARENAS) == 1 and ok)


def return_free_memory() -> bool:
    """Give the heaps' free pages back to the system; False where that is not possible."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return True
