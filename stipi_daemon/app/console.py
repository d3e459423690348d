"""The operator's console: what phase the measurement is in and what to do next.

Two renderings of the same information: a rich live view (phase, progress bar, force,
S_k, live parameters, the current instruction) when standard output is a terminal, and
plain timestamped lines otherwise (logs, tests, CI), where instructions are repeated at
most every 5 s unless what they ask for changes. This module only formats; it owns no
measurement state.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
from typing import Any, TextIO

from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.progress_bar import ProgressBar
from rich.table import Table
from rich.text import Text

from stipi_daemon.analysis.validity import (
    PRIMARY_QUANTITIES,
    QUANTITY_SYMBOLS,
    SECONDARY_QUANTITIES,
)
from stipi_daemon.measurement.pipeline import LiveParameters
from stipi_daemon.measurement.state_machine import (
    Advisory,
    Fault,
    MeasurementConfig,
    OperatorPrompt,
    Output,
    Phase,
    PhaseChanged,
)

__all__ = [
    "ETA",
    "ETA_TAU",
    "VERDICT_STYLES",
    "OperatorConsole",
    "format_results",
    "verdict_lines",
    "verdict_status",
]

#: Plain mode repeats an unchanged instruction at most this often [s of session time].
PROMPT_REPEAT_S = 5.0
#: The console's (ASCII) symbols of the two viscosities: the paper's eta = E*T_r (Eq. 8)
#: and eta_tau = E*tau from the fitted Kelvin-Voigt tau (docs/analysis.md, "Two
#: viscosities"); the report writes them η and η_τ.
ETA = "eta"
ETA_TAU = "eta_tau"


def _fmt(v: float | None, unit: str, digits: int = 3) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}g} {unit}"


class OperatorConsole:
    """Shows the measurement to the operator.

    Parameters
    ----------
    measurement : MeasurementConfig
        For phase durations (progress bar).
    out : TextIO
        Where to write (default stdout).
    live : bool or None
        Rich live view; ``None`` chooses it when ``out`` is a terminal.
    quiet : bool
        Print nothing (results still go to the session).
    """

    def __init__(
        self,
        measurement: MeasurementConfig,
        out: TextIO | None = None,
        *,
        live: bool | None = None,
        quiet: bool = False,
    ) -> None:
        self.config = measurement
        #: Why the console's output failed (closed at start, disk full, I/O error), once
        #: it has: the measurement is then stopped as by Ctrl-C (:meth:`_output_failed`).
        self.lost: str | None = None
        self._measuring = False
        stdout = out if out is not None else sys.stdout
        self._closed_at_start = stdout is None  # started with stdout closed (``>&-``)
        self.out: TextIO = stdout if stdout is not None else open(os.devnull, "w")
        self.quiet = quiet
        self.rich = Console(file=self.out)
        self.use_live = (self.out.isatty() if live is None else live) and not quiet
        self._live: Live | None = None
        self.phase = Phase.IDLE
        self.phase_since_s = 0.0
        self.now_s = 0.0
        self.prompt = ""
        self.force_n: float | None = None
        self.s_k: float | None = None
        self.fps: float | None = None
        self.params: LiveParameters | None = None
        self.notes: list[str] = []
        #: A standing warning the live view shows (frames not processed), None: none.
        self.warning: str | None = None
        self._prompt_key = ""
        self._prompt_t = -math.inf

    # ---------------------------------------------------------------- lifecycle

    def __enter__(self) -> OperatorConsole:
        self._measuring = True
        if self.use_live:
            self._live = Live(self._render(), console=self.rich, refresh_per_second=4)
            self._live.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._measuring = False
        if self._live is not None:
            self._live.update(self._render())
            self._live.__exit__(None, None, None)
            self._live = None

    def line(self, text: str, style: str | None = None) -> None:
        """Print one line above the live view (or plainly).

        ``style`` (a rich style, e.g. ``"bold green"``) colours the line on a terminal;
        plain output (logs, pipes) gets the text alone.
        """
        if self._closed_at_start and self.lost is None:
            self._output_failed("standard output is closed")
        if self.quiet:
            return
        try:
            if self._live is not None:
                self._live.console.print(text, style=style, markup=False, highlight=False)
            elif style is not None and self.out.isatty():
                self.rich.print(text, style=style, markup=False, highlight=False, soft_wrap=True)
            else:
                print(text, file=self.out, flush=True)
        except BrokenPipeError:
            self._output_closed()
        except OSError as exc:  # disk full (``>/dev/full``), I/O error (terminal gone)
            self._output_failed(f"standard output failed: {exc.strerror or exc}")

    def _output_failed(self, reason: str) -> None:
        """The console's output cannot be written (closed at start, full, an I/O error):
        the console prints nothing more and, while measuring, stops the measurement as
        Ctrl-C does (SIGINT: asyncio cancels it, the session is finished ``aborted`` and
        whole); :attr:`lost` says why, for the one line the command prints at the end.
        Unlike a closed pipe (:meth:`_output_closed`), a terminal or a disk that fails
        takes the operator's instructions with it."""
        self.quiet = True
        live, self._live = self._live, None
        if live is not None:
            with contextlib.suppress(OSError):
                live.stop()
        if self.out is sys.stdout and sys.stdout is not None:
            with contextlib.suppress(OSError, ValueError):
                stdout_to_devnull()
        if self.lost is not None:
            return
        self.lost = reason
        if self._measuring and threading.current_thread() is threading.main_thread():
            signal.raise_signal(signal.SIGINT)  # asyncio.run's Ctrl-C: cancels the measurement

    def _output_closed(self) -> None:
        """What read the console's output stopped reading (``... | head``, a closed
        terminal): the measurement goes on, printing nothing more, and says so once on
        stderr. Stdout is pointed at /dev/null, so that later prints (the results) and
        Python's flush at exit do not fail again."""
        self.quiet = True
        if self.out is sys.stdout:
            stdout_to_devnull()
        live, self._live = self._live, None
        if live is not None:
            with contextlib.suppress(OSError):  # its last refresh, to the closed output
                live.stop()
        print(
            "stipi-daemon: warning: the console's output was closed: the measurement goes on "
            "without it, its results are written to the session",
            file=sys.stderr,
            flush=True,
        )

    # ---------------------------------------------------------------- updates

    def update(
        self,
        now_s: float,
        *,
        force_n: float | None = None,
        s_k: float | None = None,
        fps: float | None = None,
        params: LiveParameters | None = None,
    ) -> None:
        """New readings; refreshes the live view."""
        self.now_s = now_s
        if force_n is not None:
            self.force_n = force_n
        if s_k is not None:
            self.s_k = s_k
        if fps is not None:
            self.fps = fps
        if params is not None:
            self.params = params
            if not self.use_live and int(params.elapsed_s) % 5 == 0:
                self.line(
                    f"[{now_s:7.2f} s] recovery {params.elapsed_s:5.1f} s:"
                    f" D_p {_fmt(params.depth_mm, 'mm')},"
                    f" F_r {_fmt(params.rebound_force_n, 'N')},"
                    f" T_r {'>=' if not params.settled else ''}"
                    f"{_fmt(params.recovery_time_s, 's')},"
                    f" E {_fmt(params.elasticity_kpa, 'kPa')}, tau {_fmt(params.tau_s, 's')},"
                    f" {ETA} {'>=' if not params.settled else ''}"
                    f"{_fmt(params.viscosity_n_s_per_mm2, 'N*s/mm^2')},"
                    f" {ETA_TAU} "
                    f"{_fmt(params.viscosity_from_time_constant_n_s_per_mm2, 'N*s/mm^2')}"
                )
        if self._live is not None:
            self._live.update(self._render())

    def warn(self, text: str | None) -> None:
        """Show ``text`` as the live view's standing warning (None: clear it); the line
        that says so is printed by :meth:`line`."""
        if text == self.warning:
            return
        self.warning = text
        if self._live is not None:
            self._live.update(self._render())

    def outputs(self, outputs: list[Output], now_s: float) -> None:
        """Show state-machine outputs (phase changes, instructions, notes, faults)."""
        self.now_s = now_s
        for o in outputs:
            if isinstance(o, PhaseChanged):
                self.phase, self.phase_since_s = o.new, o.t_s
                self.line(f"[{o.t_s:7.2f} s] {o.old} -> {o.new}: {o.reason}")
            elif isinstance(o, OperatorPrompt):
                self.prompt = o.text
                key = o.text.split(":", 1)[0]
                if not self.use_live and (
                    key != self._prompt_key or now_s - self._prompt_t >= PROMPT_REPEAT_S
                ):
                    self._prompt_key, self._prompt_t = key, now_s
                    self.line(f"           >> {o.text}")
            elif isinstance(o, Advisory):
                self.line(f"[{o.t_s:7.2f} s] note: {o.kind}: {o.detail}")
            elif isinstance(o, Fault):
                self.line(f"[{o.t_s:7.2f} s] FAULT {o.kind}: {o.reason}")
        if self._live is not None:
            self._live.update(self._render())

    # ---------------------------------------------------------------- rendering

    def _progress(self) -> tuple[float, float]:
        c = self.config
        elapsed = max(0.0, self.now_s - self.phase_since_s)
        total = {
            Phase.PITTING: c.pitting_duration_s,
            Phase.RECOVERY: c.recovery_max_s,
        }.get(self.phase, 0.0)
        return elapsed, total

    def _render(self) -> Panel:
        elapsed, total = self._progress()
        head = Text.assemble(
            ("phase ", "dim"),
            (str(self.phase).upper(), "bold cyan"),
            (f"   t = {self.now_s:6.1f} s", "dim"),
        )
        # A ProgressBar ends no line of its own (it is made for table cells): in a Group it
        # would share its line with the readings, which a full-width bar pushes off screen.
        bar = Table.grid(expand=True)
        bar.add_row(
            ProgressBar(total=total or 1.0, completed=min(elapsed, total) if total else 0.0)
        )
        readings = Table.grid(padding=(0, 2))
        readings.add_row(
            f"force {_fmt(self.force_n, 'N', 3)}",
            f"S_k {_fmt(self.s_k, 'px', 6)}",
            f"camera {_fmt(self.fps, 'fps', 3)}",
        )
        params = Table(box=None, show_header=False, padding=(0, 2))
        p = self.params
        if p is not None:
            params.add_row("D_p", _fmt(p.depth_mm, "mm", 4), "F_r", _fmt(p.rebound_force_n, "N", 4))
            t_r = _fmt(p.recovery_time_s, "s", 4)
            params.add_row(
                "T_r", ("" if p.settled else ">= ") + t_r, "E", _fmt(p.elasticity_kpa, "kPa", 4)
            )
            eta = _fmt(p.viscosity_n_s_per_mm2, "N*s/mm^2", 3)
            params.add_row("tau", _fmt(p.tau_s, "s", 4), ETA, ("" if p.settled else ">= ") + eta)
            params.add_row(
                "", "", ETA_TAU, _fmt(p.viscosity_from_time_constant_n_s_per_mm2, "N*s/mm^2", 3)
            )
        prompt = Text(self.prompt or " ", style="bold yellow")
        parts: list[Any] = [head, bar, readings, params, prompt]
        if self.warning:
            parts.append(Text(f"WARNING {self.warning}", style="bold red"))
        return Panel(Group(*parts), title="STIP-I measurement")


#: Rich style of the verdict line, by verdict status: green only for ``complete``.
VERDICT_STYLES: dict[str, str] = {
    "complete": "bold green",
    "flagged": "bold yellow",
    "invalid": "bold red",
    "incomplete": "bold red",
    "unknown": "bold",
}


def verdict_status(summary: dict[str, Any]) -> str:
    """The summary's verdict status; ``unknown`` for a summary written before verdicts."""
    v = summary.get("verdict")
    status = v.get("status") if isinstance(v, dict) else None
    return str(status) if status in VERDICT_STYLES else "unknown"


def verdict_lines(summary: dict[str, Any]) -> list[str]:
    """The verdict, then each flagged or invalid quantity with its reason, one per line.

    The first line is the verdict (``complete`` only when the session ended DONE and every
    primary quantity is valid, docs/analysis.md); a summary without a verdict (an older
    session) reads ``verdict: UNKNOWN``.
    """
    status = verdict_status(summary)
    v = summary.get("verdict")
    line = v.get("line") if isinstance(v, dict) else None
    if status == "unknown":
        line = "validity not recorded (a session from before validity was assessed)"
    out = [f"verdict: {status.upper()}: {line or ''}".rstrip(": ")]
    validity = summary.get("validity")
    if not isinstance(validity, dict) or not summary.get("results"):
        return out
    for q in (*PRIMARY_QUANTITIES, *SECONDARY_QUANTITIES):
        entry = validity.get(q)
        if not isinstance(entry, dict) or entry.get("status") not in ("flagged", "invalid"):
            continue
        flags = entry.get("flags") or []
        tail = f" [{', '.join(str(f) for f in flags)}]" if flags else ""
        out.append(f"  {QUANTITY_SYMBOLS[q]} {entry['status']}: {entry.get('reason') or '-'}{tail}")
    return out


def _shown(summary: dict[str, Any], quantity: str | tuple[str, ...], text: str) -> str:
    """A value as the results show it: ``invalid`` for an invalid quantity (its value is
    recorded in the summary, never shown as a result), marked ``(flagged)`` when flagged. A
    value computed from several quantities (a tuple) takes the worst of their statuses."""
    validity = summary.get("validity")
    statuses = set()
    for q in (quantity,) if isinstance(quantity, str) else quantity:
        entry = validity.get(q) if isinstance(validity, dict) else None
        statuses.add(entry.get("status") if isinstance(entry, dict) else None)
    if "invalid" in statuses:
        return "invalid"
    return f"{text} (flagged)" if "flagged" in statuses else text


def format_results(summary: dict[str, Any]) -> list[str]:
    """The final results as console lines: the verdict and the reasons
    (:func:`verdict_lines`), then the parameters, both estimators and the severity, invalid
    values replaced by ``invalid``."""
    res = summary.get("results")
    head = verdict_lines(summary)
    if not res:
        why = summary.get("analysis_error") or summary.get("end_reason")
        return [*head, f"no results: {why}"]
    p = res["pitting"]
    paper = res["paper_estimator"] or {}
    fit = res["fitted_recovery"]
    fm = fit["model"] or {}
    tau_se = fit.get("tau_se_s")

    def val(q: str | tuple[str, ...], v: float | None, unit: str) -> str:
        return _shown(summary, q, _fmt(v, unit, 4))

    tau = _fmt(fit["tau_s"], "s", 4) + (f" +- {tau_se:.2g} s" if tau_se is not None else "")
    lines = [
        "",
        *head,
        "",
        "results",
        f"  pitting depth      D_p = {val('depth_mm', p['depth_mm'], 'mm')}      (Eq. 3)",
        f"  rebound force      F_r = {val('rebound_force_n', p['rebound_force_n'], 'N')}"
        "       (Eq. 5)",
        f"  recovery time      T_r = {val('recovery_time_s', p['recovery_time_s'], 's')}"
        "       (Eq. 6)",
        f"  applied force      F_a = {val('applied_force_n', res['applied_force_n'], 'N')}",
        f"  elasticity         E   = {val('elasticity_kpa', paper.get('elasticity_kpa'), 'kPa')}"
        "  (Eq. 7)",
        f"  viscosity          {ETA} = "
        + val("viscosity_n_s_per_mm2", paper.get("viscosity_n_s_per_mm2"), "N*s/mm^2")
        + " (Eq. 8, E*T_r)",
        f"  time constant      tau = {_shown(summary, 'tau_s', tau)}"
        "  (fitted Kelvin-Voigt recovery)",
        f"  viscosity (fit)    {ETA_TAU} = "
        + val(
            ("viscosity_fit_n_s_per_mm2", "elasticity_kpa", "tau_s"),  # own, or E's and tau's
            fm.get("viscosity_n_s_per_mm2"),
            "N*s/mm^2",
        )
        + " (E*tau)",
    ]
    lines.extend(_severity_lines(summary, res["severity"]))
    if res["flags"]:
        lines.append(f"  flags: {', '.join(res['flags'])}")
    return lines


def _severity_lines(summary: dict[str, Any], severity: dict[str, Any]) -> list[str]:
    """One line per severity estimator; the paper's class is never shown when invalid."""
    lines = []
    for name, sev in severity.items():
        if sev is None:
            continue
        label = f"  severity ({name.replace('_', ' ')}): "
        if name == "paper_estimator" and _shown(summary, "severity", "") == "invalid":
            lines.append(label + "invalid")
            continue
        lines.append(
            label + f"{sev['severity'].upper()},"
            f" nearest grade {sev['nearest_grade']}, recovered {sev['recovered_percent']:.1f} %"
            f" in {sev['window_s'][0]:g}-{sev['window_s'][1]:g} s"
            f" (threshold {sev['threshold_recovered_percent']:.1f} %)"
        )
    return lines


def stdout_to_devnull() -> None:
    """Point the process's stdout at /dev/null, after whatever read it stopped reading:
    later prints and Python's flush at exit then succeed instead of raising
    BrokenPipeError (or ENOSPC, EIO) again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    with contextlib.suppress(OSError):  # what could not be written goes to /dev/null now
        sys.stdout.flush()
