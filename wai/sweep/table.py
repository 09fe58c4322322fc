"""A sweep's table: one CSV file, locked while a sweep writes it, appended a row at a time,
read back with its cells parsed, and copied to Parquet."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import importlib.util
import io
import os
import re
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import IO, Any

from wai.sweep.points import BOOKKEEPING, Row, plain
from wai_core.errors import WaiInputError
from wai_core.io import atomic_write_bytes

# What the table's text cells parse back into (repr() of Python floats, ints and bools).
_INT = re.compile(r"[+-]?\d+")
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|[+-]?(inf|nan)")
_EXTRA = "\0extra"  # DictReader's key for cells beyond the header
_TEXT_COLUMNS = frozenset({"point_id", "status", "worker"})  # never parsed as numbers


class SweepTable:
    """One CSV table of rows, appended a line at a time and rewritten atomically when it widens.

    Use it as a context manager: it holds an exclusive lock on the table (one sweep at a time
    writes it) and on entry drops a truncated last line that a killed run may have left.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.columns: list[str] = []
        self._out: IO[str] | None = None
        self._writer: csv.DictWriter | None = None
        self._lock: IO[str] | None = None

    def __enter__(self) -> SweepTable:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = _lock(self.path)
        try:
            self._drop_truncated_line()
            self.columns = self._header()
        except BaseException:
            self.__exit__()  # a table that is not a sweep's: no lock file left behind
            raise
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._close()
        if self._lock is not None:
            # Removed while still held (a sweep waiting for it opens a new one): nothing of the
            # lock survives the sweep.
            with contextlib.suppress(OSError):
                os.unlink(self._lock.name)
            self._lock.close()  # closing releases the flock
            self._lock = None

    def rows(self) -> list[dict[str, str]]:
        """All rows as text cells (a column a row lacks is ``""``)."""
        if not self.path.exists():
            return []
        with self.path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f, restkey=_EXTRA, restval=""))
        for line, row in enumerate(rows, start=2):
            if _EXTRA in row:
                raise WaiInputError(f"{self.path}:{line} has more cells than the header")
        return rows

    def append(self, row: Mapping[str, Any]) -> None:
        """Write one row and flush it; new columns first widen the whole table."""
        new = [name for name in row if name not in self.columns]
        if new:
            self._rewrite(_widened(self.columns, new), self.rows())
        if self._writer is None:
            self._open()
        assert self._writer is not None and self._out is not None
        self._writer.writerow({name: _cell(value) for name, value in row.items()})
        self._out.flush()  # a killed sweep keeps every finished row

    def drop(self, ids: set[str]) -> None:
        """Remove the rows of the points ``ids`` (to run them again)."""
        rows = self.rows()
        kept = [row for row in rows if row["point_id"] not in ids]
        if len(kept) < len(rows):
            self._rewrite(self.columns, kept)

    def _header(self) -> list[str]:
        if not self.path.exists() or self.path.stat().st_size == 0:
            return []
        with self.path.open(newline="", encoding="utf-8") as f:
            header = next(csv.reader(f), [])
        if "point_id" not in header or "status" not in header:
            raise WaiInputError(f"{self.path} is not a sweep table (no point_id/status column)")
        return header

    def _drop_truncated_line(self) -> None:
        """Cut a last line without its newline: a row that a killed run was writing."""
        if not self.path.exists():
            return
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            atomic_write_bytes(self.path, data[: data.rfind(b"\n") + 1])
            print(f"{self.path}: dropped a truncated last line", file=sys.stderr)

    def _rewrite(self, columns: list[str], rows: list[dict[str, str]]) -> None:
        self._close()
        buf = io.StringIO()
        writer = csv.DictWriter(buf, columns, restval="", lineterminator="\n")
        writer.writeheader()
        writer.writerows({name: row.get(name, "") for name in columns} for row in rows)
        atomic_write_bytes(self.path, buf.getvalue().encode())
        self.columns = columns

    def _open(self) -> None:
        self._out = self.path.open("a", newline="", encoding="utf-8")
        self._writer = csv.DictWriter(self._out, self.columns, restval="", lineterminator="\n")

    def _close(self) -> None:
        if self._out is not None:
            self._out.close()
        self._out = self._writer = None


def _lock(path: Path) -> IO[str]:
    """Hold an exclusive lock beside ``path``: two sweeps writing one table would lose rows.

    The holder removes the lock file when it is done (:meth:`SweepTable.__exit__`), so a lock
    taken on a file that is no longer at its path (removed meanwhile) is taken again afresh.
    """
    name = path.with_name(f".{path.name}.lock")
    while True:
        lock = name.open("w")
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            raise WaiInputError(f"another sweep is writing {path}") from None
        try:
            if os.stat(name).st_ino == os.fstat(lock.fileno()).st_ino:
                return lock
        except FileNotFoundError:
            pass
        lock.close()  # its holder removed it as we opened it: another round


def _widened(columns: list[str], new: list[str]) -> list[str]:
    """``columns`` plus ``new``, keeping the bookkeeping columns last."""
    body = [name for name in [*columns, *new] if name not in BOOKKEEPING]
    return body + list(BOOKKEEPING)


def _cell(value: Any) -> str:
    """Text of one cell, on one line (a row is a line, which makes truncation easy to spot)."""
    value = plain(value)
    return "" if value is None else " ".join(str(value).splitlines())


def parse_cell(text: str) -> Any:
    """A table cell back as a Python value: ``""`` is None; bools, ints and floats as such."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    if _INT.fullmatch(text):
        return int(text)
    if _FLOAT.fullmatch(text):
        return float(text)
    return text


def typed_row(row: Mapping[str, str]) -> Row:
    """A row of text cells parsed (:func:`parse_cell`), but for the text columns'."""
    return {k: v if k in _TEXT_COLUMNS else parse_cell(v) for k, v in row.items()}


def read_table(path: str | Path) -> list[Row]:
    """Read a sweep table with its cells parsed (see :func:`parse_cell`).

    Parameters
    ----------
    path
        The CSV table that :func:`run_sweep` wrote.

    Returns
    -------
    list of dict
        One dict per row, every column present (None where a row has no value).
    """
    path = Path(path)
    if not path.is_file():
        raise WaiInputError(f"table not found: {path}")
    with path.open(newline="", encoding="utf-8") as f:
        return [typed_row(row) for row in csv.DictReader(f, restval="")]



def write_parquet(rows: Sequence[Mapping[str, Any]], path: str | Path) -> bool:
    """Write rows as a Parquet file atomically, if pyarrow is installed.

    A column whose values pyarrow cannot put in one type (say ints and strings) is stored as
    strings. Returns whether the file was written.
    """
    if importlib.util.find_spec("pyarrow") is None:
        return False
    import pyarrow as pa
    import pyarrow.parquet as pq

    names = list(dict.fromkeys(name for row in rows for name in row))
    columns = {}
    for name in names:
        values = [row.get(name) for row in rows]
        try:
            columns[name] = pa.array(values)
        except (pa.ArrowInvalid, pa.ArrowTypeError):
            columns[name] = pa.array([None if v is None else str(v) for v in values])
    sink = pa.BufferOutputStream()
    pq.write_table(pa.table(columns), sink)
    atomic_write_bytes(path, sink.getvalue().to_pybytes())
    return True
