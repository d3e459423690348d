"""Effective force resolution of the oversampled load cell, measured on the ELF in simavr.

The harness feeds a slow ramp (35.6 mV/s, ~11 counts/s) to A0 with gaussian noise of 0, 0.5
and 1 LSB rms added to every conversion (``--noise-mv``, fixed seed: the AVR's own ADC noise
and the FC22's are of that order); the firmware samples at 100 Hz, 16 conversions per sample.
The residual of each stream around a straight-line fit (the ramp is linear) gives the rms error
``e`` [10-bit LSB] and the effective number of bits ``ENOB = 10 - log2(e * sqrt(12))`` (an ideal
10-bit quantiser has e = 1/sqrt(12)). The single-conversion figure comes from the same run: the
counts simavr produced for every fed conversion (the harness's log) around the same fit. Both
firmware builds: the default (10-bit mean on the wire, compatible with existing calibrations)
and ``STIPI_ADC_EXTRA_BITS=2`` (12-bit sum / 4). Force per 10-bit count: 10 lbf FC22
0.0538 N, 25 lbf 0.1345 N (docs/firmware.md).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stipi_daemon.protocol.messages import AckStatus, GetInfo, StreamStart
from tests.conftest import require_path, require_tool
from tests.firmware.simavr_probe import (
    FIRMWARE_ADC12_ELF,
    FIRMWARE_ELF,
    SIMAVR_HEADER,
    SimProbe,
    build,
    counts_of_mv,
    flatten,
)

pytestmark = pytest.mark.toolchain

LSB_MV = 3300 / 1023  # simavr's 10-bit step [mV]
N_PER_COUNT = {"10 lbf": 44.48 / 827, "25 lbf": 111.21 / 827}  # FC22 full scale over 827 counts


def _enob(err_lsb: float) -> float:
    return 10 - math.log2(err_lsb * math.sqrt(12))


def _residual_rms(t: np.ndarray, y: np.ndarray) -> float:
    a = np.vstack([t - t.mean(), np.ones_like(t)]).T
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    return float(np.sqrt(np.mean((y - a @ coef) ** 2)))


def _measure(elf: object, noise_lsb: float) -> tuple[float, float, int]:
    """(rms error of single conversions, of the firmware's samples) [10-bit LSB], adc_bits."""
    probe = SimProbe(
        # 35.6 mV/s for 45 s: the 4 s of samples lie on the ramp however late the host's
        # STREAM_START comes (a 4.5 s ramp ended under the samples of a loaded machine, and
        # its flat end doubled the residual of the straight-line fit)
        "ramp:1000:2600:45",
        ["--noise-mv", f"{noise_lsb * LSB_MV:.4f}", "--seed", "7"],
        elf=elf,  # type: ignore[arg-type]
    )
    try:
        bits = probe.command(GetInfo()).info().adc_bits
        assert probe.command(StreamStart()).status == AckStatus.OK
        s = flatten(probe.collect_samples(400, timeout_s=60))
        probe.wait_logged_through(s.t_us[-1] * 1e-6 + 0.01)
        starts, burst_t, burst_mv = probe.log.bursts()
    finally:
        probe.close()
    assert np.array_equal(np.diff(s.index), np.ones(len(s.index) - 1, dtype=np.int64))
    out_lsb = s.adc / 2 ** (bits - 10)
    sample_err = _residual_rms(s.t_us * 1e-6, out_lsb)
    # single conversions of the same window, as simavr converted them
    window = (starts >= s.t_us[0] * 1e-6) & (starts <= s.t_us[-1] * 1e-6 + 0.01)
    t_conv = np.concatenate([t for t, w in zip(burst_t, window, strict=True) if w])
    c_conv = np.concatenate([counts_of_mv(m) for m, w in zip(burst_mv, window, strict=True) if w])
    return _residual_rms(t_conv, c_conv.astype(np.float64)), sample_err, bits


@pytest.fixture(scope="module")
def built() -> None:
    require_tool("avr-gcc", "avr-g++", "cc", "make")
    require_path(SIMAVR_HEADER, "libsimavr-dev headers")
    build("harness", "firmware", "firmware-adc12")


def test_oversampling_gains_effective_bits(built: None) -> None:
    rows = []
    for noise in (0.0, 0.5, 1.0):
        for elf in (FIRMWARE_ELF, FIRMWARE_ADC12_ELF):
            single, sample, bits = _measure(elf, noise)
            rows.append((noise, bits, single, sample))
            res = ", ".join(f"{k} {sample * n * 1000:.1f} mN rms" for k, n in N_PER_COUNT.items())
            print(
                f"resolution: noise {noise:.1f} LSB, {bits}-bit wire: single conversion "
                f"{single:.3f} LSB rms (ENOB {_enob(single):.2f}), sample of 16 "
                f"{sample:.3f} LSB rms (ENOB {_enob(sample):.2f}); {res}"
            )
    by = {(n, b): (s1, s2) for n, b, s1, s2 in rows}
    # Without noise a slow ramp is just quantised: ~1/sqrt(12) LSB either way.
    for b in (10, 12):
        assert by[(0.0, b)][0] == pytest.approx(1 / math.sqrt(12), rel=0.15)
    # With noise, averaging 16 conversions cuts it ~4x; the 12-bit wire keeps the gain,
    # the 10-bit wire adds its own rounding (1/sqrt(12) LSB) back.
    for n in (0.5, 1.0):
        single12, sample12 = by[(n, 12)]
        single10, sample10 = by[(n, 10)]
        assert single12 == pytest.approx(math.sqrt(n**2 + 1 / 12), rel=0.15)
        assert sample12 == pytest.approx(math.sqrt(n**2 / 16 + 1 / 12 / 16), rel=0.3)
        assert sample10 == pytest.approx(math.sqrt(n**2 / 16 + 1 / 12), rel=0.2)
        assert _enob(sample12) - _enob(single12) > 1.6
        assert _enob(sample10) > _enob(single10)
