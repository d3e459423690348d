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


def connect(dataset: Path) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with the dataset's tables as views.

    Raises
    ------
    StudyError
        ``dataset`` is not a study dataset (one line).
    """
    import duckdb

    load_state(dataset)
    con = duckdb.connect()
    for table in TABLE_NAMES:
        keys = _partition_keys(table)
        directory = dataset / table
        if directory.is_dir() and next(directory.rglob("*.parquet"), None) is not None:
            pattern = _sql_text(str(directory.resolve() / "**" / "*.parquet"))
            types = "{" + ", ".join(f"{_sql_text(k)}: 'VARCHAR'" for k in keys) + "}"
            con.execute(
                f"CREATE VIEW {table} AS SELECT * FROM read_parquet({pattern}, "
                f"hive_partitioning = true, union_by_name = true, hive_types = {types})"
            )
        else:
            schema = arrow_schema(table)
            for key in keys:
                if key not in schema.names:
                    schema = schema.append(pa.field(key, pa.string()))
            con.register(f"_empty_{table}", schema.empty_table())
            con.execute(f"CREATE VIEW {table} AS SELECT * FROM _empty_{table}")
    return con


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def run_query(dataset: Path, sql: str) -> pa.Table:
    """The result of one read-only SQL statement over the dataset.

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
            statements = con.extract_statements(sql)
        except duckdb.Error as exc:
            raise StudyError(f"SQL: {_one_line(exc)}") from None
        if len(statements) != 1:
            raise StudyError(f"SQL: give exactly one statement (got {len(statements)})")
        kind = statements[0].type
        readable = {duckdb.StatementType.SELECT, duckdb.StatementType.EXPLAIN}
        if kind not in readable:
            raise StudyError(
                f"SQL: only queries are run here (SELECT, WITH ... SELECT, EXPLAIN), "
                f"not {kind.name}"
            )
        try:
            relation = con.sql(sql)
            result: pa.Table = relation.to_arrow_table()
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
    """Write a query result as CSV (header, empty for null) or Parquet, per the suffix.

    Raises
    ------
    StudyError
        Unknown suffix, or the file cannot be written.
    """
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    fmt = result_format(path)
    try:
        if fmt == "csv":
            pacsv.write_csv(result, path)
        else:
            pq.write_table(result, path)
    except (OSError, pa.ArrowException) as exc:
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
