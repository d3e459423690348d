"""What the report says about a session's validity: the verdict and each quantity's status.

``summary.json`` gives each reported quantity a validity (``valid``, ``flagged`` with the
flags that concern it, ``invalid`` with the reason) and the session a verdict (``complete``,
``flagged``, ``invalid``, ``incomplete``), by the rules of
:mod:`stipi_daemon.analysis.validity` (docs/analysis.md). This module reads them for the
page: :func:`read_validity` (each quantity, :class:`QuantityStatus`), :func:`combined`
(the worst status of the quantities a table row depends on) and :func:`session_verdict`
(:class:`VerdictView`: the status shown at the top of the page, its line and the
quantities to name under it). The report never shows "complete" unless every primary
quantity is valid, even if a summary claims it. Sessions recorded before validity was kept
read as ``unknown``; nothing here raises on a malformed summary. The primary and secondary
quantities are those of :mod:`stipi_daemon.analysis.validity` (re-exported). Pure.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final, Literal

from stipi_daemon.analysis.validity import PRIMARY_QUANTITIES, SECONDARY_QUANTITIES
from stipi_daemon.report.inputs import value_at

__all__ = [
    "PRIMARY_QUANTITIES",
    "QUANTITY_NAMES",
    "SECONDARY_QUANTITIES",
    "UNKNOWN_LINE",
    "QuantityStatus",
    "VerdictView",
    "combined",
    "read_validity",
    "session_verdict",
    "verdict_line",
]

Status = Literal["valid", "flagged", "invalid", "unknown"]
VerdictStatus = Literal["complete", "flagged", "invalid", "incomplete", "unknown"]

#: Quantity -> (symbol, words) for the page.
QUANTITY_NAMES: Final[Mapping[str, tuple[str, str]]] = {
    "depth_mm": ("D_p", "pitting depth"),
    "rebound_force_n": ("F_r", "rebound force"),
    "recovery_time_s": ("T_r", "recovery time"),
    "elasticity_kpa": ("E", "elasticity"),
    "viscosity_n_s_per_mm2": ("η", "viscosity E·T_r"),
    "severity": ("severity", "edema class (paper estimator)"),
    "tau_s": ("τ", "fitted time constant"),
    "applied_force_n": ("F_a", "applied force"),
    "viscosity_fit_n_s_per_mm2": ("η_τ", "viscosity E·τ"),
    "severity_fit": ("severity (fit)", "edema class (fitted recovery)"),
}
#: The line of a session recorded before ``summary.json`` kept validity.
UNKNOWN_LINE: Final = "validity unknown (recorded before validity was kept)"
_VERDICTS: Final = ("complete", "flagged", "invalid", "incomplete")
#: Worse statuses rank higher.
_RANK: Final[Mapping[str, int]] = {"valid": 0, "flagged": 1, "unknown": 2, "invalid": 3}


@dataclass(frozen=True)
class QuantityStatus:
    """The validity of one quantity as the page shows it.

    Attributes
    ----------
    quantity : str
        Key in ``summary["validity"]`` (``depth_mm``...).
    status : {"valid", "flagged", "invalid", "unknown"}
        ``unknown``: the session records no validity for it.
    flags : tuple of str
        The flags that concern it.
    reason : str or None
        Why it is flagged or invalid (one line).
    """

    quantity: str
    status: Status
    flags: tuple[str, ...] = ()
    reason: str | None = None

    @property
    def symbol(self) -> str:
        """The quantity's symbol (``D_p``...)."""
        return QUANTITY_NAMES.get(self.quantity, (self.quantity, ""))[0]

    @property
    def name(self) -> str:
        """A few words naming the quantity."""
        return QUANTITY_NAMES.get(self.quantity, ("", self.quantity))[1]


def _entry(quantity: str, raw: Any) -> QuantityStatus:
    status = value_at(raw, "status")
    if status not in ("valid", "flagged", "invalid"):
        return QuantityStatus(quantity, "unknown", (), "no validity recorded")
    flags = value_at(raw, "flags")
    reason = value_at(raw, "reason")
    return QuantityStatus(
        quantity,
        status,
        tuple(str(f) for f in flags) if isinstance(flags, list) else (),
        str(reason) if reason else None,
    )


def read_validity(summary: Mapping[str, Any] | None) -> dict[str, QuantityStatus] | None:
    """Each quantity's validity in ``summary``; None when the summary records none."""
    raw = value_at(summary, "validity")
    if not isinstance(raw, Mapping):
        return None
    return {str(q): _entry(str(q), v) for q, v in raw.items()}


def combined(
    validity: Mapping[str, QuantityStatus] | None, quantities: Sequence[str]
) -> QuantityStatus | None:
    """The worst status among ``quantities`` (flags merged, the worst one's reason).

    None when no quantity is given; ``unknown`` when the session records no validity or
    lacks one of them.
    """
    if not quantities:
        return None
    entries = [
        (validity or {}).get(q) or QuantityStatus(q, "unknown", (), "no validity recorded")
        for q in quantities
    ]
    if validity is None:
        return QuantityStatus(quantities[0], "unknown", (), None)
    worst = max(entries, key=lambda e: _RANK[e.status])
    flags = tuple(sorted({f for e in entries for f in e.flags}))
    reason = worst.reason
    if worst.quantity != quantities[0] and reason and worst.status == "invalid":
        reason = f"{worst.symbol} is invalid: {reason}"
    return QuantityStatus(quantities[0], worst.status, flags, reason)


@dataclass(frozen=True)
class VerdictView:
    """The top of a session's page: a coloured status, one line, the quantities to name.

    Attributes
    ----------
    status : {"complete", "flagged", "invalid", "incomplete", "unknown"}
        ``unknown``: the session records no validity (an older session, or none finished).
    line : str
        A few words on what the status means (no reasons: those are the problems').
    problems : tuple of QuantityStatus
        Every flagged or invalid quantity, primary ones first.
    """

    status: VerdictStatus
    line: str
    problems: tuple[QuantityStatus, ...]


def _primary_status(validity: Mapping[str, QuantityStatus]) -> VerdictStatus:
    statuses = [validity[q].status if q in validity else "invalid" for q in PRIMARY_QUANTITIES]
    if any(s in ("invalid", "unknown") for s in statuses):
        return "invalid"
    return "flagged" if "flagged" in statuses else "complete"


def session_verdict(summary: Mapping[str, Any] | None, session_status: str) -> VerdictView:
    """The verdict the page shows for a session.

    Parameters
    ----------
    summary : mapping or None
        ``summary.json`` (None: the session has none).
    session_status : str
        The session's final state (``complete``, ``fault``, ``interrupted``...).

    Returns
    -------
    VerdictView
        The summary's verdict, checked against its quantities: "complete" is shown only
        when the session completed and every primary quantity is valid; otherwise the
        status the quantities imply (``incomplete`` for a session that did not complete).
        Its line is a few words on what the status means (:func:`verdict_line`); the
        reasons are the problems', one per quantity, not the summary's recorded sentence.
    """
    if summary is None:
        if session_status != "complete":
            return VerdictView(
                "incomplete", verdict_line("incomplete", session_status, "no summary.json"), ()
            )
        return VerdictView("unknown", "validity unknown: the session has no summary.json", ())
    validity = read_validity(summary)
    end = value_at(summary, "end_reason")
    end_reason = str(end) if isinstance(end, str) and end.strip() else None
    if validity is None:
        if session_status != "complete":
            return VerdictView(
                "incomplete", verdict_line("incomplete", session_status, end_reason), ()
            )
        return VerdictView("unknown", UNKNOWN_LINE, ())
    order = [*PRIMARY_QUANTITIES, *SECONDARY_QUANTITIES]
    order += sorted(q for q in validity if q not in order)
    problems = tuple(validity[q] for q in order if q in validity and validity[q].status != "valid")
    status = value_at(summary, "verdict", "status")
    implied = _primary_status(validity) if validity else "invalid"
    if session_status != "complete" or status == "incomplete":
        implied = "incomplete"
    shown: VerdictStatus = status if status in _VERDICTS else implied
    if _RANK_VERDICT[implied] > _RANK_VERDICT[shown]:
        shown = implied  # the recorded verdict is milder than its quantities allow
    return VerdictView(shown, verdict_line(shown, session_status, end_reason), problems)


#: Verdicts in increasing gravity, for checking a recorded one against its quantities.
_RANK_VERDICT: Final[Mapping[str, int]] = {
    "complete": 0,
    "flagged": 1,
    "invalid": 2,
    "incomplete": 3,
    "unknown": 4,
}


def verdict_line(status: VerdictStatus, session_status: str, why: str | None = None) -> str:
    """A few words on what ``status`` means (the quantities' reasons are listed under it).

    ``why`` says how an incomplete session ended (its ``end_reason``).
    """
    if status == "incomplete":
        how = session_status if why is None else f"{session_status}: {why}"
        return f"the session did not finish ({how}); results are what its data allow"
    if status == "invalid":
        return "some primary results cannot be trusted"
    if status == "flagged":
        return "every primary result has a value; some carry a caveat"
    if status == "complete":
        return "every primary result is valid"
    return UNKNOWN_LINE
