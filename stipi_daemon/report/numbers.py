"""How the report writes numbers: one rounding rule for every table, caption and legend.

Three kinds of number, each with its rule:

- a **value** without an uncertainty (:func:`value_text`): 4 significant figures, trailing
  zeros dropped; integers and values from 10^4 to 10^9 (pixel counts) to the unit; below
  10^-4 in exponent notation;
- a **value with its uncertainty** (a standard error, a standard deviation;
  :func:`value_with_uncertainty`): the uncertainty to 2 significant figures and the value to
  the same decimal place (JCGM 100:2008, the GUM, 7.2.6: an uncertainty needs at most two
  significant digits, and the value is rounded to agree with it), but never to more than
  :data:`MAX_VALUE_DIGITS` significant figures nor fewer than 1;
- a **relative difference in percent** (an error against a ground truth, a coefficient of
  variation; :func:`percent_text`): 2 significant figures, never finer than 0.01 %, so an
  agreement below the table's own rounding reads ``0.00`` rather than ``0.0008376``.

Missing and non-finite numbers read ``-``. Pure; the page's markup is :mod:`.html`'s.
"""

from __future__ import annotations

import math
from typing import Final

__all__ = [
    "MAX_VALUE_DIGITS",
    "PERCENT_RESOLUTION",
    "VALUE_DIGITS",
    "percent_text",
    "value_text",
    "value_with_uncertainty",
    "with_unit",
]

#: Significant figures of a value without an uncertainty.
VALUE_DIGITS: Final = 4
#: Most significant figures a value is given with, however small its uncertainty.
MAX_VALUE_DIGITS: Final = 6
#: Significant figures of an uncertainty.
UNCERTAINTY_DIGITS: Final = 2
#: Finest step of a relative difference [%].
PERCENT_RESOLUTION: Final = 0.01

MISSING: Final = "-"


def _finite(value: float | None) -> bool:
    return value is not None and math.isfinite(value)


def _exponent(value: float) -> int:
    """Decimal exponent of the leading digit of ``value`` (``value`` != 0)."""
    return math.floor(math.log10(abs(value)))


def _fixed(value: float, decimals: int) -> str:
    """``value`` rounded to ``decimals`` places (negative: tens, hundreds...), no ``-0``."""
    if decimals < 0:
        q = 10.0 ** (-decimals)
        text = f"{round(value / q) * q:.0f}"
    else:
        text = f"{value:.{decimals}f}"
    if text.lstrip("-").strip("0.") == "":
        text = text.lstrip("-")
    return text


def with_unit(text: str, unit: str = "") -> str:
    """``text`` followed by ``unit`` (no unit for ``-`` or an empty unit)."""
    return f"{text} {unit}" if unit and unit != "-" and text != MISSING else text


def value_text(value: float | None, unit: str = "") -> str:
    """A value without an uncertainty: 4 significant figures, ``-`` when missing.

    Trailing zeros are dropped (``0.5``, not ``0.5000``); integers and values from 10^4 to
    10^9 (pixel counts) are written to the unit; values below 10^-4 or from 10^9 on in
    exponent notation.
    """
    if value is None or not _finite(float(value)):
        return MISSING
    v = float(value)
    if v.is_integer() and abs(v) < 1e9:
        text = f"{int(v)}"
    elif 1e4 <= abs(v) < 1e9:
        text = _fixed(v, 0)
    else:
        text = f"{v:.{VALUE_DIGITS}g}"
    return with_unit(text, unit)


def value_with_uncertainty(value: float | None, uncertainty: float | None) -> tuple[str, str]:
    """(value text, uncertainty text) rounded together (GUM 7.2.6).

    The uncertainty to 2 significant figures, the value to its last decimal place, within
    1 to :data:`MAX_VALUE_DIGITS` significant figures of the value. Without a usable
    uncertainty (missing, not finite, negative) the value follows :func:`value_text` and the
    uncertainty reads ``-``; a zero uncertainty reads ``0``.
    """
    if not _finite(value):
        return MISSING, value_text(uncertainty)
    assert value is not None
    if uncertainty is None or not math.isfinite(uncertainty) or uncertainty < 0.0:
        return value_text(value), MISSING
    if uncertainty == 0.0:
        return value_text(value), "0"
    u = float(f"{uncertainty:.{UNCERTAINTY_DIGITS - 1}e}")  # 0.0996 -> 0.1: its own exponent
    u_decimals = UNCERTAINTY_DIGITS - 1 - _exponent(u)
    decimals = u_decimals
    if value != 0.0:
        lead = _exponent(value)
        decimals = min(decimals, MAX_VALUE_DIGITS - 1 - lead)
        decimals = max(decimals, -lead)  # at least one significant figure of the value
    return _fixed(value, decimals), _fixed(u, u_decimals)


def percent_text(value: float | None) -> str:
    """A relative difference [%]: 2 significant figures, never finer than 0.01 %."""
    if not _finite(value):
        return MISSING
    assert value is not None
    if abs(value) < PERCENT_RESOLUTION / 2:
        return "0.00"
    decimals = min(2, UNCERTAINTY_DIGITS - 1 - _exponent(value))
    return _fixed(value, decimals)
