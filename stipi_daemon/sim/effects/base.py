"""Base classes shared by every simulator effect.

An effect is one small module under :mod:`stipi_daemon.sim.effects` holding a pydantic
``Params`` model (its ``name`` is the scene's discriminator) and an ``Effect`` class built
from it. This module owns the parameter base class and the five kinds of effect the
pipeline knows how to run; it does not own any effect, nor the registry
(:mod:`stipi_daemon.sim.effects`) nor the pipeline (:mod:`stipi_daemon.sim.pipeline`).
Every method is pure apart from drawing from the ``numpy.random.Generator`` it is given.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "EffectContext",
    "EffectParams",
    "ForceEffect",
    "FrameDropEffect",
    "FrameEffect",
    "RenderEffect",
    "SampleClockEffect",
]


class EffectParams(BaseModel):
    """Parameters of one effect; subclasses fix ``name`` with a ``Literal``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str


class SpanParams(EffectParams):
    """Parameters of an effect over one time span ``[t_start_s, t_end_s)`` [s] (default:
    empty); subclasses fix ``name``."""

    t_start_s: float = Field(default=0.0, ge=0.0, allow_inf_nan=False)
    t_end_s: float = Field(default=0.0, ge=0.0, allow_inf_nan=False)

    @model_validator(mode="after")
    def _ordered(self) -> SpanParams:
        if self.t_end_s < self.t_start_s:
            raise ValueError(f"t_end_s {self.t_end_s} is before t_start_s {self.t_start_s}")
        return self


@dataclass(frozen=True)
class EffectContext:
    """What an effect may know about the scene it runs in.

    Attributes
    ----------
    width_px, height_px : int
        Frame size [px].
    fps : float
        Nominal frame rate [1/s].
    exposure_s : float
        Exposure time of one frame [s].
    threshold : int
        Binarisation level p of Eq. (1) [gray level].
    sample_rate_hz : float
        Load-cell sample rate [1/s].
    range_n : float
        Load-cell full scale [N].
    px_per_mm : float
        Image scale at the waveguide [px/mm].
    """

    width_px: int
    height_px: int
    fps: float
    exposure_s: float
    threshold: int
    sample_rate_hz: float
    range_n: float
    px_per_mm: float


class FrameEffect(ABC):
    """Transforms a rendered frame (uint8, HxW or HxWx3)."""

    @abstractmethod
    def apply_frame(
        self, image: NDArray[np.uint8], t_s: float, rng: np.random.Generator
    ) -> NDArray[np.uint8]:
        """Return the transformed frame (may modify ``image`` in place and return it)."""


class RenderEffect:
    """Changes what the renderer draws: the occluded disc's position or its time average."""

    def offset_px(self, t_s: float, rng: np.random.Generator) -> tuple[float, float]:
        """Offset (dx, dy) of the occluded disc's centre at time ``t_s`` [px]."""
        return (0.0, 0.0)

    def sub_times_s(self, t_s: float) -> tuple[float, ...]:
        """Times whose renders are averaged into the frame at ``t_s`` [s] (motion blur)."""
        return (t_s,)


class FrameDropEffect(ABC):
    """Decides which frames reach the output and when they are stamped."""

    @abstractmethod
    def keep(self, index: int, t_s: float, rng: np.random.Generator) -> bool:
        """Whether frame ``index`` (nominal time ``t_s`` [s]) is delivered."""


class ForceEffect(ABC):
    """Transforms the force seen by the load cell, before the ADC [N]."""

    @abstractmethod
    def apply_force(
        self, t_s: NDArray[np.float64], force_n: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        """Return the force at the sample times ``t_s`` [s] after the effect [N]."""

    def apply_counts(
        self, counts: NDArray[np.int64], rng: np.random.Generator
    ) -> NDArray[np.int64]:
        """Transform ADC counts after quantisation (default: unchanged)."""
        return counts


class SampleClockEffect:
    """Relates the MCU's microsecond clock to true time, and may lose or delay samples.

    The pipeline calls, for each such effect in registry order and with one generator per
    effect: :meth:`true_time_s`, :meth:`mcu_time_us`, :meth:`delivered`,
    :meth:`host_time_s`; each receives the previous effect's output.
    """

    def true_time_s(
        self, t_nominal_s: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        """True time [s] at which the MCU takes the samples it schedules at ``t_nominal_s``."""
        return t_nominal_s

    def mcu_time_us(
        self, t_true_s: NDArray[np.float64], mcu_us: NDArray[np.float64], rng: np.random.Generator
    ) -> NDArray[np.float64]:
        """MCU clock reading stamped on each sample, since the boot offset [us] (not rounded).

        ``mcu_us`` is the reading so far (default: the nominal schedule, ``1e6 * t``); the
        default keeps it.
        """
        return mcu_us

    def delivered(self, index: NDArray[np.int64], rng: np.random.Generator) -> NDArray[np.bool_]:
        """Which samples reach the host (BLE loss); default: all."""
        return np.ones(index.shape, dtype=np.bool_)

    def host_time_s(
        self,
        index: NDArray[np.int64],
        t_host_s: NDArray[np.float64],
        delivered: NDArray[np.bool_],
        rng: np.random.Generator,
    ) -> NDArray[np.float64]:
        """Host receive time of every sample [s] (lost ones: when they would have arrived).

        ``t_host_s`` is the time so far (default: the true time, an ideal link) and
        ``delivered`` the samples every effect lets through; the default keeps the times.
        """
        return t_host_s
