"""The daemon's heap: frame buffers reused while measuring, large blocks returned after.

A measurement allocates and frees a frame buffer (hundreds of kB to a few MB) tens to
hundreds of times a second on several threads. Left to itself, glibc's allocator raises its
mmap threshold to the largest block freed and gives each thread an arena of its own: the
frames then come from arena heaps, and whatever those heaps once held stays resident (the
demo's peak RSS was 352 MB). Holding the threshold at 128 kB instead had every frame buffer
mmapped, page-faulted in and unmapped again: about 1,000 page faults and 2.3 ms of CPU more
per 1080p frame decoded and counted at 60 fps (1.76x glibc's defaults), 4-5 s of system CPU
in the demo (docs/performance.md, "Heap settings and frame CPU").

So :func:`hold_heap` sets, for the acquisition, a threshold of :data:`FRAME_HEAP_MAX_B`
(a 1080p BGR frame comes from the heap), a trim threshold of :data:`TRIM_THRESHOLD_B` (a
frame freed at the heap's top is not given back just to be faulted in again) and
:data:`ARENAS` arenas; :func:`return_free_memory`, once the acquisition ends, gives the
heaps' free pages back (``malloc_trim``) and sets both thresholds to
:data:`MMAP_THRESHOLD_B` for the analysis and the report, whose large arrays are then
mmapped and returned as soon as they are freed (the demo's report is its peak of memory).
Figures: docs/performance.md, "Demo speed". Both do nothing where the C library is not
glibc. No result depends on them.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from typing import Final

__all__ = [
    "ARENAS",
    "FRAME_HEAP_MAX_B",
    "MMAP_THRESHOLD_B",
    "TRIM_THRESHOLD_B",
    "hold_heap",
    "return_free_memory",
]

#: While measuring, allocations at least this large are mmapped and unmapped when freed,
#: smaller ones come from the heap [B] (above a 1920x1080 BGR frame, 6.2 MB).
FRAME_HEAP_MAX_B: Final = 8 * 1024 * 1024
#: While measuring, free memory at a heap's top is given back once it exceeds this [B].
TRIM_THRESHOLD_B: Final = 8 * 1024 * 1024
#: After the acquisition, both thresholds [B] (glibc's default starting values, held
#: instead of raised to the largest block freed).
MMAP_THRESHOLD_B: Final = 128 * 1024
#: Arenas of the allocator at most [-] (glibc's default: 8 per CPU).
ARENAS: Final = 2
_M_TRIM_THRESHOLD: Final = -1
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
    """For the acquisition: the mmap threshold at :data:`FRAME_HEAP_MAX_B`, the trim
    threshold at :data:`TRIM_THRESHOLD_B`, the arenas at :data:`ARENAS` (for the rest of
    the process); False where that is not possible."""
    libc = _glibc()
    if libc is None:
        return False
    ok = _thresholds(libc, FRAME_HEAP_MAX_B, TRIM_THRESHOLD_B)
    return bool(libc.mallopt(_M_ARENA_MAX, ARENAS) == 1 and ok)


def _thresholds(libc: ctypes.CDLL, mmap_b: int, trim_b: int) -> bool:
    ok = libc.mallopt(_M_MMAP_THRESHOLD, mmap_b) == 1
    return bool(libc.mallopt(_M_TRIM_THRESHOLD, trim_b) == 1 and ok)


def return_free_memory() -> bool:
    """After the acquisition: give the heaps' free pages back to the system and set both
    thresholds to :data:`MMAP_THRESHOLD_B`; False where that is not possible."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)
    return _thresholds(libc, MMAP_THRESHOLD_B, MMAP_THRESHOLD_B)
