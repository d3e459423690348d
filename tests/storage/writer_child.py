"""A session writer in its own process, driven by the storage tests.

Usage: ``python writer_child.py ROOT SESSION_ID MODE COMMIT_INTERVAL_S``

MODE ``stream``: record one force sample per ~1 ms (``t_host_s = time.monotonic()``,
which is the same clock in every process on Linux) and a frame every ~16 ms, print
``ready`` after the first commit, and go on until killed (at most 60 s). After every
``add_force_samples`` returns, the sample's index and ``t_host_s`` are stored in the
shared file ``ROOT/progress.bin`` (an mmap: it survives a kill -9), so the parent knows
exactly which rows the writer had accepted when it died.

MODE ``hold``: record 100 force samples, commit, print ``committed 100``, then obey
lines on stdin: ``more K`` adds K samples and commits (prints ``committed N``),
``finish`` finishes the session as complete and closes it (prints ``done``).
"""

from __future__ import annotations

import mmap
import struct
import sys
import time
from pathlib import Path

from stipi_daemon.storage import SessionWriter, StorageOptions

#: Layout of ``progress.bin``: last accepted sample index, its t_host_s [s].
PROGRESS = struct.Struct("<qd")


def _sample(i: int) -> tuple[int, int, int, int, float, float]:
    t_us = 1000 * i
    return (i, 512 + i % 100, t_us % 2**32, t_us, time.monotonic(), 0.01 * (i % 100))


def main() -> int:
    root, session_id, mode, interval = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    options = StorageOptions(commit_interval_s=interval, min_free_bytes=0)
    writer = SessionWriter.create(
        Path(root), {"mode": mode}, {"span": 1.0}, None, session_id=session_id, options=options
    )
    if mode == "stream":
        progress_path = Path(root) / "progress.bin"
        progress_path.write_bytes(bytes(PROGRESS.size))
        with open(progress_path, "r+b") as f:
            progress = mmap.mmap(f.fileno(), PROGRESS.size)
        i = 0
        deadline = time.monotonic() + 60.0
        writer.add_force_samples([_sample(i)])
        writer.commit()
        print("ready", flush=True)
        while time.monotonic() < deadline:
            i += 1
            row = _sample(i)
            writer.add_force_samples([row])
            progress[:] = PROGRESS.pack(i, row[4])
            if i % 16 == 0:
                now = time.monotonic()
                writer.add_frames([(i // 16, now, now, i, "")])
            time.sleep(0.001)
        return 1  # the parent should have killed us
    n = 100
    writer.add_force_samples([_sample(i) for i in range(n)])
    writer.commit()
    print(f"committed {n}", flush=True)
    for line in sys.stdin:
        words = line.split()
        if words[0] == "more":
            k = int(words[1])
            writer.add_force_samples([_sample(i) for i in range(n, n + k)])
            writer.commit()
            n += k
            print(f"committed {n}", flush=True)
        elif words[0] == "finish":
            writer.finish("complete", {"n": n})
            writer.close()
            print("done", flush=True)
            return 0
    return 1


if __name__ == "__main__":
    sys.exit(main())
