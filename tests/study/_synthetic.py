"""Small synthetic sessions written by the real storage writer (few rows each).

Each session is a :class:`~stipi_daemon.storage.SessionWriter` recording: a manifest with
metadata (subject, site) and a probe record naming the probe, a handful of force samples
and frames, and a summary in the daemon's layout (``results``, ``validity``, ``verdict``;
docs/storage.md) whose viscosity is valid, flagged or invalid. Nothing is written by hand
besides what the writer is given.
"""

from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from stipi_daemon.storage import SessionWriter, StorageOptions

SITES = ("Lab A", "Clinic/B", "site=C")
PROBES = ("usb:FTX-001", "ble:AA:BB:CC:DD:EE:01", "emulated")
GRADES = ("I", "II", "III", "IV")
STATUSES = ("valid", "valid", "valid", "flagged", "invalid")


@dataclass(frozen=True)
class Synthetic:
    directory: Path
    site: str
    probe_id: str
    grade: str
    viscosity: float
    status: str  # viscosity's validity


def _summary(grade: str, viscosity: float, status: str) -> dict[str, Any]:
    severity = "mild" if grade in ("I", "II") else "severe"
    entry: dict[str, Any] = {"status": "valid", "flags": [], "reason": None}
    validity = {
        q: dict(entry)
        for q in (
            "depth_mm",
            "rebound_force_n",
            "recovery_time_s",
            "elasticity_kpa",
            "severity",
            "tau_s",
            "applied_force_n",
        )
    }
    validity["viscosity_n_s_per_mm2"] = {
        "status": status,
        "flags": [] if status == "valid" else ["recovery_not_settled"],
        "reason": None if status == "valid" else "the recovery did not settle in the window",
    }
    verdict = "complete" if status == "valid" else status
    return {
        "status": "complete",
        "results": {
            "pitting": {"depth_mm": 2.0, "rebound_force_n": 1.5, "recovery_time_s": 9.0},
            "applied_force_n": 16.0,
            "paper_estimator": {"elasticity_kpa": 100.0, "viscosity_n_s_per_mm2": viscosity},
            "fitted_recovery": {"tau_s": 3.0},
            "severity": {"paper_estimator": {"severity": severity, "nearest_grade": grade}},
        },
        "validity": validity,
        "verdict": {"status": verdict, "line": f"{verdict.capitalize()}."},
    }


def write_session(root: Path, i: int, rng: random.Random) -> Synthetic:
    """Session ``S<i>`` under ``root``: 5 force samples, 3 frames, a summary."""
    site, probe = SITES[i % len(SITES)], PROBES[(i // 3) % len(PROBES)]
    grade = GRADES[rng.randrange(len(GRADES))]
    viscosity = rng.uniform(0.2, 8.0)
    status = STATUSES[rng.randrange(len(STATUSES))]
    firmware = {"transport": "serial:/dev/ttyACM0", "probe_id": probe, "rate_hz": 100}
    writer = SessionWriter.create(
        root,
        {"analysis": {"indenter_radius_mm": 7.5}, "imaging": {"threshold_p": 120}},
        {"threshold_p": 120},
        firmware,
        session_id=f"S{i:05d}",
        options=StorageOptions(min_free_bytes=0, background_commit=False),
        metadata={"subject": f"P-{i % 17:03d}", "site": site},
    )
    with writer:
        writer.add_force_samples(
            [(k, 100 + k, 1000 * k, 1000 * k, 0.01 * k, 0.5 * k) for k in range(5)]
        )
        writer.add_frames([(k, 0.033 * k, 0.034 * k, 1000 + k, "") for k in range(3)])
        writer.finish("complete", _summary(grade, viscosity, status))
    return Synthetic(root / f"S{i:05d}", site, probe, grade, viscosity, status)
