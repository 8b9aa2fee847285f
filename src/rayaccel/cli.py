"""The ``rayaccel`` command line (layer 8): list, info, render, bench, cache.

::

    rayaccel list
    rayaccel info SCENE [--accel KEY] [--option k=v ...]
    rayaccel render SCENE [--accel KEY ...] [--traversal KEY] --view shade|heatmap
                    [--metric NAME] -o out.png [--legend legend.png] [--scale-max V]
    rayaccel bench SCENE ... [--accel KEY ... | all] [--rays primary,diffuse,shadow]
                   [--threads N[,M]] [--peers embree,open3d,trimesh|all|none]
                   [--repeats K] [--json results.jsonl] [--validate N]
    rayaccel cache clear|info
    rayaccel cache warm [--structure NAME ...] [--jobs N] [--serial-only]
    rayaccel scenes list [--remote] [--json]
    rayaccel scenes fetch NAME ... [--no-verify] [--force] [--progress]

``SCENE`` is a catalog name (``rayaccel list`` shows them; file scenes are found
through ``RAYACCEL_SCENE_PATH``) or the path of a scene file. Choices of builders,
traversals, counters and peers come from the registry, so new variants appear
here without edits. This is the only place that catches exceptions broadly: an
error prints one line to stderr and exits with status 1 (2 for usage errors,
130 when interrupted); ``--debug`` adds the traceback.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import sys
import traceback
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rayaccel.errors import InvalidInputError, RayAccelError

if TYPE_CHECKING:
    import numpy.typing as npt

    from rayaccel.registry import Role

EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130


# -- argument helpers --------------------------------------------------------------------------


def parse_value(text: str) -> Any:
    """Return a Python literal for ``text`` (int, float, bool, None, tuple...), else the string."""
    lowered = text.strip().lower()
    if lowered in ("true", "yes", "on"):
        return True
    if lowered in ("false", "no", "off"):
        return False
    if lowered in ("none", "null"):
        return None
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def parse_options(items: Sequence[str] | None) -> dict[str, Any]:
    """Parse repeated ``k=v`` options into a dict.

    Raises
    ------
    InvalidInputError
        An item without ``=``.
    """
    options: dict[str, Any] = {}
    for item in items or ():
        for part in item.split(","):
            if not part.strip():
                continue
            key, sep, value = part.partition("=")
            if not sep or not key.strip():
                raise InvalidInputError(f"--option: expected key=value, got {part!r}")
            options[key.strip()] = parse_value(value.strip())
    return options


def _split_list(values: Sequence[str] | None) -> list[str]:
    return [item.strip() for value in values or () for item in value.split(",") if item.strip()]


def _threads(text: str) -> list[int]:
    try:
        counts = [int(item) for item in text.split(",") if item.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected N or N,M,..., got {text!r}") from None
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"expected positive thread counts, got {text!r}")
    return counts


def _int_at_least(minimum: int, expected: str) -> Callable[[str], int]:
    """Return an argparse ``type`` parsing an int ``>= minimum`` (``expected`` names it)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {value}")
        return value

    return parse


_positive_int = _int_at_least(1, "a positive integer")
_nonnegative_int = _int_at_least(0, "an integer >= 0")


def _add_image_size(p: argparse.ArgumentParser) -> None:
    """Add ``--width`` and ``--height``, the pixels of the camera's image (render, bench)."""
    for name in ("--width", "--height"):
        p.add_argument(name, type=_positive_int, default=512)


def default_builder() -> str:
    """Return the builder :func:`rayaccel.build` uses when none is named."""
    from rayaccel import registry

    return registry.DEFAULT_BUILD_KEY


def _builder_keys(values: Sequence[str] | None, default_all: bool) -> list[str]:
    from rayaccel import registry

    keys = _split_list(values)
    if not keys:
        return registry.build_keys() if default_all else [default_builder()]
    if "all" in keys:
        return registry.build_keys()
    for key in keys:
        registry.get_chain(key)
    return keys


def load_scene(spec: str, params: dict[str, Any] | None = None) -> Any:
    """Return the mesh of a catalog name or scene file path."""
    from rayaccel.scene import catalog

    return catalog.get(spec, **(params or {}))


def _out(text: str = "") -> None:
    sys.stdout.write(text + "\n")


# -- commands ----------------------------------------------------------------------------------


def cmd_list(args: argparse.Namespace) -> int:
    """Print every registered builder, build step and traversal, the counters, peers, scenes."""
    from rayaccel import registry
    from rayaccel.bench.peers import PEERS
    from rayaccel.counters import COUNTER_NAMES
    from rayaccel.render.heatmap import counter_unit
    from rayaccel.scene import catalog

    if args.json:
        role_order: tuple[Role, ...] = ("builder", "step", "traversal")
        data: dict[str, object] = {
            role: [
                {"key": v.key, "structure": v.structure, "backend": v.backend,
                 "summary": v.summary, "reference": v.reference,
                 "options": _option_defaults(v.options),
                 **({"stage": v.stage} if v.role == "step" else {}),
                 **({"takes_refs": v.takes_refs} if v.role == "builder" else {})}
                for v in registry.variants(role)
            ]
            for role in role_order
        }  # fmt: skip
        data["configurations"] = registry.configurations()
        data["counters"] = list(COUNTER_NAMES)
        data["peers"] = {name: cls().available() for name, cls in PEERS.items()}
        data["scenes"] = catalog.names()
        _out(json.dumps(data, indent=2, default=str))
        return 0
    roles: tuple[tuple[Role, str], ...] = (
        ("builder", "Builders"),
        ("step", "Build steps (chain as BUILDER+STEP; 'before' steps run ahead of the builder)"),
        ("traversal", "Traversals"),
    )
    for role, title in roles:
        variants = registry.variants(role)
        _out(f"{title} ({len(variants)}):")
        width = max((len(v.key) for v in variants), default=0)
        for v in variants:
            if v.role == "step":
                _out(f"  {v.key:<{width}}  [{v.stage}] {v.summary}")
            elif v.role == "builder" and v.takes_refs:
                _out(f"  {v.key:<{width}}  {v.summary} (takes pre-split refs)")
            else:
                _out(f"  {v.key:<{width}}  {v.summary}")
            if v.reference:
                _out(f"  {'':<{width}}  ref: {v.reference}")
            options = _option_defaults(v.options)
            if options:
                text = ", ".join(f"{k}={val!r}" for k, val in options.items())
                _out(f"  {'':<{width}}  options: {text}")
        _out()
    _out("Configurations (builder+steps; the thesis's BVH comparison):")
    for key in registry.configurations():
        _out(f"  {key}")
    _out()
    _out("Counters (per ray; heatmap --metric):")
    for name in COUNTER_NAMES:
        _out(f"  {name:<22}  {counter_unit(name)}")
    _out()
    _out("Peers (bench --peers):")
    for name, cls in PEERS.items():
        reason = cls().unavailable_reason()
        _out(f"  {name:<8}  {'available' if reason is None else 'unavailable: ' + reason}")
    _out()
    _out("Scenes:")
    for info in catalog.describe():
        _out(f"  {info.name:<20}  {info.kind:<10}  {info.summary}")
    return 0


def _option_defaults(options: type) -> dict[str, Any]:
    import dataclasses

    if not dataclasses.is_dataclass(options):
        return {}
    return {
        f.name: f.default for f in dataclasses.fields(options)
        if f.default is not dataclasses.MISSING
    }  # fmt: skip


def cmd_info(args: argparse.Namespace) -> int:
    """Print mesh statistics and the built structure's ``info()``."""
    import numpy as np

    from rayaccel import api

    mesh = load_scene(args.scene, parse_options(args.scene_option))
    lo, hi = mesh.bounds()
    areas = mesh.areas()
    mesh_info = {
        "name": mesh.name,
        "n_triangles": mesh.n_triangles,
        "n_vertices": mesh.n_vertices,
        "bounds_lo": [round(float(x), 6) for x in lo],
        "bounds_hi": [round(float(x), 6) for x in hi],
        "surface_area": float(np.sum(areas, dtype=np.float64)),
        "degenerate_triangles": int(np.count_nonzero(areas == 0)),
    }
    accel = api.build(mesh, args.accel, **parse_options(args.option))
    accel_info = accel.info(epo=args.epo)
    if args.validate:
        accel.validate()
        accel_info["validated"] = True
    if args.json:
        _out(json.dumps({"mesh": mesh_info, "accel": accel_info}, indent=2, default=str))
        return 0
    _out(f"scene {args.scene}")
    for key, value in mesh_info.items():
        _out(f"  {key:<22} {_show(value)}")
    _out(f"accel {accel.key}")
    for key, value in accel_info.items():
        _out(f"  {key:<22} {_show(value)}")
    return 0


def _show(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    if isinstance(value, dict):
        return ", ".join(f"{k}={v!r}" for k, v in value.items()) or "-"
    return str(value)


def _output_paths(out: Path, names: Sequence[str]) -> list[Path]:
    if len(names) == 1:
        return [out]
    suffix = out.suffix or ".png"
    return [out.with_name(f"{out.stem}-{name}{suffix}") for name in names]


def cmd_render(args: argparse.Namespace) -> int:
    """Render shaded or heatmap images of one or more structures (heatmaps share a scale)."""
    from rayaccel import api, registry
    from rayaccel.bench.raysets import scene_camera
    from rayaccel.render import heatmap as hm
    from rayaccel.render.shading import shade

    if args.view == "path":
        return _render_path(args)
    if args.record or args.exr:
        raise InvalidInputError("--record and --exr go with --view path")
    if args.view == "heatmap":
        hm.check_metric(args.metric)
    elif args.legend:
        raise InvalidInputError("--legend: only heatmaps have a legend (use --view heatmap)")
    for path in (args.output, args.legend):
        if path is not None and not Path(path).parent.resolve().is_dir():
            raise InvalidInputError(f"{path}: the folder does not exist")
    mesh = load_scene(args.scene, parse_options(args.scene_option))
    builders = _builder_keys(args.accel, default_all=False)
    options = parse_options(args.option)
    traversals = _split_list(args.traversal)
    for key in traversals:
        registry.get(key, "traversal")
    camera, _ = scene_camera(mesh, args.scene, width=args.width, height=args.height)
    images: list[tuple[str, Any]] = []
    for builder in builders:
        accel = api.build(mesh, builder, **options)
        traversal_or_default: list[str | None] = list(traversals) if traversals else [None]
        for traversal in traversal_or_default:
            name = builder if traversal is None else f"{builder}+{traversal}"
            image: npt.NDArray[Any]
            if args.view == "shade":
                image = shade(accel, camera, traversal=traversal, ao_samples=args.ao,
                              ao_radius=args.ao_radius, seed=args.seed)  # fmt: skip
            else:
                image = hm.trace_counters(accel, camera, args.metric, traversal=traversal,
                                          query=args.query)  # fmt: skip
            images.append((name, image))
    paths = _output_paths(Path(args.output), [name for name, _ in images])
    if args.view == "heatmap":
        scale = hm.HeatScale.fit(
            [values for _, values in images],
            args.metric,
            vmin=args.scale_min,
            vmax=args.scale_max,
            log=not args.linear,
        )
        for (name, values), path in zip(images, paths, strict=True):
            hm.write_png(path, hm.heatmap_image(values, scale))
            _out(f"{path}: {name} {args.metric} per ray, mean {values.mean():.4g}, "
                 f"max {values.max():.4g}")  # fmt: skip
        _out(f"scale: {scale.vmin:g} .. {scale.vmax:g} {'log' if scale.log else 'linear'}")
        if args.legend:
            hm.write_png(args.legend, hm.legend_image(scale))
            _out(f"{args.legend}: legend")
    else:
        for (name, image), path in zip(images, paths, strict=True):
            hm.write_png(path, image)
            _out(f"{path}: {name} shaded{f', {args.ao} AO rays per pixel' if args.ao else ''}")
    return 0


def _render_path(args: argparse.Namespace) -> int:
    """``render --view path``: path trace one structure; record its rays with ``--record``."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from rayaccel import api
    from rayaccel.render import heatmap as hm
    from rayaccel.render.path import PathOptions
    from rayaccel.study.recording import render_scene

    builders = _builder_keys(args.accel, default_all=False)
    traversals = _split_list(args.traversal)
    if len(builders) > 1 or len(traversals) > 1:
        raise InvalidInputError("--view path renders one structure and traversal at a time")
    for path in (args.output, args.exr):
        if path is not None and not Path(path).parent.resolve().is_dir():
            raise InvalidInputError(f"{path}: the folder does not exist")
    options = PathOptions(spp=args.spp, max_depth=args.max_depth, seed=args.seed)
    mesh = load_scene(args.scene, parse_options(args.scene_option))
    accel = api.build(mesh, builders[0], **parse_options(args.option))
    with Progress("[bold]path[/]", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=Console(stderr=True), transient=True) as bar:  # fmt: skip
        task = bar.add_task("samples", total=options.spp)
        image = render_scene(
            mesh, args.scene, accel=accel, traversal=traversals[0] if traversals else None,
            width=args.width, height=args.height, options=options, record_to=args.record,
            progress=lambda done, total: bar.update(task, completed=done),
        )  # fmt: skip
    hm.write_png(args.output, image.tonemapped(args.exposure))
    _out(f"{args.output}: path traced, {options.spp} samples per pixel, depth {options.max_depth}")
    if args.exr:
        image.write_exr(args.exr)
        _out(f"{args.exr}: linear radiance (OpenEXR)")
    counts = ", ".join(f"{name} {n:,}" for name, n in image.counts.items())
    _out(f"rays: {counts}")
    if args.record:
        _out(f"{args.record}: recorded ray sets (rays.json lists them)")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the benchmark harness, print a table and write JSONL results."""
    from rayaccel.bench import harness, report
    from rayaccel.bench.peers import parse_peers
    from rayaccel.bench.raysets import parse_kinds

    done: dict[Any, Any] = {}
    if args.resume:
        if not args.json:
            raise InvalidInputError("--resume: needs --json, the results file to complete")
        if Path(args.json).exists():
            done = harness.completed_cells(report.read_jsonl(args.json))
    config = harness.BenchConfig(
        done=done,
        scenes=list(args.scenes),
        builders=_builder_keys(args.accel, default_all=True),
        traversals=_split_list(args.traversal),
        builder_options=parse_options(args.option),
        ray_kinds=parse_kinds(args.rays),
        threads=args.threads or [],
        peers=parse_peers(args.peers),
        repeats=args.repeats,
        build_repeats=args.build_repeats,
        width=args.width,
        height=args.height,
        validate=args.validate,
        seed=args.seed,
        warmup_triangles=args.warmup_triangles,
        settle_ms=args.settle_ms,
    )
    writer = report.JsonlWriter(args.json) if args.json else None
    records: list[dict[str, Any]] = []

    def sink(record: dict[str, Any]) -> None:
        records.append(record)
        if writer is not None:
            writer.append(record)

    interrupted = False
    result = None
    try:
        result = harness.run_bench(config, on_record=sink, progress=not args.no_progress)
    except KeyboardInterrupt:
        interrupted = True
    _print_bench(records, result.notes if result else [], markdown=args.markdown)
    if writer is not None:
        _out(f"results: {len(records)} records appended to {args.json}")
    if interrupted:
        kept = f"; {len(records)} finished records kept in {args.json}" if writer else ""
        sys.stderr.write(f"rayaccel: interrupted{kept}\n")
        return EXIT_INTERRUPTED
    return 0


def _print_bench(records: list[dict[str, Any]], notes: list[str], *, markdown: bool) -> None:
    from rayaccel.bench import report

    table = report.markdown_table(records) if markdown else report.text_table(records)
    _out(table)
    for line in (report.compile_summary(records), report.environment_line(records)):
        if line:
            _out(line)
    for note in notes:
        _out(f"note: {note}")


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run (or resume) a sweep: every cell of a configuration, records appended to a file."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from rayaccel.study.config import load_config
    from rayaccel.study.sweep import sweep

    config = load_config(args.config)
    if args.workers < 0:
        raise InvalidInputError("--workers must be >= 0")
    with Progress("[bold]sweep[/]", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  "{task.description}", console=Console(stderr=True),
                  transient=True) as bar:  # fmt: skip
        task = bar.add_task("", total=None)

        def step(done: int, total: int, label: str) -> None:
            bar.update(task, completed=done, total=total, description=label)

        summary = sweep(config, args.output, workers=args.workers, scheduler=args.scheduler,
                        rays_folder=args.rays, progress=step)  # fmt: skip
    _out(f"{args.output}: {summary.ran} cells run ({summary.failed} failed), "
         f"{summary.skipped} already done, of {summary.cells}")  # fmt: skip
    _out(f"time: {summary.wall_seconds:.1f} s in all, {summary.cell_seconds:.1f} s in cells, "
         f"{summary.rays_seconds:.1f} s making ray sets; sweep overhead "
         f"{100 * summary.overhead:.1f}%")  # fmt: skip
    return 1 if summary.failed else 0


def cmd_report(args: argparse.Namespace) -> int:
    """Write the study's HTML report of a sweep's results file; print the page's path."""
    from rayaccel.study.report import write_report

    index = write_report(args.results, args.output, heatmaps=args.heatmaps)
    _out(str(index))
    return 0


def cmd_cache(args: argparse.Namespace) -> int:
    """Show, clear or fill numba's on-disk cache of rayaccel kernels."""
    from rayaccel.bench.harness import numba_cache_dirs, numba_cache_files

    if args.action == "warm":
        return _warm_cache(args)

    files = numba_cache_files()
    size = sum(p.stat().st_size for p in files if p.exists())
    where = ", ".join(str(d) for d in numba_cache_dirs()[:3])
    more = len(numba_cache_dirs()) - 3
    where += f" and {more} more" if more > 0 else ""
    if args.action == "info":
        _out(f"{len(files)} cache files, {size / 2**20:.1f} MiB in {where or 'nothing'}")
        return 0
    removed = 0
    for path in files:
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            continue
    _out(f"removed {removed} numba cache files ({size / 2**20:.1f} MiB) from {where or 'nothing'}")
    return 0


def _warm_cache(args: argparse.Namespace) -> int:
    """Compile every build key and traversal kernel into the cache, ``--jobs`` at a time."""
    from rayaccel import precompile

    keep = precompile.common_parallel if args.common_parallel else None
    todo = precompile.jobs(args.structure, parallel=not args.serial_only, variant_filter=keep)
    total = len(todo)
    _out(f"compiling {total} kernel groups on {args.jobs} processes")

    def done(job: precompile.Job, seconds: float, k: int) -> None:
        if not args.quiet:
            _out(f"[{k}/{total}] {job.name}: {seconds:.1f} s")

    wall = precompile.precompile(todo, args.jobs, on_done=done)
    _out(f"cache warm: {total} jobs in {wall:.0f} s")
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    """List the scenes (``--remote``: the downloadable ones) or fetch downloadable scenes."""
    from rayaccel.scene import catalog
    from rayaccel.scene.fetch import cache_dir, download_sha256, lookup

    if args.action == "fetch":
        if not args.names:
            raise InvalidInputError(
                "scenes fetch: name at least one scene (see 'scenes list --remote')"
            )
        for name in args.names:
            path = catalog.fetch(name, verify=not args.no_verify, force=args.force,
                                 progress=args.progress)  # fmt: skip
            _out(f"{name}: {path}")
            if lookup(name).sha256 is None:
                sys.stderr.write(
                    f"rayaccel: warning: {name} was downloaded unchecked (no published "
                    f"SHA-256); its download has SHA-256 {download_sha256(name)}\n"
                )
        return 0
    if args.names:
        raise InvalidInputError(f"scenes list takes no scene names, got {args.names}")
    if not args.remote:
        infos = catalog.describe()
        if args.json:
            _out(json.dumps([{"name": i.name, "kind": i.kind, "summary": i.summary, "up": i.up,
                              "path": None if i.path is None else str(i.path)}
                             for i in infos], indent=2))  # fmt: skip
            return 0
        for info in infos:
            _out(f"  {info.name:<20}  {info.kind:<10}  {info.summary}")
        return 0
    rows = catalog.remote_status()
    if args.json:
        _out(json.dumps([{"name": r.scene.name, "title": r.scene.title, "url": r.scene.url,
                          "sha256": r.scene.sha256, "size": r.scene.size,
                          "member": r.scene.member, "licence": r.scene.licence,
                          "credit": r.scene.credit, "notes": r.scene.notes,
                          "cached": r.cached,
                          "path": None if r.path is None else str(r.path)}
                         for r in rows], indent=2))  # fmt: skip
        return 0
    _out(f"Downloadable scenes (cache: {cache_dir()}):")
    width = max((len(r.scene.name) for r in rows), default=0)
    for r in rows:
        size = "size ?" if r.scene.size is None else f"{r.scene.size / 1e6:.1f} MB"
        state = "cached" if r.cached else "not fetched"
        check = "sha256 known" if r.verified else "NO published sha256 (needs --no-verify)"
        _out(f"  {r.scene.name:<{width}}  {r.scene.title}; {size}; {state}; {check}")
        _out(f"  {'':<{width}}  licence: {r.scene.licence}")
        _out(f"  {'':<{width}}  credit: {r.scene.credit}")
        _out(f"  {'':<{width}}  from: {r.scene.url}")
    return 0


# -- parser ------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    """Return the argument parser of ``rayaccel`` (help texts list registry keys)."""
    from rayaccel import registry
    from rayaccel.counters import COUNTER_NAMES

    builders = ", ".join(registry.keys("builder"))
    traversals = ", ".join(registry.keys("traversal"))
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                        help="show the traceback of errors")  # fmt: skip
    parser = argparse.ArgumentParser(
        prog="rayaccel",
        parents=[common],
        description="Build, traverse, measure and compare ray tracing acceleration structures.",
    )
    parser.add_argument("--version", action="version", version=f"rayaccel {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("list", parents=[common], help="registered builders, traversals, "
                       "counters, peers and scenes")  # fmt: skip
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_list)

    scene_help = "catalog scene name (see 'rayaccel list') or scene file path"
    accel_help = f"builder key ({builders})"
    option_help = "builder option key=value (repeatable), e.g. max_leaf_size=4"

    p = sub.add_parser("info", parents=[common], help="mesh statistics and structure info")
    p.add_argument("scene", help=scene_help)
    p.add_argument("--accel", default=default_builder(), help=accel_help)
    p.add_argument("--option", action="append", metavar="K=V", help=option_help)
    p.add_argument("--scene-option", action="append", metavar="K=V",
                   help="procedural scene parameter, e.g. level=3")  # fmt: skip
    p.add_argument("--validate", action="store_true", help="also check every invariant")
    p.add_argument(
        "--epo", action="store_true", help="also compute the end-point overlap (slow on big scenes)"
    )
    p.add_argument("--json", action="store_true", help="print JSON")
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("render", parents=[common], help="shaded picture or counter heatmap")
    p.add_argument("scene", help=scene_help)
    p.add_argument("--accel", nargs="+", metavar="KEY",
                   help=f"{accel_help}; several (or 'all') write one image each, "
                        "heatmaps on one shared scale")  # fmt: skip
    p.add_argument(
        "--traversal",
        nargs="+",
        metavar="KEY",
        help=f"traversal key ({traversals}); default the structure's stack traversal",
    )
    p.add_argument("--view", choices=("shade", "heatmap", "path"), default="shade",
                   help="shade: headlight preview; heatmap: a counter per pixel; path: path "
                        "tracing (materials and lights of the scene)")  # fmt: skip
    p.add_argument(
        "--metric",
        default="nodes",
        help=f"heatmap counter ({', '.join(COUNTER_NAMES)}); default nodes",
    )
    p.add_argument("--query", choices=("closest", "any"), default="closest",
                   help="heatmap query kind")  # fmt: skip
    p.add_argument("-o", "--output", required=True, help="output PNG")
    p.add_argument("--legend", help="write the heatmap legend PNG here")
    p.add_argument("--scale-max", type=float, help="heatmap value mapped to white")
    p.add_argument("--scale-min", type=float, help="heatmap value mapped to black")
    p.add_argument("--linear", action="store_true", help="linear instead of log heatmap scale")
    _add_image_size(p)
    p.add_argument(
        "--ao",
        type=_nonnegative_int,
        default=0,
        help="ambient occlusion rays per pixel for --view shade (0: off)",
    )
    p.add_argument("--ao-radius", type=float, help="ambient occlusion distance")
    p.add_argument("--spp", type=_positive_int, default=4,
                   help="--view path: samples per pixel (default 4)")  # fmt: skip
    p.add_argument("--max-depth", type=_nonnegative_int, default=3,
                   help="--view path: bounces after the camera ray (default 3)")  # fmt: skip
    p.add_argument("--exposure", type=float, default=1.0,
                   help="--view path: radiance scale before the sRGB encoding")  # fmt: skip
    p.add_argument("--exr", help="--view path: also write the linear radiance as OpenEXR")
    p.add_argument(
        "--record", metavar="DIR", help="--view path: record the ray sets into DIR (rays.json)"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--option", action="append", metavar="K=V", help=option_help)
    p.add_argument("--scene-option", action="append", metavar="K=V",
                   help="procedural scene parameter")  # fmt: skip
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("bench", parents=[common], help="time structures and peers on "
                       "primary, diffuse and shadow rays")  # fmt: skip
    p.add_argument("scenes", nargs="+", metavar="SCENE",
                   help=scene_help + ", optionally with another view of its camera: "
                   "living_room@yaw40 (turned in place), teapot@orbit90 (around the target), "
                   "kitchen@walk0.3+yaw180 (30%% of the way to the target, looking back)")
    p.add_argument("--accel", nargs="+", metavar="KEY",
                   help=f"{accel_help} or 'all' (default)")  # fmt: skip
    p.add_argument(
        "--traversal",
        nargs="+",
        metavar="KEY",
        help=f"traversal keys ({traversals}); default every traversal of the structure",
    )
    p.add_argument("--rays", default="primary,diffuse,shadow",
                   help="ray sets: primary,diffuse,shadow (default all)")  # fmt: skip
    p.add_argument("--threads", type=_threads,
                   help="thread counts, e.g. 1 or 1,2 (default all cores)")  # fmt: skip
    p.add_argument(
        "--peers",
        default="all",
        help="peer ray tracers on the same rays: embree,open3d,trimesh, all or none",
    )
    p.add_argument("--repeats", type=_positive_int, default=5, help="timed passes (default 5)")
    p.add_argument("--build-repeats", type=_positive_int, default=3,
                   help="timed builds (default 3)")  # fmt: skip
    _add_image_size(p)
    p.add_argument(
        "--validate",
        type=_nonnegative_int,
        default=200,
        help="rays checked against the oracle per system and ray set (0: off)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="PATH", help="append JSONL records here (atomically)")
    p.add_argument("--resume", action="store_true",
                   help="complete the --json file of an interrupted run of this command: "
                        "cells it holds are not measured again")  # fmt: skip
    p.add_argument("--markdown", action="store_true", help="print the table as markdown")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--option", action="append", metavar="K=V",
                   help="option passed to every builder")  # fmt: skip
    p.add_argument("--settle-ms", type=float, default=50.0,
                   help="pause (ms) before a pass on another thread pool than the pass "
                        "before, so its spinning threads are idle (default 50)")  # fmt: skip
    p.add_argument("--warmup-triangles", type=_positive_int, default=40_000,
                   help="size of the compile warm-up mesh (default 40000, enough to "
                        "reach the parallel build paths)")  # fmt: skip
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("sweep", parents=[common], help="the study: every structure x "
                       "traversal x ray set of a TOML configuration, resumable")  # fmt: skip
    p.add_argument("config", help="sweep configuration (TOML; see docs/study.md)")
    p.add_argument("-o", "--output", required=True,
                   help="results file (JSON lines), created or resumed")  # fmt: skip
    p.add_argument("--workers", type=int, default=0,
                   help="run on a local Dask cluster of this many processes (0: here)")  # fmt: skip
    p.add_argument("--scheduler", help="run on the Dask cluster at this address (tcp://HOST:PORT)")
    p.add_argument("--rays", help="folder for recorded ray sets (default <output>.rays)")
    p.set_defaults(func=cmd_sweep)

    p = sub.add_parser("report", parents=[common], help="the study's HTML report of a "
                       "sweep's results: tables, charts, optional heatmaps")  # fmt: skip
    p.add_argument("results", help="results file of a sweep (JSON lines)")
    p.add_argument("-o", "--output", required=True,
                   help="folder of the report (index.html and its PNG files)")  # fmt: skip
    p.add_argument("--heatmaps", action="store_true",
                   help="also draw each scene's heatmaps (builds and traces again)")  # fmt: skip
    p.set_defaults(func=cmd_report)

    p = sub.add_parser("cache", parents=[common], help="numba's cache of compiled kernels")
    p.add_argument("action", choices=("clear", "info", "warm"),
                   help="warm: compile every kernel ahead of its first call")  # fmt: skip
    p.add_argument("--structure", action="append",
                   help="warm only this structure's kernels (repeatable)")  # fmt: skip
    p.add_argument("--jobs", type=_positive_int, default=os.cpu_count() or 1,
                   help="worker processes for warm (default: one per core)")  # fmt: skip
    p.add_argument("--serial-only", action="store_true",
                   help="warm: skip the parallel kernels (batches of 4096 rays and more)")
    p.add_argument("--common-parallel", action="store_true",
                   help="warm: of the parallel kernels, only those plain queries reach (every "
                   "kernel of the default and fastest traversals, closest hits of the others)")
    p.add_argument("--quiet", action="store_true", help="warm: no line per job")
    p.set_defaults(func=cmd_cache)

    p = sub.add_parser("scenes", parents=[common], help="list the scenes; download the "
                       "standard benchmark scenes into the user cache")  # fmt: skip
    p.add_argument("action", choices=("list", "fetch"),
                   help="list: the scenes (--remote: the downloadable ones); fetch: download "
                        "NAME... once, checked against its known SHA-256")  # fmt: skip
    p.add_argument("names", nargs="*", metavar="NAME", help="fetch: downloadable scene names")
    p.add_argument(
        "--remote",
        action="store_true",
        help="list: the downloadable scenes, their licence, credit and cache state",
    )
    p.add_argument(
        "--no-verify",
        action="store_true",
        help="fetch: also download scenes without a published SHA-256, unchecked",
    )
    p.add_argument("--force", action="store_true", help="fetch: download again even if cached")
    p.add_argument("--progress", action="store_true", help="fetch: show a progress bar")
    p.add_argument("--json", action="store_true", help="list: print JSON")
    p.set_defaults(func=cmd_scenes)
    return parser


def _version() -> str:
    try:
        from rayaccel import __version__

        return __version__
    except Exception:  # pragma: no cover - a broken install still answers --version
        return "unknown"


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, OSError) and exc.filename and str(exc.filename) not in text:
        text = f"{exc.filename}: {text}"
    return text if isinstance(exc, RayAccelError) else f"{type(exc).__name__}: {text}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``rayaccel`` command line; return the exit status.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name; default ``sys.argv[1:]``.

    Returns
    -------
    int
        0 on success, 1 on an error, 2 on a usage error, 130 when interrupted.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    # numba falls back to another threading layer when the installed TBB is too old;
    # its warning says nothing a user of the CLI can act on
    warnings.filterwarnings("ignore", message="The TBB threading layer requires")
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as exit_:
            return int(exit_.code) if isinstance(exit_.code, int) else EXIT_USAGE
        debug = bool(getattr(args, "debug", False))
        return int(args.func(args))
    except KeyboardInterrupt:
        sys.stderr.write("rayaccel: interrupted\n")
        return EXIT_INTERRUPTED
    except Exception as exc:  # the one broad catch of the package (STYLE §7)
        if debug:
            traceback.print_exc()
        sys.stderr.write(f"rayaccel: error: {_one_line(exc)}\n")
        return EXIT_ERROR


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())


__all__ = ["build_parser", "main", "parse_options", "parse_value"]
