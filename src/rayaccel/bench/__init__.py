"""Benchmarks: the harness behind ``rayaccel bench``, peer adapters, ray sets, reports (layer 7).

* :mod:`rayaccel.bench.harness`: compile, validate, warm up, time (STYLE §11).
* :mod:`rayaccel.bench.raysets`: the primary, diffuse and shadow rays of a scene.
* :mod:`rayaccel.bench.peers`: Embree (embreex), Open3D and trimesh on the same rays.
* :mod:`rayaccel.bench.report`: atomic JSONL results, terminal and markdown tables.
"""

from __future__ import annotations

from rayaccel.bench.harness import BenchConfig, BenchResult, environment, run_bench
from rayaccel.bench.peers import PEERS, get_peer, parse_peers
from rayaccel.bench.raysets import RAY_KINDS, RaySet, parse_kinds, standard_raysets
from rayaccel.bench.report import JsonlWriter, markdown_table, read_jsonl, rich_table

__all__ = [
    "PEERS",
    "RAY_KINDS",
    "BenchConfig",
    "BenchResult",
    "JsonlWriter",
    "RaySet",
    "environment",
    "get_peer",
    "markdown_table",
    "parse_kinds",
    "parse_peers",
    "read_jsonl",
    "rich_table",
    "run_bench",
    "standard_raysets",
]
