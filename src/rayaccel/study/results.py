"""A sweep's results file: JSON lines, one record per finished cell, safe against interruption.

The first line is a header naming the format (:data:`FORMAT`) and the rayaccel
version that started the file. Every later line is one cell's record with its
stable ``key``. Each line is written whole, flushed and ``fsync``-ed before the
next cell starts, so a sweep stopped by Ctrl-C, SIGKILL or a crash loses at most
the cell it was running; a torn last line (the write cut short) is ignored when
the file is read back, and cut off before the next append. A file of another
format is refused, never overwritten.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from rayaccel.bench.report import dumps
from rayaccel.errors import InvalidInputError

#: Format tag of the header line.
FORMAT = "rayaccel-sweep/1"

Record = dict[str, Any]


class ResultsFormatError(InvalidInputError):
    """A results file that this version cannot read or append to."""


def _lines(path: Path) -> Iterator[tuple[int, str, bool]]:
    """Yield ``(offset, line, complete)`` for each line of ``path``."""
    data = path.read_bytes()
    offset = 0
    while offset < len(data):
        end = data.find(b"\n", offset)
        if end < 0:
            yield offset, data[offset:].decode("utf-8", "replace"), False
            return
        yield offset, data[offset:end].decode("utf-8", "replace"), True
        offset = end + 1


def read_results(path: str | os.PathLike[str]) -> tuple[Record, list[Record]]:
    """Read a results file: its header and its cell records.

    A torn last line is ignored. Raises :class:`ResultsFormatError` when the file
    has no header of :data:`FORMAT` or a complete line is not JSON.
    """
    source = Path(path)
    header: Record | None = None
    records: list[Record] = []
    for number, (_, line, complete) in enumerate(_lines(source), start=1):
        try:
            record = json.loads(line)
        except ValueError as exc:
            if not complete:
                break  # a torn last line
            raise ResultsFormatError(f"{source}:{number}: not a JSON line ({exc})") from exc
        if not isinstance(record, dict):
            raise ResultsFormatError(f"{source}:{number}: not a JSON object")
        if header is None:
            if record.get("record") != "header":
                raise ResultsFormatError(f"{source}: no sweep header on line 1")
            if record.get("format") != FORMAT:
                raise ResultsFormatError(
                    f"{source}: written in format {record.get('format')!r} by rayaccel "
                    f"{record.get('rayaccel', '?')}; this version reads {FORMAT!r}. Use "
                    "another results file (this one is left as it is)."
                )
            header = record
        else:
            records.append(record)
    if header is None:
        raise ResultsFormatError(f"{source}: empty (no sweep header)")
    return header, records


class ResultsFile:
    """Append cell records to a results file, each line synced to disk.

    Opening an existing file checks its header (:func:`read_results`) and cuts a
    torn last line; a new file gets a header with ``header`` fields.
    """

    def __init__(self, path: str | os.PathLike[str], header: Record) -> None:
        self.path = Path(path)
        if self.path.exists() and self.path.stat().st_size > 0:
            self.header, self.records = read_results(self.path)
            self._cut_torn_line()
        else:
            self.header = {"record": "header", "format": FORMAT, **header}
            self.records = []
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._append_line(dumps(self.header))

    def _cut_torn_line(self) -> None:
        last = None
        for offset, _, complete in _lines(self.path):
            last = (offset, complete)
        if last is not None and not last[1]:
            with self.path.open("r+b") as handle:
                handle.truncate(last[0])
                handle.flush()
                os.fsync(handle.fileno())

    def _append_line(self, line: str) -> None:
        with self.path.open("ab") as handle:
            handle.write(line.encode() + b"\n")
            handle.flush()
            os.fsync(handle.fileno())

    def append(self, record: Record) -> None:
        """Write ``record`` as one synced line."""
        self._append_line(dumps(record))
        self.records.append(json.loads(dumps(record)))

    def finished_keys(self, max_attempts: int) -> set[str]:
        """Return the keys of cells needing no more work: done, or failed ``max_attempts`` times."""
        done = set()
        for record in self.records:
            gave_up = record.get("status") == "failed" and record.get("attempts", 0) >= max_attempts
            if record.get("status") == "ok" or gave_up:
                done.add(record["key"])
        return done
