"""``stipi-daemon study``: many sessions as one dataset.

``study index ROOT... --out DATASET`` writes (or brings up to date) a Parquet dataset of
every session under the roots (:func:`stipi_daemon.study.index.index_sessions`); ``study
query DATASET "SQL"`` runs one SQL query over it with DuckDB and prints the result or
writes it to CSV/Parquet (:mod:`stipi_daemon.study.query`); ``study reanalyze DATASET
--settings S.yaml`` analyses every session again as Dask tasks into a new analysis version
(:func:`stipi_daemon.study.reanalyze.reanalyze`); ``study diff DATASET V1 V2`` compares two
versions (:func:`stipi_daemon.study.diff.diff_versions`). Each sub-subcommand is one
``_add_*`` function in :data:`_SUBCOMMANDS`; the layout and schema are in docs/study.md.
The study modules are imported when a subcommand runs, not when the parser is built.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeAlias

from stipi_daemon.commands import given_path, out_path

_Sub: TypeAlias = "argparse._SubParsersAction[argparse.ArgumentParser]"


def register(subparsers: _Sub) -> None:
    parser = subparsers.add_parser(
        "study",
        help="many sessions as one dataset: index, query with SQL, re-analyse, compare",
        description="A study: the sessions of many probes and sites as one Parquet dataset "
        "(hive-partitioned by site, probe and date; docs/study.md), queried with SQL.",
    )

    def show_help(_args: argparse.Namespace) -> int:
        parser.print_help()
        return 0

    parser.set_defaults(handler=show_help)
    sub = parser.add_subparsers(title="subcommands", metavar="SUBCOMMAND")
    for add in _SUBCOMMANDS:
        add(sub)


def _add_index(sub: _Sub) -> None:
    p = sub.add_parser(
        "index",
        help="write or update a study dataset from sessions directories",
        description="Index every session under each ROOT into DATASET: tables sessions, "
        "force_samples, frames and results (analysis 'recorded': each session's own "
        "summary, with its data hash, settings hash and package version). Indexing again "
        "adds new and changed sessions only and removes nothing it did not write. "
        "Unreadable sessions are reported (one line each) and skipped; sessions still "
        "being recorded are skipped with a note.",
    )
    p.add_argument("roots", nargs="+", type=Path, metavar="ROOT", help="sessions directory")
    p.add_argument(
        "--out", type=str, required=True, metavar="DATASET", help="the dataset directory"
    )
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    p.set_defaults(handler=_cmd_index)


def _add_query(sub: _Sub) -> None:
    p = sub.add_parser(
        "query",
        help="run one SQL query over a study dataset (DuckDB)",
        description="Run one SQL query with DuckDB. The tables sessions, force_samples, "
        "frames and results are views over the dataset's Parquet files; the partition "
        "keys site, probe, date (and analysis for results) are text columns. Example: "
        "SELECT site, severity_grade, avg(viscosity_n_s_per_mm2) FROM results WHERE "
        "analysis = 'recorded' GROUP BY ALL",
    )
    p.add_argument("dataset", type=Path, metavar="DATASET", help="the dataset directory")
    p.add_argument("sql", metavar="SQL", help="one query (SELECT, WITH ... SELECT, EXPLAIN)")
    p.add_argument(
        "--out",
        type=str,
        metavar="FILE",
        help="write the whole result to FILE.csv or FILE.parquet instead of printing it "
        "(never into the dataset)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument(
        "--max-rows", type=int, default=200, metavar="N", help="rows printed (default 200)"
    )
    p.set_defaults(handler=_cmd_query)


def _add_reanalyze(sub: _Sub) -> None:
    p = sub.add_parser(
        "reanalyze",
        help="analyse every session of a study again, as Dask tasks",
        description="Analyse every session of DATASET again with the settings of S.yaml "
        "(configs/study-settings.example.yaml) and write them as a new analysis version "
        "(results/analysis=V). Each session is a Dask distributed task: on an embedded "
        "LocalCluster (one worker process per CPU) or on the cluster at --scheduler. "
        "Sessions already done for V (same data and settings hashes) are not analysed "
        "again, so an interrupted run is finished by running it again. A session's "
        "error is its row's error, not the run's. Exit 1 when a task failed outside "
        "the analysis (run again to retry it).",
    )
    p.add_argument("dataset", type=Path, metavar="DATASET", help="the dataset directory")
    p.add_argument(
        "--settings", type=Path, required=True, metavar="S.yaml", help="the settings file"
    )
    p.add_argument(
        "--recompute-sk", action="store_true", help="count S_k again from each session's video"
    )
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--scheduler", metavar="tcp://HOST:8786", help="a running Dask scheduler's address"
    )
    where.add_argument(
        "--serial", action="store_true", help="no cluster: one session after the other, here"
    )
    p.add_argument(
        "--workers", type=int, metavar="N", help="embedded cluster's workers (default: CPUs)"
    )
    p.add_argument("--name", metavar="V", help="analysis version (default s-<settings hash>)")
    p.add_argument("--quiet", action="store_true", help="no progress, only the summary")
    p.set_defaults(handler=_cmd_reanalyze)


def _add_diff(sub: _Sub) -> None:
    p = sub.add_parser(
        "diff",
        help="what changed between two analysis versions of a study",
        description="Compare analysis versions V1 and V2 (e.g. recorded and a "
        "re-analysis): the sessions whose verdict or severity class changed, and per "
        "quantity the distribution of the changes V2 - V1 (n, median, 5th and 95th "
        "percentiles, largest absolute change, in the quantity's unit).",
    )
    p.add_argument("dataset", type=Path, metavar="DATASET", help="the dataset directory")
    p.add_argument("v1", metavar="V1", help="the analysis version compared against")
    p.add_argument("v2", metavar="V2", help="the analysis version compared")
    p.add_argument(
        "--out", type=str, metavar="FILE.csv", help="also write one row per session to CSV"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument(
        "--max-rows", type=int, default=50, metavar="N", help="changed sessions listed (50)"
    )
    p.set_defaults(handler=_cmd_diff)


#: The ``study`` sub-subcommands, in the order ``--help`` shows them.
_SUBCOMMANDS: tuple[Callable[[_Sub], None], ...] = (
    _add_index,
    _add_query,
    _add_reanalyze,
    _add_diff,
)


def _cmd_index(args: argparse.Namespace) -> int:
    from stipi_daemon.study.index import index_sessions

    report = index_sessions(args.roots, given_path(args.out))
    if not args.quiet:
        for line in report.skipped:
            print(f"stipi-daemon: skipped {line}", file=sys.stderr)
        for line in report.notes:
            print(f"stipi-daemon: note: {line}", file=sys.stderr)
    print(report.line())
    return 0


def _cmd_query(args: argparse.Namespace) -> int:
    from stipi_daemon.study.dataset import check_output_file
    from stipi_daemon.study.query import format_result, result_format, run_query, write_result

    out = out_path(args.out)
    if out is not None:  # refused before the query runs
        result_format(out)
        check_output_file(out, args.dataset, overwrite=args.overwrite, what="a query")
    result = run_query(args.dataset, args.sql)
    if out is not None:
        write_result(result, out)
        print(f"{out}: {result.num_rows} rows")
    else:
        print(format_result(result, max(0, args.max_rows)))
    return 0


def _cmd_reanalyze(args: argparse.Namespace) -> int:
    from stipi_daemon.study.reanalyze import SYNCHRONOUS, reanalyze

    report = reanalyze(
        args.dataset,
        args.settings,
        recompute_sk=args.recompute_sk,
        scheduler=SYNCHRONOUS if args.serial else args.scheduler,
        workers=args.workers,
        name=args.name,
        progress=None if args.quiet else sys.stderr,
    )
    *problems, line = report.lines()
    for problem in problems:
        print(f"stipi-daemon: {problem}", file=sys.stderr)
    print(line)
    return report.exit_code


def _cmd_diff(args: argparse.Namespace) -> int:
    from stipi_daemon.study.dataset import check_output_file
    from stipi_daemon.study.diff import diff_versions

    out = out_path(args.out)
    if out is not None:
        check_output_file(out, args.dataset, overwrite=args.overwrite, what="a diff")
    diff = diff_versions(args.dataset, args.v1, args.v2)
    if out is not None:
        diff.write_csv(out)
    print("\n".join(diff.lines(max(0, args.max_rows))))
    if out is not None:
        print(f"{out}: {len(diff.sessions)} rows")
    return 0
