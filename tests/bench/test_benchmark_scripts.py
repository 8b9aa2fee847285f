"""Smoke runs of benchmark scripts whose figures docs/performance.md cites (tiny inputs)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import rayaccel

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_build_ready_times_the_default_queries_layouts(tmp_path: Path) -> None:
    bench_build = _script("bench_build")
    mesh_scene = "cornell-box"
    mesh = rayaccel.scenes.get(mesh_scene)
    queries = bench_build.default_queries(mesh, mesh_scene, "bvh2.binned_sah")
    # The default picks a packet traversal for coherent rays and a single-ray one for the rest.
    assert ("bvh2.packet", "closest") in queries
    assert ("bvh2.wide", "closest") in queries
    out = tmp_path / "build.jsonl"
    argv = [mesh_scene, "--ready", "--rounds", "1", "--peers", "--json", str(out)]
    assert bench_build.main(argv) == 0
    (record,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert record["system"] == "bvh2.binned_sah"
    assert record["ready"] is True
    assert record["build_ms"] > 0


def test_bench_memory_reports_rayaccel_bytes(capsys, monkeypatch) -> None:
    """One measuring child run in this process: growth and the layouts' bytes."""
    bench_memory = _script("bench_memory")
    monkeypatch.setattr(bench_memory, "SIZE", 16)
    argv = ["cornell-box", "--child", "rayaccel"]
    assert bench_memory.main(argv) == 0
    record = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert record["system"] == "rayaccel"
    assert record["n_tris"] > 0
    # The default queries derived their node rows over the packed layout's triangle rows.
    assert "bvh2.packed" in record["layouts"]
    assert {"bvh2.pairs", "bvh2.wide8"} & set(record["layouts"])
    assert record["info_bytes"] >= sum(record["layouts"].values())


def test_bound_irregular_map_replays_the_walks_cells(tmp_path: Path) -> None:
    """The recorded-cells walk returns the traversal's hits (checked inside) and is timed."""
    bound = _script("bound_irregular_map")
    out = tmp_path / "bound.jsonl"
    argv = ["--scenes", "cornell-box", "--rays", "primary", "--size", "16", "--repeats", "1",
            "--output", str(out)]  # fmt: skip
    assert bound.main(argv) == 0
    (record,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert record["rays"] == "primary"
    assert record["cells_per_ray"] > 0
    assert set(record["seconds"]) == {"map_walk", "known_cells_walk", "bvh2.stack"}
    assert all(s > 0 for s in record["seconds"].values())
