"""Benchmark output: JSONL records written atomically, and tables for terminals and docs.

:class:`JsonlWriter` keeps every record of a results file in memory and, for each
new record, rewrites the **whole** file into a temporary file in the same folder,
``fsync``-s it and moves it over the old one with :func:`os.replace`. The file on
disk is therefore always a complete set of whole records: an interrupted run (a
Ctrl-C, a crash) loses only the measurement in progress, and readers never see a
half-written line. Records already in the file when the writer opens it are kept
(runs accumulate; each record carries its ``run_id``).

:func:`markdown_table` and :func:`rich_table` show one row per scene × system ×
ray set: build time, Mrays/s (median and best of the timed passes), the ratio to
Open3D's Embree on the same rays, mean nodes (cells for grids) and primitives per ray, and the
stats overhead.
"""

from __future__ import annotations

import datetime
import json
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

from rayaccel._atomic import write_bytes_atomic
from rayaccel.errors import InvalidInputError
from rayaccel.rays.io import json_default

Record = dict[str, Any]

#: Columns of the benchmark table.
COLUMNS: tuple[str, ...] = (
    "scene",
    "tris",
    "system",
    "threads",
    "rays",
    "n rays",
    "build ms",
    "Mrays/s",
    "best",
    "× open3d",
    "nodes/ray (grids: cells)",
    "prims/ray",
    "stats +%",
)
#: Columns right-aligned in tables (numbers).
NUMERIC = frozenset(COLUMNS) - {"scene", "system", "rays"}


def utc_stamp() -> str:
    """Return the current UTC time as ``YYYYMMDDTHHMMSSZ``, the stamp in result file names."""
    return datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%dT%H%M%SZ")


def dumps(record: Record) -> str:
    """Return one record as a single JSON line (non-finite floats become null)."""
    clean = {key: _finite(value) for key, value in record.items()}
    return json.dumps(clean, default=json_default, sort_keys=False, allow_nan=False)


def _finite(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def read_jsonl(path: str | os.PathLike[str]) -> list[Record]:
    """Read every record of a JSONL results file.

    Raises
    ------
    InvalidInputError
        A line is not a JSON object (the line number is named).
    """
    records = []
    with open(path, encoding="utf-8") as handle:
        for number, line in enumerate(handle, 1):
            if not line.strip():
                continue
            try:
                value = json.loads(line)
            except json.JSONDecodeError as exc:
                raise InvalidInputError(f"{path}:{number}: not JSON ({exc})") from exc
            if not isinstance(value, dict):
                raise InvalidInputError(f"{path}:{number}: expected a JSON object")
            records.append(value)
    return records


class JsonlWriter:
    """Append records to a JSONL file, rewriting it atomically after every record.

    Parameters
    ----------
    path : str or path-like
        The results file; its folder is created if missing. Existing records are kept.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lines: list[str] = []
        if self.path.exists():
            self._lines = [dumps(record) for record in read_jsonl(self.path)]

    def __len__(self) -> int:
        return len(self._lines)

    def append(self, record: Record) -> None:
        """Add ``record`` and rewrite the file through a temporary file and ``os.replace``."""
        self._lines.append(dumps(record))
        text = "".join(line + "\n" for line in self._lines)
        write_bytes_atomic(self.path, text.encode("utf-8"))


def _fmt(value: Any, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "–"
        if abs(value) >= 1000:
            return f"{value:,.0f}"
        return f"{value:.{digits}g}"
    if isinstance(value, int):
        return f"{value:,}"
    return str(value)


def table_rows(records: Iterable[Record]) -> list[list[str]]:
    """Return the :data:`COLUMNS` cells of every ``trace``/``invalid`` record.

    Repeated scene, triangle count and system cells are blanked for readability.
    """
    rows: list[list[str]] = []
    previous: tuple[Any, ...] = ()
    for r in records:
        if r.get("record") not in ("trace", "invalid"):
            continue
        key = (r.get("scene"), r.get("system"), r.get("threads"))
        same_scene = bool(previous) and previous[0] == key[0]
        same_system = bool(previous) and previous == key
        previous = key
        if r["record"] == "invalid":
            validation = r.get("validation") or {}
            speed = f"INVALID {validation.get('mismatches')}/{validation.get('checked')}"
            best = ratio = "–"
        else:
            speed = _fmt(r.get("mrays_median"))
            best = _fmt(r.get("mrays_best"))
            ratio = _fmt(r.get("ratio_vs_open3d"), 2)
        overhead = r.get("stats_overhead")
        system = str(r.get("system"))
        if r.get("note"):
            system += f" ({r['note']})"
        rows.append([
            "" if same_scene else str(r.get("scene")),
            "" if same_scene else _fmt(r.get("n_tris")),
            "" if same_system else system,
            _fmt(r.get("threads")),
            str(r.get("ray_type")),
            _fmt(r.get("n_rays")),
            "" if same_system else _fmt(r.get("build_ms")),
            speed,
            best,
            ratio,
            _fmt(r.get("nodes_per_ray") or (r.get("counters_mean") or {}).get("cells")),
            _fmt(r.get("prims_per_ray")),
            "–" if overhead is None else f"{100.0 * overhead:+.1f}",
        ])  # fmt: skip
    return rows


def markdown_table(records: Iterable[Record]) -> str:
    """Return the benchmark table as GitHub markdown (as in ``docs/performance.md``)."""
    rows = table_rows(records)
    align = ["---:" if c in NUMERIC else ":---" for c in COLUMNS]
    lines = ["| " + " | ".join(COLUMNS) + " |", "| " + " | ".join(align) + " |"]
    lines += ["| " + " | ".join(cell.replace("|", "\\|") for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def text_table(records: Iterable[Record]) -> str:
    """Return the benchmark table as aligned plain text (readable at any terminal width)."""
    rows = [list(COLUMNS), *table_rows(records)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(COLUMNS))]

    def line(row: Sequence[str]) -> str:
        cells = [
            cell.rjust(width) if column in NUMERIC else cell.ljust(width)
            for cell, width, column in zip(row, widths, COLUMNS, strict=True)
        ]
        return "  ".join(cells).rstrip()

    rule = "  ".join("-" * width for width in widths)
    return "\n".join([line(rows[0]), rule, *(line(row) for row in rows[1:])])


def rich_table(records: Iterable[Record], title: str | None = None) -> Any:
    """Return the benchmark table as a :class:`rich.table.Table`."""
    from rich.table import Table

    table = Table(title=title, header_style="bold", show_lines=False)
    for column in COLUMNS:
        table.add_column(column, justify="right" if column in NUMERIC else "left")
    for row in table_rows(records):
        style = "red" if row[7].startswith("INVALID") else None
        table.add_row(*row, style=style)
    return table


def compile_summary(records: Sequence[Record]) -> str | None:
    """Summarise the ``compile`` records: how many variants compiled or loaded, and how long."""
    compiled = [r for r in records if r.get("record") == "compile"]
    if not compiled:
        return None
    jit = [r for r in compiled if r.get("compile_kind") == "jit"]
    cached = [r for r in compiled if r.get("compile_kind") != "jit"]
    parts = []
    if jit:
        parts.append(f"{len(jit)} compiled in {sum(r['compile_ms'] for r in jit) / 1e3:.1f} s")
    if cached:
        total = sum(r["compile_ms"] for r in cached) / 1e3
        parts.append(f"{len(cached)} loaded from cache in {total:.2f} s")
    return f"kernels: {len(compiled)} variants, " + ", ".join(parts)


def environment_line(records: Sequence[Record]) -> str | None:
    """Return one line naming the machine and versions of the first record."""
    if not records:
        return None
    r = records[-1]
    sha = r.get("git_sha") or "unknown"
    return (
        f"{r.get('cpu_model')} ({r.get('cpu_count')} CPUs), numba {r.get('numba_version')} "
        f"({r.get('threading_layer')}), numpy {r.get('numpy_version')}, "
        f"Python {r.get('python_version')}, rayaccel {r.get('rayaccel_version')} @ {sha[:12]}"
    )
