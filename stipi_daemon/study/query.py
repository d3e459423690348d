"""``study query``: SQL over a study dataset with DuckDB.

:func:`connect` opens an in-memory DuckDB database in which each table of the dataset
(:data:`~.dataset.TABLE_NAMES`) is a view over its Parquet files, read with hive
partitioning (the partition keys ``site``, ``probe``, ``date`` and, for ``results``,
``analysis`` become text columns, percent-decoded) and ``union_by_name`` (files written by
different versions may differ in columns; missing ones read as null). A table with no file
yet is an empty view of its schema. :func:`run_query` runs one read-only statement
(``SELECT``, ``WITH ... SELECT``, ``EXPLAIN``...) and returns its result as an Arrow table;
:func:`write_result` writes one to CSV or Parquet and :func:`format_result` as text.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Final

import pyarrow as pa

from stipi_daemon.study.dataset import (
    PARTITION_KEYS,
    TABLE_NAMES,
    StudyError,
    arrow_schema,
    load_state,
)

if TYPE_CHECKING:
    import duckdb

#: Rows :func:`format_result` shows by default.
SHOWN_ROWS: Final = 200


def _partition_keys(table: str) -> tuple[str, ...]:
    return ("analysis", *PARTITION_KEYS) if table == "results" else PARTITION_KEYS


def _sql_text(value: str) -> str:
    return "'" + value.replace("'", "''") + "'"


def _parquet_files(dataset: Path, table: str) -> list[Path]:
    """The table's Parquet files (absolute: under the resolved table directory), hidden
    temporary files left out."""
    directory = dataset / table
    if not directory.is_dir():
        return []
    base = directory.resolve()
    return sorted(p for p in base.rglob("*.parquet") if not p.name.startswith("."))


def _create_view(con: duckdb.DuckDBPyConnection, table: str, files: list[Path]) -> None:
    """``table`` as a view over ``files`` (hive partitions as text), or an empty view of
    its schema when there is no file."""
    keys = _partition_keys(table)
    if files:
        listed = "[" + ", ".join(_sql_text(str(f)) for f in files) + "]"
        types = "{" + ", ".join(f"{_sql_text(k)}: 'VARCHAR'" for k in keys) + "}"
        con.execute(
            f"CREATE VIEW {table} AS SELECT * FROM read_parquet({listed}, "
            f"hive_partitioning = true, union_by_name = true, hive_types = {types})"
        )
        return
    schema = arrow_schema(table)
    for key in keys:
        if key not in schema.names:
            schema = schema.append(pa.field(key, pa.string()))
    con.register(f"_empty_{table}", schema.empty_table())
    con.execute(f"CREATE VIEW {table} AS SELECT * FROM _empty_{table}")


def _sandbox(con: duckdb.DuckDBPyConnection, files: list[Path]) -> None:
    """Allow the connection to read ``files`` and nothing else, and lock that in.

    External access off (no other local file, no network, no extension installed or
    loaded), the dataset's files the only allowed paths (read; writing one is refused as
    DuckDB writes through a temporary name beside it), no spilling to a temporary
    directory, and the configuration locked so that no statement can change it back.
    """
    listed = "[" + ", ".join(_sql_text(str(f)) for f in files) + "]"
    con.execute(f"SET allowed_paths = {listed}")
    con.execute("SET temp_directory = ''")
    con.execute("SET enable_external_access = false")
    con.execute("SET lock_configuration = true")


def connect(dataset: Path) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with the dataset's tables as views, that reads
    the dataset's Parquet files and no other file, and writes none (:func:`_sandbox`).

    Raises
    ------
    StudyError
        ``dataset`` is not a study dataset, or one of its Parquet files is unreadable
        (truncated, corrupt: one line, as DuckDB names it, and how to repair it).
    """
    import duckdb

    load_state(dataset)
    con = duckdb.connect(
        config={"autoinstall_known_extensions": False, "autoload_known_extensions": False}
    )
    allowed: list[Path] = []
    try:
        for table in TABLE_NAMES:
            files = _parquet_files(dataset, table)
            _create_view(con, table, files)
            allowed.extend(files)
        _sandbox(con, allowed)
    except duckdb.Error as exc:
        con.close()
        raise StudyError(
            f"{dataset}: a dataset file is unreadable: {_one_line(exc)} (run `stipi-daemon "
            "study index` again to write it anew)"
        ) from None
    return con


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _explained(sql: str) -> str | None:
    """The statement an ``EXPLAIN [ANALYZE] [(options)] ...`` statement explains, found
    with DuckDB's own tokenizer (comments skipped); None when there is none."""
    import duckdb

    starts = [p for p, kind in duckdb.tokenize(sql) if kind != duckdb.token_type.comment]
    words = [
        (sql[p:end].split() or [""])[0].upper()
        for p, end in zip(starts, [*starts[1:], len(sql)], strict=True)
    ]
    depth = 0
    for p, word in list(zip(starts, words, strict=True))[1:]:  # [0] is EXPLAIN
        if depth == 0 and word not in ("ANALYZE", "ANALYSE", "("):
            return sql[p:]
        depth += word.count("(") - word.count(")")
    return None


def _check_read_only(con: duckdb.DuckDBPyConnection, sql: str) -> None:
    """Refuse anything but one query: a ``SELECT`` (``WITH ... SELECT``), or an
    ``EXPLAIN [ANALYZE]`` of one, as DuckDB's parser classifies the statement.

    Raises
    ------
    StudyError
        Not exactly one statement, or one that is not a query (one line, naming its type).
    """
    import duckdb

    statements = con.extract_statements(sql)
    if len(statements) != 1:
        raise StudyError(f"SQL: give exactly one statement (got {len(statements)})")
    kind = statements[0].type
    if kind == duckdb.StatementType.EXPLAIN:
        inner = _explained(statements[0].query)
        inner_statements = con.extract_statements(inner) if inner else []
        if len(inner_statements) == 1 and inner_statements[0].type == duckdb.StatementType.SELECT:
            return
        kind = inner_statements[0].type if len(inner_statements) == 1 else kind
        raise StudyError(
            f"SQL: EXPLAIN is run here of a query only (SELECT, WITH ... SELECT), not of "
            f"{kind.name}; a study query changes nothing"
        )
    if kind != duckdb.StatementType.SELECT:
        raise StudyError(
            f"SQL: only queries are run here (SELECT, WITH ... SELECT, EXPLAIN), "
            f"not {kind.name}; a study query changes nothing"
        )


def run_query(dataset: Path, sql: str) -> pa.Table:
    """The result of one read-only SQL statement over the dataset.

    The statement is classified by DuckDB's parser (:func:`_check_read_only`) and run on
    a connection that can read the dataset's Parquet files and nothing else and can
    write no file (:func:`connect`): a statement that would write or read elsewhere is
    refused in one line.

    Raises
    ------
    StudyError
        Not a study dataset; not exactly one statement; a statement that changes
        something; or DuckDB refuses the SQL (its first line, which names the problem).
    """
    import duckdb

    con = connect(dataset)
    try:
        try:
            _check_read_only(con, sql)
            relation = con.sql(sql)
            result: pa.Table = relation.to_arrow_table()
        except duckdb.PermissionException as exc:
            raise StudyError(
                f"SQL: {_one_line(exc)} (a study query reads the dataset's own files only)"
            ) from None
        except duckdb.Error as exc:
            raise StudyError(f"SQL: {_one_line(exc)}") from None
        return result
    finally:
        con.close()


def result_format(path: Path) -> str:
    """``csv`` or ``parquet`` from an output file's name.

    Raises
    ------
    StudyError
        Any other suffix.
    """
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix in (".parquet", ".pq"):
        return "parquet"
    raise StudyError(f"--out {path}: give a file name ending in .csv or .parquet")


def write_result(result: pa.Table, path: Path) -> None:
    """Write a query result as CSV (header, empty for null) or Parquet, per the suffix,
    atomically: a hidden temporary file beside it, renamed over it when whole (removed
    when the write fails: a full disk leaves no partial result).

    Raises
    ------
    StudyError
        Unknown suffix, or the file cannot be written.
    """
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    fmt = result_format(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        if fmt == "csv":
            pacsv.write_csv(result, tmp)
        else:
            pq.write_table(result, tmp)
        os.replace(tmp, path)
    except (OSError, pa.ArrowException) as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise StudyError(f"{path}: cannot write the result: {exc}") from None


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def format_result(result: pa.Table, max_rows: int = SHOWN_ROWS) -> str:
    """A query result as a text table (two spaces between columns; null is ``-``); at
    most ``max_rows`` rows, then one line saying how many more there are."""
    from stipi_daemon.app.sessions_view import format_table

    head = result.slice(0, max_rows)
    columns = [column.to_pylist() for column in head.columns]
    rows = [[_cell(v) for v in row] for row in zip(*columns, strict=True)]
    text = format_table(result.column_names, rows)
    more = result.num_rows - head.num_rows
    if more > 0:
        text += f"\n... {more} more rows (write them all with --out FILE.csv|FILE.parquet)"
    elif result.num_rows == 0:
        text += "\n(no rows)"
    return text
