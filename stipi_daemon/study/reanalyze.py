"""``study reanalyze``: every session of a study analysed again, as Dask distributed tasks.

Each session of the dataset's ``sessions`` table is one task, :func:`analyse_session`:
the offline analysis of ``stipi-daemon analyze SESSION``
(:func:`stipi_daemon.app.analyze.replay_session`) with the settings of a settings file
(:mod:`.settings`), optionally counting S_k again on the session's video
(``--recompute-sk``). The task checks first that the session still holds the data that
was indexed (its data hash), then writes the session's ``results`` row of the new
analysis version atomically (``results/analysis=V/site=/probe=/date=/<uid>.parquet``) and
returns it. A session whose analysis fails is a row with ``error`` (one line) and no
values; the run goes on.

Where the tasks run (:func:`reanalyze`):

* by default an embedded :class:`distributed.LocalCluster` sized to the machine: one
  worker process per CPU, one thread each (the analysis holds the GIL in places);
* ``scheduler="tcp://HOST:8786"``: a running Dask cluster (``dask scheduler``, ``dask
  worker``), which must see the dataset and the sessions at the same paths;
* ``scheduler="synchronous"`` (``--serial``): in this process, one after the other; the
  same function, the reference the distributed paths are tested against.

Resumable: a session whose results file for V exists and carries the session's data hash
and the settings hash is not analysed again, so a run stopped in any way (the client
killed, the machine restarted) is finished by running it again. A worker that dies
mid-task loses nothing: the scheduler gives the task to another worker (and the nanny
starts a new worker); the task writes the same file whoever runs it. A task that fails
outside the analysis (a worker lost more than ``distributed.scheduler.allowed-failures``
times) is reported and writes nothing, so a rerun tries it again.

``analyses/V.json`` records how V was made: the settings as given and normalised, the
settings hash, the package version, ``--recompute-sk``, and each run (start, end, where,
sessions analysed, skipped, errors) with the totals.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import re
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TextIO

import pyarrow.parquet as pq

from stipi_daemon import __version__
from stipi_daemon.analysis.imaging import CircleROI, RectROI
from stipi_daemon.errors import ConfigError, SessionError, StipiError
from stipi_daemon.storage import layout
from stipi_daemon.storage.lock import WriterLock
from stipi_daemon.study.dataset import (
    ANALYSES_DIR,
    RECORDED,
    StudyError,
    load_state,
    partition_value,
    results_row,
    to_table,
    write_parquet_atomic,
)
from stipi_daemon.study.settings import StudySettings, load_settings, settings_hash

__all__ = [
    "ANALYSIS_FORMAT",
    "Plan",
    "ReanalysisReport",
    "SessionTask",
    "analyse_session",
    "list_sessions",
    "reanalyze",
    "version_name",
]

ANALYSIS_FORMAT: Final = "stipi-study-analysis"
#: ``--scheduler`` value that runs every task in this process (the reference path).
SYNCHRONOUS: Final = "synchronous"
#: How long ``--scheduler`` is tried before the run is refused [s] (Dask retries a refused
#: connection until then: a scheduler that is still starting is waited for).
SCHEDULER_CONNECT_TIMEOUT_S: Final = 30.0
#: Times a task that raised is run again (the analysis itself never raises: its errors
#: are rows; this covers a worker's own failures, e.g. out of memory).
TASK_RETRIES: Final = 2
#: Operating-system errors that may pass (a network filesystem's, memory): the task is
#: retried, not given an error row.
_TRANSIENT_ERRNOS: Final = frozenset(
    {errno.EIO, errno.ESTALE, errno.ETIMEDOUT, errno.EAGAIN, errno.ENOMEM, errno.EINTR}
)
_NAME_RE: Final = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,99}")


@dataclass(frozen=True)
class SessionTask:
    """One session to analyse: its uid, directory, indexed data hash and the relative
    partition directory of its dataset files (``site=.../probe=.../date=...``)."""

    uid: str
    path: str
    data_hash: str
    partition: str


@dataclass(frozen=True)
class Plan:
    """What every task does (pickled to the workers: plain values only).

    Attributes
    ----------
    dataset : str
        The dataset directory (absolute; the same path on every worker).
    version : str
        The analysis version written.
    settings_hash : str
        The settings' hash (:func:`~stipi_daemon.study.settings.settings_hash`).
    recompute_sk : bool
        Count S_k again on each session's video.
    calibration : str or None
        Calibration file replacing each session's (absolute).
    threshold_p : int or None
        Threshold p of Eq. (1) [0..255] replacing every other source.
    roi, roi_given :
        ROI [px] replacing every other source when ``roi_given`` (None: the whole frame).
    sections : dict
        Fields set over each session's measurement/analysis/imaging sections.
    """

    dataset: str
    version: str
    settings_hash: str
    recompute_sk: bool
    calibration: str | None = None
    threshold_p: int | None = None
    roi: CircleROI | RectROI | None = None
    roi_given: bool = False
    sections: dict[str, dict[str, Any]] = field(default_factory=dict)

    def result_path(self, task: SessionTask) -> Path:
        return (
            Path(self.dataset)
            / "results"
            / f"analysis={partition_value(self.version)}"
            / task.partition
            / f"{task.uid}.parquet"
        )


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if isinstance(exc, StipiError) else f"{type(exc).__name__}: {text}"


def _analyse(task: SessionTask, plan: Plan) -> dict[str, Any]:
    """The recomputed summary of one session (raises on any failure)."""
    from stipi_daemon.app.analyze import AnalyzeRequest, replay_session
    from stipi_daemon.storage.reader import SessionReader
    from stipi_daemon.storage.schema import to_jsonable
    from stipi_daemon.study.hashing import data_hash

    with SessionReader(task.path) as reader:
        now = data_hash(reader)
    if now != task.data_hash:
        raise StudyError(
            f"{task.path}: the session changed since it was indexed (data hash {now[:19]}, "
            f"indexed {task.data_hash[:19]}): run `study index` again"
        )
    request = AnalyzeRequest(
        session_dir=Path(task.path),
        calibration=None if plan.calibration is None else Path(plan.calibration),
        threshold_p=plan.threshold_p,
        roi=plan.roi,
        roi_given=plan.roi_given,
        recompute_sk=plan.recompute_sk,
        sections=plan.sections,
    )
    doc = replay_session(request)[0]
    summary: dict[str, Any] = to_jsonable(doc["summary"], "summary")
    return summary


def _one_thread_on_a_worker() -> None:
    """On a Dask worker (one task thread per process, BLAS and OpenMP held to one thread
    by the nanny's environment), OpenCV's own thread pool and FFmpeg's video decoder held
    to one thread too, so that the worker processes do not oversubscribe the CPUs (the
    serial path keeps them)."""
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return
    import cv2

    from stipi_daemon.storage.video_readback import set_decode_threads

    if cv2.getNumThreads() != 1:
        cv2.setNumThreads(1)
    set_decode_threads(1)


def analyse_session(task: SessionTask, plan: Plan) -> dict[str, Any]:
    """Analyse one session, write its ``results`` file of ``plan.version`` atomically and
    return the row. A failure of the analysis is the row's ``error``; what may pass
    (out of memory, an I/O error or timeout such as a network filesystem's) and a
    failure to write the file raise, so that Dask retries the task and, failing that,
    nothing is written and a rerun tries again. Idempotent: the same inputs write the
    same row (but for ``analysed_utc``)."""
    _one_thread_on_a_worker()
    try:
        summary: dict[str, Any] | None = _analyse(task, plan)
        error = None
    except MemoryError:
        raise
    except OSError as exc:
        if exc.errno in _TRANSIENT_ERRNOS:
            raise
        summary, error = None, _one_line(exc)
    except Exception as exc:  # the analysis failed on this session: told in its row
        summary, error = None, _one_line(exc)
    row = results_row(
        session_uid=task.uid,
        analysis_version=plan.version,
        data_hash=task.data_hash,
        settings_hash=plan.settings_hash,
        package_version=__version__,
        analysed_utc=layout.utc_now_iso(),
        summary=summary,
        error=error,
    )
    write_parquet_atomic(
        plan.result_path(task), to_table("results", {k: [v] for k, v in row.items()})
    )
    return row


# --------------------------------------------------------------------------------------------
# the dataset's side
# --------------------------------------------------------------------------------------------


def version_name(name: str | None, settings_hash_value: str) -> str:
    """The analysis version: ``name``, else ``s-`` and 12 hex digits of the settings hash.

    Raises
    ------
    ConfigError
        A name that is not 1-100 of ``A-Z a-z 0-9 . _ + -`` (not starting with a
        punctuation mark), or ``recorded`` (the daemon's own results).
    """
    if name is None:
        return "s-" + settings_hash_value.removeprefix("sha256:")[:12]
    if not _NAME_RE.fullmatch(name):
        raise ConfigError(
            f"--name {name!r}: use 1-100 letters, digits and . _ + - (starting with a "
            "letter or digit)"
        )
    if name == RECORDED:
        raise ConfigError(f"--name {name}: 'recorded' is the daemon's own analysis")
    return name


def list_sessions(dataset: Path) -> list[SessionTask]:
    """Every session of the dataset's ``sessions`` table, by uid.

    Raises
    ------
    StudyError
        Not a study dataset, or a sessions file cannot be read.
    """
    load_state(dataset)
    root = dataset / "sessions"
    tasks: dict[str, SessionTask] = {}
    for path in sorted(root.rglob("*.parquet")) if root.is_dir() else []:
        try:
            table = pq.read_table(path, columns=["session_uid", "path", "data_hash"])
        except (OSError, ValueError) as exc:
            raise StudyError(f"{path}: cannot read ({_one_line(exc)})") from None
        partition = path.parent.relative_to(root).as_posix()
        for row in table.to_pylist():
            uid = row["session_uid"]
            if uid in tasks:
                raise StudyError(f"{path}: session_uid {uid} is in two sessions files")
            tasks[uid] = SessionTask(uid, row["path"], row["data_hash"], partition)
    return [tasks[uid] for uid in sorted(tasks)]


def finished(plan: Plan, tasks: Sequence[SessionTask]) -> dict[str, str | None]:
    """Sessions whose results file for ``plan.version`` holds their data hash and the
    settings hash: uid -> the row's error (None: analysed). Results files of this version
    for a session that now lives in another partition are removed (this run wrote them)."""
    done: dict[str, str | None] = {}
    wanted = {t.uid: plan.result_path(t) for t in tasks}
    by_uid = {t.uid: t for t in tasks}
    root = Path(plan.dataset) / "results" / f"analysis={partition_value(plan.version)}"
    for path in sorted(root.rglob("*.parquet")) if root.is_dir() else []:
        uid = path.stem
        if uid in wanted and path != wanted[uid]:
            path.unlink(missing_ok=True)
            continue
        if uid not in by_uid:
            continue
        try:
            cols = ["session_uid", "data_hash", "settings_hash", "error"]
            row = pq.read_table(path, columns=cols).to_pylist()
        except (OSError, ValueError):
            continue  # unreadable: analysed again, the file replaced
        if (
            len(row) == 1
            and row[0]["session_uid"] == uid
            and row[0]["data_hash"] == by_uid[uid].data_hash
            and row[0]["settings_hash"] == plan.settings_hash
        ):
            done[uid] = row[0]["error"]
    return done


# --------------------------------------------------------------------------------------------
# running the tasks
# --------------------------------------------------------------------------------------------

#: Called as each session ends: the task, its row (None when the task failed) and why it
#: failed (None when it did not).
_OnDone = Callable[[SessionTask, dict[str, Any] | None, str | None], None]


def package_version() -> str:
    """This process's stipi-daemon version (run on every worker before the tasks)."""
    return __version__


def run_serial(tasks: Sequence[SessionTask], plan: Plan, on_done: _OnDone) -> None:
    """Run every task in this process, one after the other (the reference path)."""
    for task in tasks:
        try:
            row = analyse_session(task, plan)
        except (StipiError, OSError, MemoryError) as exc:
            on_done(task, None, _one_line(exc))
        else:
            on_done(task, row, None)


@contextmanager
def dask_client(scheduler: str | None, workers: int | None) -> Iterator[tuple[Any, str]]:
    """A :class:`distributed.Client` of the cluster at ``scheduler``, or of an embedded
    :class:`~distributed.LocalCluster` of ``workers`` processes (default: one per CPU),
    one thread each; and a description of where the tasks run. Closed on exit."""
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=SCHEDULER_CONNECT_TIMEOUT_S)  # type: ignore[no-untyped-call]
        except (OSError, TimeoutError, ValueError) as exc:
            raise StudyError(
                f"--scheduler {scheduler}: cannot connect ({_one_line(exc)})"
            ) from None
        with client:
            n = len(client.scheduler_info(n_workers=-1).get("workers", {}))
            yield client, f"Dask scheduler {scheduler} ({n} workers when it started)"
        return
    n = workers if workers is not None else len(os.sched_getaffinity(0))
    with (
        LocalCluster(  # type: ignore[no-untyped-call]
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",  # its HTTP server on a free port, not 8787 (may be taken)
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,  # type: ignore[no-untyped-call]
    ):
        yield client, f"LocalCluster, {n} worker process(es) x 1 thread"


def run_distributed(
    tasks: Sequence[SessionTask], plan: Plan, client: Any, on_done: _OnDone
) -> None:
    """Run every task on ``client``'s cluster; ``on_done`` as each finishes.

    Raises
    ------
    StudyError
        A worker runs another stipi-daemon version than this process.
    """
    from distributed import as_completed

    versions = client.run(package_version)
    other = {addr: v for addr, v in versions.items() if v != __version__}
    if other:
        addr, version = next(iter(other.items()))
        raise StudyError(
            f"worker {addr} runs stipi-daemon {version}, this is {__version__}: install the "
            "same version on every worker"
        )
    token = uuid.uuid4().hex[:8]  # a rerun's tasks never meet an old run's in the scheduler
    keys = [f"reanalyze-{plan.version}-{task.uid}-{token}" for task in tasks]
    futures = client.map(
        analyse_session, tasks, plan=plan, key=keys, retries=TASK_RETRIES, pure=False
    )
    by_key = {future.key: task for future, task in zip(futures, tasks, strict=True)}
    for future in as_completed(futures):  # type: ignore[no-untyped-call]
        task = by_key[future.key]
        try:
            row = future.result()
        except Exception as exc:  # the task's worker was lost too often, or it raised
            on_done(task, None, _one_line(exc))
        else:
            on_done(task, row, None)
        future.release()


class Progress:
    """A progress bar (rich) on a terminal, else a plain line every 5 % and at the end."""

    def __init__(self, total: int, stream: TextIO | None, what: str) -> None:
        self.total, self.done, self.errors = total, 0, 0
        self._stream = stream
        self._what = what
        self._step = max(1, total // 20)
        self._bar: Any = None
        if stream is not None and stream.isatty() and total:
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

            self._bar = Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(file=stream),
                transient=False,
            )
            self._bar.start()
            self._task = self._bar.add_task(what, total=total)

    def advance(self, error: bool) -> None:
        self.done += 1
        self.errors += int(error)
        if self._bar is not None:
            desc = f"{self._what} ({self.errors} errors)" if self.errors else self._what
            self._bar.update(self._task, advance=1, description=desc)
        elif self._stream is not None and (self.done % self._step == 0 or self.done == self.total):
            print(
                f"{self._what}: {self.done}/{self.total} sessions, {self.errors} errors",
                file=self._stream,
                flush=True,
            )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


# --------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------


@dataclass
class ReanalysisReport:
    """What a run did.

    Attributes
    ----------
    dataset : Path
    version : str
        The analysis version written.
    settings_hash : str
    where : str
        Where the tasks ran.
    sessions : int
        Sessions in the dataset.
    computed : int
        Sessions analysed by this run.
    skipped : int
        Sessions whose results were there already (same data and settings hashes).
    errors : list of (str, str)
        (session_uid, error) of every session whose results row holds an error, this
        run's and those skipped.
    failed : list of (str, str)
        (session_uid, why) of tasks that ended without a results file (a rerun tries them).
    """

    dataset: Path
    version: str
    settings_hash: str
    where: str = ""
    sessions: int = 0
    computed: int = 0
    skipped: int = 0
    errors: list[tuple[str, str]] = field(default_factory=list)
    failed: list[tuple[str, str]] = field(default_factory=list)

    @property
    def exit_code(self) -> int:
        """0 when every session has its results row (errors included), else 1."""
        return 1 if self.failed else 0

    def lines(self) -> list[str]:
        """The errors and failures, one line each, then the summary."""
        out = [f"error {uid}: {why}" for uid, why in self.errors]
        out += [f"failed {uid} (run again to retry): {why}" for uid, why in self.failed]
        out.append(
            f"{self.dataset}: analysis {self.version}: {self.computed} analysed, "
            f"{self.skipped} already done, {len(self.errors)} with errors, "
            f"{len(self.failed)} failed, of {self.sessions} sessions ({self.where})"
        )
        return out


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def _open_record(
    path: Path, plan: Plan, raw: Any, settings: StudySettings, tasks: int
) -> dict[str, Any]:
    """``analyses/V.json`` as a previous run left it, or a new one.

    Raises
    ------
    StudyError
        V exists and was made with other settings.
    """
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        doc = None
    except (OSError, ValueError) as exc:
        raise StudyError(f"{path}: cannot read ({_one_line(exc)})") from None
    if doc is not None:
        if not isinstance(doc, dict) or doc.get("settings_hash") != plan.settings_hash:
            old = doc.get("settings_hash") if isinstance(doc, dict) else None
            raise StudyError(
                f"{path}: analysis {plan.version} was made with other settings "
                f"({str(old)[:19]}, these are {plan.settings_hash[:19]}): give another --name"
            )
        return doc
    return {
        "format": ANALYSIS_FORMAT,
        "version": 1,
        "analysis_version": plan.version,
        "settings": _jsonable(raw),
        "settings_normalised": settings.normalised(plan.recompute_sk),
        "settings_hash": plan.settings_hash,
        "recompute_sk": plan.recompute_sk,
        "calibration": plan.calibration,
        "package_version": __version__,
        "started_utc": layout.utc_now_iso(),
        "finished_utc": None,
        "status": "running",
        "counts": {"sessions": tasks, "done": 0, "errors": 0, "failed": 0},
        "runs": [],
    }


def _plan(dataset: Path, settings: StudySettings, recompute_sk: bool, name: str | None) -> Plan:
    digest = settings_hash(settings, recompute_sk)
    return Plan(
        dataset=str(dataset),
        version=version_name(name, digest),
        settings_hash=digest,
        recompute_sk=recompute_sk,
        calibration=None if settings.calibration is None else str(settings.calibration),
        threshold_p=settings.threshold_p,
        roi=settings.roi,
        roi_given=settings.roi_given,
        sections=settings.sections(),
    )


def _check_options(
    settings_path: Path,
    settings: StudySettings,
    recompute_sk: bool,
    scheduler: str | None,
    workers: int | None,
) -> None:
    only_sk = settings.changes_s_k_only()
    if only_sk and not recompute_sk:
        raise ConfigError(
            f"{settings_path}: field '{only_sk[0]}' acts on the S_k count, which the stored "
            "S_k already is: give --recompute-sk to count S_k again from each video"
        )
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers}: give 1 or more")
    if workers is not None and scheduler is not None:
        raise ConfigError(
            "--workers sizes the embedded cluster; a cluster given with --scheduler has "
            "its own workers"
        )


def reanalyze(
    dataset: Path,
    settings_path: Path,
    *,
    recompute_sk: bool = False,
    scheduler: str | None = None,
    workers: int | None = None,
    name: str | None = None,
    progress: TextIO | None = None,
) -> ReanalysisReport:
    """Analyse every session of ``dataset`` again with the settings of ``settings_path``
    (see the module doc) and write the analysis version.

    Parameters
    ----------
    scheduler : str or None
        ``tcp://HOST:PORT`` of a Dask scheduler; ``"synchronous"``: in this process; None:
        an embedded LocalCluster of ``workers`` processes (default: one per CPU).
    name : str or None
        The analysis version (default ``s-`` + 12 hex digits of the settings hash).
    progress : text stream or None
        Where the progress goes (a bar on a terminal, else plain lines); None: nowhere.

    Raises
    ------
    ConfigError
        The settings file or an option is wrong (one line, before anything is written).
    StudyError
        Not a study dataset, no sessions, the version exists with other settings, another
        run writes it, or the cluster cannot be reached.
    """
    settings, raw = load_settings(settings_path)
    _check_options(settings_path, settings, recompute_sk, scheduler, workers)
    dataset = dataset.resolve()
    tasks = list_sessions(dataset)
    if not tasks:
        raise StudyError(f"{dataset}: the dataset holds no sessions (run `study index` first)")
    plan = _plan(dataset, settings, recompute_sk, name)
    record_path = dataset / ANALYSES_DIR / f"{plan.version}.json"
    new_dir = not record_path.parent.exists()
    record_path.parent.mkdir(exist_ok=True)
    try:
        lock = WriterLock.acquire(
            record_path.with_suffix(".lock"), started_utc=layout.utc_now_iso()
        )
    except SessionError as exc:
        busy = "another writer" in str(exc)
        raise StudyError(
            f"{dataset}: another `study reanalyze` is writing analysis {plan.version}"
            if busy
            else str(exc)
        ) from None
    try:
        return _run(plan, tasks, record_path, (settings, raw), scheduler, workers, progress)
    finally:
        lock.release()
        if new_dir:  # a run refused before it recorded anything leaves no analyses/
            with contextlib.suppress(OSError):
                record_path.parent.rmdir()


def _save_record(path: Path, doc: dict[str, Any]) -> None:
    try:
        layout.write_json_atomic(path, doc, what="analysis record")
    except StipiError as exc:
        raise StudyError(str(exc)) from None


def _run(
    plan: Plan,
    tasks: list[SessionTask],
    record_path: Path,
    given: tuple[StudySettings, Any],
    scheduler: str | None,
    workers: int | None,
    stream: TextIO | None,
) -> ReanalysisReport:
    """The run, the lock held: skip what is done, reach the cluster (refused before
    anything is recorded when it cannot be), run the rest, record it."""
    doc = _open_record(record_path, plan, given[1], given[0], len(tasks))
    report = ReanalysisReport(Path(plan.dataset), plan.version, plan.settings_hash)
    report.sessions = len(tasks)
    done = finished(plan, tasks)
    report.skipped = len(done)
    report.errors = [(uid, err) for uid, err in sorted(done.items()) if err is not None]
    todo = [t for t in tasks if t.uid not in done]
    with contextlib.ExitStack() as stack:
        client = None
        if todo and scheduler != SYNCHRONOUS:
            client, report.where = stack.enter_context(dask_client(scheduler, workers))
        _record_run(plan, todo, record_path, doc, report, client, stream)
    report.errors.sort()
    return report


def _record_run(
    plan: Plan,
    todo: list[SessionTask],
    record_path: Path,
    doc: dict[str, Any],
    report: ReanalysisReport,
    client: Any,
    stream: TextIO | None,
) -> None:
    """Run ``todo`` (on ``client``, or here without one) and keep ``doc`` (the analysis
    record) up to date: saved before the run and after it, however it ends."""
    tasks = report.sessions
    run: dict[str, Any] = {"started_utc": layout.utc_now_iso(), "skipped": report.skipped}
    doc["status"] = "running"
    doc["runs"].append(run)
    _save_record(record_path, doc)
    bar = Progress(len(todo), stream, f"analysis {plan.version}")

    def on_done(task: SessionTask, row: dict[str, Any] | None, failure: str | None) -> None:
        if row is None:
            report.failed.append((task.uid, failure or "no result"))
        else:
            report.computed += 1
            if row["error"] is not None:
                report.errors.append((task.uid, str(row["error"])))
        bar.advance(error=row is None or row["error"] is not None)

    try:
        if not todo:
            report.where = "nothing to do"
        elif client is None:
            report.where = "serial, in this process"
            run_serial(todo, plan, on_done)
        else:
            run_distributed(todo, plan, client, on_done)
    finally:
        bar.close()
        run |= {
            "finished_utc": layout.utc_now_iso(),
            "where": report.where,
            "analysed": report.computed,
            "failed": len(report.failed),
        }
        errors = len(report.errors)
        doc["counts"] = {
            "sessions": tasks,
            "done": report.skipped + report.computed,
            "errors": errors,
            "failed": len(report.failed),
        }
        complete = doc["counts"]["done"] == tasks
        doc["status"] = "finished" if complete else "incomplete"
        doc["finished_utc"] = run["finished_utc"] if complete else None
        _save_record(record_path, doc)
