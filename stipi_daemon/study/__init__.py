"""Studies: many sessions of many probes and sites as one dataset, queried and re-analysed.

:mod:`.index` turns sessions directories into a Parquet dataset (:mod:`.dataset`: layout,
schemas with units, atomic files, :class:`~.dataset.StudyError`), incrementally, with the
provenance of every result (:mod:`.hashing`: the session's data hash, the analysis
settings' hash, the package version); :mod:`.query` runs SQL over it with DuckDB. The
layout and schema are in ``docs/study.md``. This package is application code: it reads
sessions through :mod:`stipi_daemon.storage` and never imports the simulator. Nothing is
imported here, so that ``stipi-daemon --help`` does not load pyarrow or DuckDB.
"""
