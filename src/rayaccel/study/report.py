"""The study's report: one self-contained HTML page of a sweep's results, with its charts.

:func:`write_report` reads a results file (:mod:`rayaccel.study.results`; when a
cell's key appears more than once, its last record wins) and writes
``index.html`` and its PNG files into a folder. The page follows the MSc thesis's
chapter 5, Tables 5.1–5.4 and Figures 5.1–5.6:

- throughput: Mrays/s by scene × system, one table per ray set and thread count,
  the peers as rows of their own (the median of their Mrays/s over the scene's
  cells) and the arithmetic mean across scenes as the last column, as the
  thesis averaged; bar charts per family of structures and ray set;
- build: median build time and structure size by scene × builder (Table 5.4);
- traversal cost: nodes, primitive tests and bytes fetched per ray (the memory
  traffic), with the validation against the oracle, mismatches in red; a chart
  of bytes per ray per system;
- optionally a heatmap gallery (:func:`rayaccel.study.report_figures.heatmap_gallery`);
- the failed cells, the machine, the versions and the sweep configuration.

The page is rendered by Jinja2 with autoescaping (every name and error message
in the results is text, never markup), keeps its CSS inline, needs no
JavaScript and loads nothing over the network; sections without data are left
out. Every file is written atomically, so a reader never sees half a report.
"""

from __future__ import annotations

import json
import os
import statistics
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from rayaccel._atomic import write_bytes_atomic
from rayaccel.errors import BackendUnavailableError
from rayaccel.study.config import GENERATED_KINDS, PATH_SETS
from rayaccel.study.report_figures import (
    HeatmapScene,
    Picture,
    Series,
    bar_chart,
    heatmap_gallery,
    safe_name,
)
from rayaccel.study.results import Record, read_results

#: Ray sets in the order the report lists them; others follow, sorted.
RAYSET_ORDER = (*GENERATED_KINDS, *PATH_SETS)

#: Shown for a value the results do not hold.
MISSING = "—"


@dataclass(frozen=True, slots=True)
class TableCell:
    """One ``<td>``: its text and CSS classes (``num``, ``bad``, ``best``, ``peer``)."""

    text: str
    css: str = ""
    title: str = ""


@dataclass(slots=True)
class Table:
    """One ``<table>`` with its caption; a trailing note explains marks in the cells."""

    caption: str
    header: list[str]
    rows: list[list[TableCell]]
    note: str = ""


@dataclass(slots=True)
class Study:
    """A results file, one record per cell key, and the axes of its tables."""

    name: str
    header: Record
    records: list[Record]
    scenes: list[str] = field(default_factory=list)
    raysets: list[str] = field(default_factory=list)
    threads: list[int] = field(default_factory=list)  # of the build and timing cells

    def ok(self, kind: str) -> list[Record]:
        """Return the finished (``status`` "ok") records of ``kind``."""
        return [r for r in self.records if r.get("kind") == kind and r.get("status") == "ok"]

    def of(self, kind: str) -> list[Record]:
        """Return every record of ``kind``, failed ones included."""
        return [r for r in self.records if r.get("kind") == kind]


def _ordered(values: Iterable[Any], first: Iterable[Any] = ()) -> list[Any]:
    """Return the distinct non-None values, those of ``first`` first, then by appearance."""
    seen = [v for v in first if v is not None]
    out = list(dict.fromkeys(seen))
    return out + [v for v in dict.fromkeys(values) if v is not None and v not in out]


def load_study(results_path: str | os.PathLike[str]) -> Study:
    """Read a results file and keep the last record of every cell key."""
    path = Path(results_path)
    header, records = read_results(path)
    latest: dict[str, Record] = {}
    for number, record in enumerate(records):
        latest[str(record.get("key", f"#{number}"))] = record
    kept = list(latest.values())
    config = header.get("config") or {}
    present = {r.get("rayset") for r in kept}
    raysets = [s for s in RAYSET_ORDER if s in present]
    raysets += sorted(str(s) for s in present if s is not None and s not in RAYSET_ORDER)
    scenes = _ordered((str(r["scene"]) for r in kept if r.get("scene") is not None),
                      config.get("scenes", ()))  # fmt: skip
    # Counter cells run on one thread whatever the sweep's thread counts
    threads = {int(r["threads"]) for r in kept
               if r.get("kind") != "counters" and isinstance(r.get("threads"), int)}  # fmt: skip
    return Study(path.name, header, kept, scenes, raysets, sorted(threads))


def system(record: Record) -> str:
    """Return a record's system: ``builder + traversal`` (the builder for build cells)."""
    if record.get("traversal"):
        return f"{record.get('builder')} + {record.get('traversal')}"
    return str(record.get("builder"))


def family(builder: str) -> str:
    """Return the family of a builder key: the part before the first dot (``bvh2``)."""
    return builder.split(".", 1)[0]


def _num(value: Any, digits: int = 2) -> str:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return MISSING
    return f"{value:,.{digits}f}"


def _size(value: Any) -> str:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return MISSING
    amount = float(value)
    for unit in ("B", "KiB", "MiB"):
        if amount < 1024.0:
            return f"{amount:,.0f} B" if unit == "B" else f"{amount:,.1f} {unit}"
        amount /= 1024.0
    return f"{amount:,.1f} GiB"


def _threads_label(threads: int) -> str:
    return f"{threads} thread" + ("" if threads == 1 else "s")


def _grid_of(records: list[Record], value: str) -> tuple[list[str], dict[tuple[str, str], Any]]:
    """Return the systems and ``(system, scene) -> value or "failed"`` of a scene-column table."""
    rows = _ordered(system(r) for r in records)
    grid: dict[tuple[str, str], Any] = {}
    for r in records:
        grid[(system(r), str(r.get("scene")))] = (
            r.get(value) if r.get("status") == "ok" else "failed"
        )
    return rows, grid


def _scene_cells(
    study: Study,
    values: dict[str, Any],
    fmt: Callable[[Any], str],
    best: dict[str, Any] | None = None,
) -> list[TableCell]:
    """Return one cell per scene; "failed" in red, the best value of a column in bold."""
    cells = []
    for scene in study.scenes:
        value = values.get(scene)
        if value == "failed":
            cells.append(TableCell("failed", "num bad"))
        else:
            top = best is not None and value is not None and value == best.get(scene)
            cells.append(TableCell(fmt(value), "num best" if top else "num"))
    return cells


def _peer_medians(cells: list[Record]) -> dict[str, dict[str, float]]:
    """Return ``peer -> scene -> median Mrays/s`` over the cells of one table."""
    values: dict[str, dict[str, list[float]]] = {}
    for record in cells:
        if record.get("status") != "ok":
            continue
        for name, peer in (record.get("peers") or {}).items():
            mrays = peer.get("mrays_median") if isinstance(peer, dict) else None
            if isinstance(mrays, (int, float)):
                values.setdefault(name, {}).setdefault(record["scene"], []).append(float(mrays))
    return {name: {scene: statistics.median(v) for scene, v in by_scene.items()}
            for name, by_scene in values.items()}  # fmt: skip


def mrays_tables(study: Study) -> list[Table]:
    """Return the throughput tables (Tables 5.1–5.3): one per ray set and thread count."""
    tables = []
    for rayset in study.raysets:
        for threads in study.threads:
            cells = [r for r in study.of("timing")
                     if r.get("rayset") == rayset and r.get("threads") == threads]  # fmt: skip
            if not cells:
                continue
            names, grid = _grid_of(cells, "mrays_median")
            rows: dict[str, dict[str, Any]] = {
                n: {s: grid.get((n, s)) for s in study.scenes} for n in names
            }
            peers: dict[str, dict[str, Any]] = {
                f"{n} (peer)": dict(v) for n, v in _peer_medians(cells).items()
            }
            rows.update(peers)
            # The fastest system of each scene is shown in bold
            best: dict[str, Any] = {}
            for s in study.scenes:
                numbers = [float(v[s]) for v in rows.values() if isinstance(v.get(s), (int, float))]
                best[s] = max(numbers, default=None)
            table = Table(f"Mrays/s by scene × structure: {rayset} rays, "
                          f"{_threads_label(threads)}",
                          ["system", *study.scenes, "average across scenes"], [])  # fmt: skip
            for name, values in rows.items():
                numbers = [v for v in values.values() if isinstance(v, (int, float))]
                average = _num(statistics.fmean(numbers)) if numbers else MISSING
                if numbers and len(numbers) < len(study.scenes):
                    average += "*"
                    table.note = "* the average of the scenes with a value."
                cells_ = [TableCell(name), *_scene_cells(study, values, _num, best),
                          TableCell(average, "num")]  # fmt: skip
                if name in peers:
                    cells_ = [replace(c, css=f"{c.css} peer".strip()) for c in cells_]
                table.rows.append(cells_)
            tables.append(table)
    return tables


def build_tables(study: Study) -> list[Table]:
    """Return Table 5.4's figures: median build ms per thread count, and structure size."""
    builds = study.of("build")
    if not builds:
        return []
    tables = []
    header = ["builder", *study.scenes]
    for threads in study.threads:
        cells = [r for r in builds if r.get("threads") == threads]
        if not cells:
            continue
        names, grid = _grid_of(cells, "build_ms_median")
        table = Table(f"Build time by scene × builder: median ms, {_threads_label(threads)}",
                      header, [])  # fmt: skip
        for name in names:
            values = {s: grid.get((name, s)) for s in study.scenes}
            table.rows.append([TableCell(name), *_scene_cells(study, values, _num)])
        tables.append(table)
    # Sizes do not depend on the thread count: the last record wins, so finished builds
    # go last, and of those the one with the most threads
    ordered = sorted(builds, key=lambda r: (r.get("status") == "ok", int(r.get("threads") or 0)))
    names, grid = _grid_of(ordered, "bytes")
    table = Table("Structure size by scene × builder", header, [])
    for name in names:
        values = {s: grid.get((name, s)) for s in study.scenes}
        table.rows.append([TableCell(name), *_scene_cells(study, values, _size)])
    tables.append(table)
    return tables


def _validation(record: Record) -> TableCell:
    validated, mismatches = record.get("validated"), record.get("mismatches")
    if not isinstance(validated, int):
        return TableCell(MISSING, "num")
    bad = isinstance(mismatches, int) and mismatches > 0
    return TableCell(f"{mismatches}/{validated}", "num bad" if bad else "num",
                     "mismatches / rays checked against the oracle")  # fmt: skip


def counter_tables(study: Study) -> list[Table]:
    """Return the traversal-cost tables: counters per ray, one table per ray set."""
    tables = []
    header = ["scene", "system", "nodes/ray (grids: cells)", "nodes p95", "prim tests/ray",
              "bytes/ray", "hit rate", "mismatches/validated"]  # fmt: skip
    for rayset in study.raysets:
        cells = [r for r in study.of("counters") if r.get("rayset") == rayset]
        if not cells:
            continue
        order = {s: i for i, s in enumerate(study.scenes)}
        cells.sort(key=lambda r: order.get(str(r.get("scene")), len(order)))
        table = Table(f"Traversal cost per ray: {rayset} rays", header, [])
        for r in cells:
            row = [TableCell(str(r.get("scene"))), TableCell(system(r))]
            if r.get("status") != "ok":
                row += [TableCell("failed", "num bad")] + [TableCell(MISSING, "num")] * 5
                table.rows.append(row)
                continue
            means = r.get("counters_mean") or {}
            grid = family(str(r.get("builder"))) == "grid"
            nodes = means.get("cells") if grid else r.get("nodes_per_ray")
            row += [TableCell(_num(nodes), "num"),
                    TableCell(MISSING if grid else _num(r.get("nodes_p95"), 0), "num"),
                    TableCell(_num(r.get("prims_per_ray")), "num"),
                    TableCell(_num(r.get("bytes_per_ray"), 0), "num"),
                    TableCell(_num(100 * r["hit_rate"], 1) + "%" if isinstance(
                        r.get("hit_rate"), (int, float)) else MISSING, "num"),
                    _validation(r)]  # fmt: skip
            table.rows.append(row)
        tables.append(table)
    return tables


def charts(study: Study, out_dir: Path) -> tuple[list[Picture], list[Picture]]:
    """Write the bar charts (Figures 5.1–5.6); return (throughput charts, traffic chart).

    Throughput charts show the most threads a ray set was timed with.
    """
    throughput: list[Picture] = []
    timing = study.ok("timing")
    families = _ordered(family(str(r.get("builder"))) for r in timing)
    for fam in families:
        for rayset in study.raysets:
            cells = [r for r in timing if r.get("rayset") == rayset
                     and family(str(r.get("builder"))) == fam]  # fmt: skip
            if not cells:
                continue
            threads = max(int(r.get("threads") or 0) for r in cells)
            cells = [r for r in cells if r.get("threads") == threads]
            names, grid = _grid_of(cells, "mrays_median")
            series = [Series(n, tuple(grid.get((n, s)) for s in study.scenes)) for n in names]
            for peer, medians in _peer_medians(cells).items():
                series.append(Series(f"{peer} (peer)", tuple(medians.get(s) for s in study.scenes),
                                     hatched=True))  # fmt: skip
            title = f"{fam}: Mrays/s, {rayset} rays, {_threads_label(threads)}"
            name = safe_name("mrays", fam, rayset) + ".png"
            width, height = bar_chart(out_dir / name, title, study.scenes, series, "Mrays/s")
            throughput.append(Picture(name, f"bar chart: {title}", width, height,
                                      f"{title}; peers hatched."))  # fmt: skip
    traffic: list[Picture] = []
    counters = study.ok("counters")
    systems = _ordered(system(r) for r in counters)
    if systems:
        series = []
        for rayset in study.raysets:
            means: list[float | None] = []
            for name in systems:
                found = [r["bytes_per_ray"] for r in counters if system(r) == name
                         and r.get("rayset") == rayset
                         and isinstance(r.get("bytes_per_ray"), (int, float))]  # fmt: skip
                means.append(statistics.fmean(found) if found else None)
            series.append(Series(rayset, tuple(means)))
        title = "Memory traffic: bytes fetched per ray, mean across scenes"
        width, height = bar_chart(out_dir / "bytes-per-ray.png", title, systems, series,
                                  "bytes/ray")  # fmt: skip
        traffic.append(Picture("bytes-per-ray.png", f"bar chart: {title}", width, height,
                               f"{title}, one bar per ray set."))  # fmt: skip
    return throughput, traffic


def _heatmap_pairs(study: Study) -> dict[str, list[tuple[str, str]]]:
    pairs: dict[str, list[tuple[str, str]]] = {}
    for r in study.records:
        if r.get("kind") in ("counters", "timing") and r.get("traversal") and r.get("scene"):
            pair = (str(r["builder"]), str(r["traversal"]))
            scene_pairs = pairs.setdefault(str(r["scene"]), [])
            if pair not in scene_pairs:
                scene_pairs.append(pair)
    return {s: pairs[s] for s in study.scenes if s in pairs}


def _notes(study: Study) -> list[str]:
    notes = []
    for r in study.ok("timing"):
        for note in r.get("notes") or ():
            notes.append(f"{r.get('scene')}, {r.get('rayset')} rays: {note}")
    return list(dict.fromkeys(notes))


def _settings_table(caption: str, items: dict[str, Any]) -> Table:
    rows = []
    for key, value in items.items():
        text = value if isinstance(value, str) else json.dumps(value, sort_keys=True)
        rows.append([TableCell(str(key)), TableCell(text, "code")])
    return Table(caption, ["setting", "value"], rows)


def _number(tables: list[Table], start: int) -> int:
    for k, table in enumerate(tables, start=start):
        table.caption = f"Table {k}. {table.caption}"
    return start + len(tables)


def write_report(
    results_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    heatmaps: bool = False,
    heatmap_size: tuple[int, int] = (160, 120),
) -> Path:
    """Write the study's HTML report of a results file; return the path of ``index.html``.

    Parameters
    ----------
    results_path : path-like
        A sweep's results file (JSON lines, :mod:`rayaccel.study.results`).
    out_dir : path-like
        Folder of the report, created if needed: ``index.html`` and its PNG files.
    heatmaps : bool
        Also trace and draw the heatmap gallery (builds every structure again and
        may compile kernels; off by default).
    heatmap_size : (width, height)
        Resolution of each heatmap.

    Returns
    -------
    pathlib.Path
        The written ``index.html``.

    Raises
    ------
    rayaccel.study.results.ResultsFormatError
        When the file is not a results file this version reads.
    BackendUnavailableError
        When Jinja2 (the ``study`` extra) is not installed.
    """
    try:
        import jinja2
    except ImportError as exc:  # pragma: no cover - jinja2 comes with the study extra
        raise BackendUnavailableError(
            "the study report needs Jinja2: pip install 'rayaccel[study]'"
        ) from exc
    study = load_study(results_path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    throughput, build, cost = mrays_tables(study), build_tables(study), counter_tables(study)
    failed = [r for r in study.records if r.get("status") == "failed"]
    machine = {"rayaccel": study.header.get("rayaccel", MISSING),
               **(study.header.get("environment") or {})}  # fmt: skip
    settings = [_settings_table("Machine and versions", machine)]
    if study.header.get("config"):
        settings.append(_settings_table("Sweep configuration", study.header["config"]))
    start = _number(throughput, 1)
    start = _number(build, start)
    start = _number(cost, start)
    failed_caption = f"Table {start}. Failed cells" if failed else ""
    _number(settings, start + bool(failed))
    bars, traffic = charts(study, out)
    numbered = [replace(p, caption=f"Figure {k}. {p.caption}")
                for k, p in enumerate([*bars, *traffic], start=1)]  # fmt: skip
    bars, traffic = numbered[: len(bars)], numbered[len(bars) :]
    gallery: list[HeatmapScene] = []
    if heatmaps:
        width, height = heatmap_size
        gallery = heatmap_gallery(_heatmap_pairs(study), out, width=width, height=height)
    environment = jinja2.Environment(
        loader=jinja2.PackageLoader("rayaccel.study", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    html = environment.get_template("report.html.j2").render(
        name=study.name,
        n_records=len(study.records),
        n_failed=len(failed),
        scenes=study.scenes,
        raysets=study.raysets,
        threads=study.threads,
        throughput=throughput,
        bars=bars,
        notes=_notes(study),
        build=build,
        cost=cost,
        traffic=traffic,
        gallery=gallery,
        failed_caption=failed_caption,
        failed=failed,
        settings=settings,
    )
    return write_bytes_atomic(out / "index.html", html.encode("utf-8"))
