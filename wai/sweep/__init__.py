"""Run a sweep of independent points on Dask and stream its rows into one CSV table.

A sweep is a list of points (dicts of parameters) and a top-level function ``fn(point) -> dict``
that returns one row of results. :func:`run_sweep` evaluates the points that the table does not
hold yet, on a local cluster of worker processes, on an existing Dask cluster, or in the calling
process, and appends each row to the table as soon as it is finished, so a killed sweep keeps
its rows and a rerun carries on where it stopped.

Next to ``table`` (``NAME.csv``) it writes ``NAME.parquet``, a copy of the table, and
``NAME.json``, a record of each run (where it ran, when, how many points ran, were skipped or
failed, how many workers died under them). A point whose worker process died runs once more;
a run stopped before its first row leaves the record as it was. ``docs/cluster.md`` describes
how to use it.
"""

from wai.sweep.backend import Runner
from wai.sweep.options import SweepOptions, add_sweep_arguments
from wai.sweep.points import (
    BOOKKEEPING,
    IN_PROCESS,
    MAX_MESSAGE,
    OK,
    WORKER_DIED,
    WORKER_LOSSES,
    WORKER_RETRIES,
    Outcome,
    Point,
    Row,
    error_status,
    is_error,
    point_id,
)
from wai.sweep.run import run_sweep
from wai.sweep.table import SweepTable, parse_cell, read_table, write_parquet

__all__ = [
    "BOOKKEEPING",
    "IN_PROCESS",
    "MAX_MESSAGE",
    "OK",
    "WORKER_DIED",
    "WORKER_LOSSES",
    "WORKER_RETRIES",
    "Outcome",
    "Point",
    "Row",
    "Runner",
    "SweepOptions",
    "SweepTable",
    "add_sweep_arguments",
    "error_status",
    "is_error",
    "parse_cell",
    "point_id",
    "read_table",
    "run_sweep",
    "write_parquet",
]
