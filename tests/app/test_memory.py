"""The daemon's heap settings (glibc's mallopt and malloc_trim through ctypes)."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from stipi_daemon.app.memory import hold_heap, return_free_memory


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's")
def test_frames_reuse_the_heap_while_measuring_and_large_blocks_go_back_after() -> None:
    """In a child (mallopt changes the process for good). While measuring, a 2 MB frame
    buffer freed and allocated again stays resident (no page faults per frame: the minor
    fault count grows by far less than its 512 pages); after return_free_memory, a 1 MB
    block is unmapped as soon as it is freed (the resident set falls back)."""
    code = (
        "import ctypes, ctypes.util, resource\n"
        "from stipi_daemon.app.memory import hold_heap, return_free_memory\n"
        "def rss():\n"
        "    return int(open('/proc/self/status').read().split('VmRSS:')[1].split()[0])\n"
        "def faults():\n"
        "    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "libc = ctypes.CDLL(ctypes.util.find_library('c'))\n"
        "libc.malloc.restype = ctypes.c_void_p\n"
        "libc.free.argtypes = [ctypes.c_void_p]\n"
        "assert hold_heap()\n"
        "p = libc.malloc(2 << 20)\n"
        "ctypes.memset(p, 1, 2 << 20)\n"
        "libc.free(p)\n"
        "f0 = faults()\n"
        "for _ in range(20):  # frame after frame\n"
        "    p = libc.malloc(2 << 20)\n"
        "    ctypes.memset(p, 1, 2 << 20)\n"
        "    libc.free(p)\n"
        "assert faults() - f0 < 20 * 50, faults() - f0\n"
        "assert return_free_memory()\n"
        "for _ in range(50):  # glibc would raise its threshold after the first free\n"
        "    before = rss()\n"
        "    p = libc.malloc(1 << 20)\n"
        "    ctypes.memset(p, 1, 1 << 20)\n"
        "    assert rss() - before >= 900\n"
        "    libc.free(p)\n"
        "    assert rss() - before < 100, (before, rss())\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_calls_never_fail_where_the_c_library_is_not_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    from stipi_daemon.app import memory

    monkeypatch.setattr(memory, "_glibc", lambda: None)
    assert hold_heap() is False and return_free_memory() is False
