"""The sweep: configuration errors, cells, resuming after interruption, failures, Dask."""

from __future__ import annotations

import itertools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from rayaccel.scene import catalog
from rayaccel.study import cells as cells_mod
from rayaccel.study.cells import balance, enumerate_cells, homes
from rayaccel.study.config import ConfigError, parse_config
from rayaccel.study.raysets import scene_raysets
from rayaccel.study.results import ResultsFile, ResultsFormatError, read_results
from rayaccel.study.sweep import MAX_ATTEMPTS, sweep

TINY = """\
scenes = ["cornell-box"]
builders = ["bvh2.binned_sah", "grid.uniform"]
traversals = ["bvh2.stack", "grid.dda"]
threads = [1]
repeats = 1
build_repeats = 1
validate = 50

[rays]
kinds = ["primary", "shadow", "path"]
width = 16
height = 12

[rays.path]
spp = 1
max_depth = 1
"""


def _with(line: str) -> str:
    """TINY with one more top-level line (before its tables)."""
    return line + "\n" + TINY


def _by_key(records):
    out = {}
    for record in records:
        out.setdefault(record["key"], []).append(record)
    return out


@pytest.mark.parametrize(
    ("text", "line", "match"),
    [
        ('scenes = ["cornell-box"]\nbuilders = ["bvh2.binned_sah"]\nfoo = 1\n', 3, "unknown key"),
        ('scenes = ["cornel-box"]\nbuilders = ["bvh2.binned_sah"]\n', 1, "unknown scene"),
        ('scenes = ["teapot"]\n\nbuilders = ["bvh2.binned_sha"]\n', 3, "unknown builder"),
        ('scenes = ["teapot"]\nbuilders = ["bvh2.lbvh+reinsrt"]\n', 2, "unknown build step"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\ntraversals = ["bvh2.stack"]\n', 2,
         "no listed traversal"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\ntraversals = ["grid.dd"]\n', 3,
         "unknown traversal"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\nthreads = [0]\n', 3, "threads"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\npeers = ["embre"]\n', 3,
         "unknown peer"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\n[rays]\nkinds = ["diffus"]\n', 4,
         "unknown kind"),
        ('scenes = ["teapot"]\nbuilders = ["grid.uniform"]\npasses = ["time"]\n', 3,
         "unknown pass"),
        ('scenes = ["teapot"]\nbuilders = [\n  {key = "bvh2.lbvh", max_leaf = 2},\n]\n', 3,
         "unknown option 'max_leaf'"),
        ('scenes = ["teapot"]\nbuilders = ["bvh2.lbvh"]\n'
         'traversals = [{key = "bvh2.restart_trail", short = 3}]\n', 3, "unknown option"),
        ('scenes = ["teapot"]\nbuilders = [{max_leaf_size = 2}]\n', 2, "table with a 'key'"),
    ],
)
def test_config_errors_name_the_line(text, line, match):
    with pytest.raises(ConfigError, match=match) as caught:
        parse_config(text, "sweep.toml")
    assert f"sweep.toml:{line}:" in str(caught.value)


def test_config_syntax_error_and_required_keys():
    with pytest.raises(ConfigError, match=r"sweep\.toml"):
        parse_config("scenes = [\n", "sweep.toml")
    with pytest.raises(ConfigError, match="required"):
        parse_config('scenes = ["teapot"]\n', "sweep.toml")


def test_cells_and_their_keys():
    config = parse_config(TINY)
    cells = enumerate_cells(config)
    sets = config.rays.set_names()
    assert sets == ["primary", "shadow", "path-primary", "path-bounce", "path-shadow"]
    kinds = [c.kind for c in cells]
    assert kinds.count("build") == 2
    assert kinds.count("counters") == kinds.count("timing") == 2 * len(sets)
    assert len({c.key for c in cells}) == len(cells)
    assert [c.key for c in enumerate_cells(parse_config(TINY))] == [c.key for c in cells]
    wider = parse_config(TINY.replace("width = 16", "width = 20"))
    assert not {c.key for c in enumerate_cells(wider)} & {c.key for c in cells if c.rayset}
    only = parse_config(_with('passes = ["counters"]'))
    assert {c.kind for c in enumerate_cells(only)} == {"counters"}
    assert all(not c.exclusive for c in enumerate_cells(only))


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """One complete tiny sweep, run in this process."""
    folder = tmp_path_factory.mktemp("sweep")
    results = folder / "results.jsonl"
    summary = sweep(parse_config(TINY), results)
    return results, summary


def test_local_sweep_records_every_cell(finished):
    results, summary = finished
    header, records = read_results(results)
    config = parse_config(TINY)
    expected = {c.key for c in enumerate_cells(config)}
    assert {r["key"] for r in records} == expected
    assert summary.ran == len(expected)
    assert summary.failed == 0
    assert summary.skipped == 0
    assert all(r["status"] == "ok" for r in records)
    assert header["config"]["rays"]["width"] == 16
    for record in records:
        if record["kind"] == "counters":
            assert record["mismatches"] == 0
            assert record["validated"] > 0 or record["n_rays"] == 0
            assert record["nodes_per_ray"] is None or record["nodes_per_ray"] >= 0
        elif record["kind"] == "timing":
            assert record["mrays_median"] > 0 or record["n_rays"] == 0
        else:
            assert record["build_ms_median"] > 0
            assert record["bytes"] > 0
    # The recorded path sets were written beside the results, with the scene's digest.
    manifest = json.loads((results.with_suffix(".rays") / "cornell-box" / "rays.json").read_text())
    assert manifest["spp"] == 1
    assert manifest["camera"]["width"] == 16
    # The accounting holds (the cells' and ray sets' time lies within the wall time); how
    # large the overhead is is measured by benchmarks/bench_sweep.py, not asserted here: a
    # loaded CI machine pushed it past the 0.5 this test once asserted.
    assert summary.cell_seconds + summary.rays_seconds <= summary.wall_seconds * 1.01
    assert summary.overhead >= -0.01


def test_resume_skips_finished_cells_and_cuts_a_torn_line(finished, tmp_path):
    results, _ = finished
    lines = results.read_bytes().splitlines(keepends=True)
    copy = tmp_path / "results.jsonl"
    keep = 7
    copy.write_bytes(b"".join(lines[: 1 + keep]) + lines[1 + keep][:25])  # a torn line
    summary = sweep(parse_config(TINY), copy, rays_folder=results.with_suffix(".rays"))
    assert summary.skipped == keep
    assert summary.ran == len(lines) - 1 - keep
    _, records = read_results(copy)
    counts = _by_key(records)
    assert all(len(v) == 1 for v in counts.values())
    assert len(counts) == len(lines) - 1
    assert all(line.endswith(b"\n") for line in copy.read_bytes().splitlines(keepends=True))
    again = sweep(parse_config(TINY), copy, rays_folder=results.with_suffix(".rays"))
    assert again.ran == 0
    assert again.skipped == len(counts)


def test_sigkill_mid_sweep_loses_no_finished_cell(finished, tmp_path):
    """A sweep killed with SIGKILL resumes where it stopped."""
    results, _ = finished
    config = tmp_path / "tiny.toml"
    config.write_text(TINY)
    out = tmp_path / "killed.jsonl"
    command = [sys.executable, "-m", "rayaccel", "sweep", str(config), "-o", str(out),
               "--rays", str(results.with_suffix(".rays"))]
    process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 600  # a cold numba cache on a loaded machine is slow
        while time.monotonic() < deadline:
            if out.exists() and out.read_bytes().count(b"\n") >= 4:
                break
            time.sleep(0.05)
        process.send_signal(signal.SIGKILL)
    finally:
        process.wait(timeout=30)
    _, before = read_results(out)
    assert 3 <= len(before) < len(enumerate_cells(parse_config(TINY)))
    summary = sweep(parse_config(TINY), out, rays_folder=results.with_suffix(".rays"))
    assert summary.skipped == len(before)
    _, records = read_results(out)
    assert all(len(v) == 1 for v in _by_key(records).values())
    assert {r["key"] for r in records} == {c.key for c in enumerate_cells(parse_config(TINY))}


def test_results_of_another_format_are_refused_untouched(tmp_path):
    path = tmp_path / "old.jsonl"
    path.write_text('{"record": "header", "format": "rayaccel-sweep/0", "rayaccel": "0.0"}\n')
    before = path.read_bytes()
    with pytest.raises(ResultsFormatError, match="rayaccel-sweep/0"):
        sweep(parse_config(TINY), path)
    assert path.read_bytes() == before
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"record": "header", "format": "rayaccel-sweep/1"}\nnot json\n{"a": 1}\n')
    with pytest.raises(ResultsFormatError, match=":2:"):
        read_results(bad)
    headless = tmp_path / "headless.jsonl"
    headless.write_text('{"key": "k"}\n')
    with pytest.raises(ResultsFormatError, match="no sweep header"):
        ResultsFile(headless, {})


def test_a_failing_cell_is_tried_three_times_then_recorded(finished, tmp_path, monkeypatch):
    results, _ = finished
    calls = []

    def broken(cell, config, mesh, rayset):
        calls.append(cell.key)
        raise RuntimeError("no <luck> here")

    monkeypatch.setattr(cells_mod, "_counters", broken)
    config = parse_config(_with('passes = ["counters"]'))
    out = tmp_path / "failing.jsonl"
    summary = sweep(config, out, rays_folder=results.with_suffix(".rays"))
    n = len(enumerate_cells(config))
    assert summary.failed == n
    assert len(calls) == MAX_ATTEMPTS * n
    _, records = read_results(out)
    assert all(r["status"] == "failed" and r["attempts"] == MAX_ATTEMPTS for r in records)
    assert "no <luck> here" in records[0]["error"]
    monkeypatch.undo()
    again = sweep(config, out, rays_folder=results.with_suffix(".rays"))
    assert again.ran == 0  # given up for good


def test_structure_homes_turn_from_scene_to_scene():
    """The heaviest group alone on one worker, the rest on the other; the next scene swaps."""
    groups = {"bvh2.binned_sah": 28, "kdtree.sah": 20, "grid.uniform": 12}
    first = homes(groups, 2, 0)
    assert first == {"bvh2.binned_sah": 0, "kdtree.sah": 1, "grid.uniform": 1}
    assert homes(groups, 2, 1) == {b: 1 - w for b, w in first.items()}
    assert homes(groups, 2, 2) == first
    assert set(homes(groups, 1, 5).values()) == {0}


def test_balance_keeps_the_groups_already_placed():
    """The sweep places each (builder, traversal)'s counter cells once for the whole sweep
    (so no kernel is loaded on two workers): groups already placed keep their bin and
    count toward its load, new ones go to the lightest bin."""
    groups = {("bvh", "stack"): 8, ("bvh", "wide"): 8, ("kd", "stack"): 6, ("grid", "dda"): 4}
    first = balance(groups, 2)
    assert first == {("bvh", "stack"): 0, ("bvh", "wide"): 1, ("kd", "stack"): 0,
                     ("grid", "dda"): 1}  # fmt: skip
    later = balance({**groups, ("kd", "ropes"): 5}, 2, first)
    assert {g: later[g] for g in groups} == first
    assert later[("kd", "ropes")] == 1  # bin 0 held 14, bin 1 held 12
    assert set(balance(groups, 1, first).values()) == {0}


def test_a_counter_cell_uses_the_structure_and_answers_it_is_handed(finished, monkeypatch):
    """On Dask a counter cell receives its structure from a build task and its ray set's
    oracle answers from a task of their own: nothing is built or answered again."""
    results, _ = finished
    config = parse_config(_with('passes = ["counters"]'))
    cell = enumerate_cells(config)[0]
    mesh = catalog.get(cell.scene)
    rayset = scene_raysets(mesh, cell.scene, config.rays, results.with_suffix(".rays"))[cell.rayset]
    handed = cells_mod.counter_structure(config, mesh, cell.builder)
    answers = cells_mod.counter_reference(config, mesh, rayset)
    monkeypatch.setattr(cells_mod, "_ACCELS", {})
    monkeypatch.setattr(cells_mod, "_REFERENCES", {})

    def no_build(*args, **kwargs):
        raise AssertionError("built again")

    def no_oracle(*args, **kwargs):
        raise AssertionError("answered again")

    monkeypatch.setattr(cells_mod, "_build_once", no_build)
    monkeypatch.setattr(cells_mod, "reference_hits", no_oracle)
    record = cells_mod.run_cell(cell, config, mesh, rayset, handed, answers)
    assert record["status"] == "ok", record.get("error")
    assert record["validated"] > 0
    assert record["mismatches"] == 0
    assert cells_mod._ACCELS[(mesh.digest(), cell.builder)] is handed


def test_dask_local_cluster_runs_every_cell_once_and_survives_a_dead_worker(finished, tmp_path):
    """A LocalCluster of two workers, one of which dies in its first counters cell.

    The sweep runs in a subprocess (``dask_dying_worker.py``), so the Dask scheduler
    and client threads never live in the test process. The scheduler's active memory
    manager runs every 20 ms there: it drops the replicas of scattered inputs that it sees
    no use for, so the dead worker may have held the only copy of a mesh or ray set
    (which cannot be recomputed: its cells are cancelled for "lost dependencies" and the
    sweep must scatter it again).
    """
    results, _ = finished
    config_path = tmp_path / "tiny.toml"
    config_path.write_text(TINY)
    marker = tmp_path / "died"
    out = tmp_path / "dask.jsonl"
    script = Path(__file__).with_name("dask_dying_worker.py")
    done = subprocess.run(
        [sys.executable, str(script), str(config_path), str(out),
         str(results.with_suffix(".rays")), str(marker)],
        capture_output=True, text=True, timeout=600, check=False,
        env={**os.environ, "DASK_DISTRIBUTED__SCHEDULER__ACTIVE_MEMORY_MANAGER__INTERVAL": "20ms"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    summary = json.loads(done.stdout.strip().splitlines()[-1])
    assert marker.exists()  # a worker died mid-cell
    config = parse_config(TINY)
    _, records = read_results(out)
    assert summary["failed"] == 0
    assert {r["key"] for r in records} == {c.key for c in enumerate_cells(config)}
    assert all(len(v) == 1 for v in _by_key(records).values())
    assert all(r["status"] == "ok" for r in records)
    # No two timed cells of one host overlapped.
    timed = sorted((r["started"], r["started"] + r["seconds"]) for r in records
                   if r["kind"] != "counters")  # fmt: skip
    for (_, end), (start, _) in itertools.pairwise(timed):
        assert start >= end - 1e-3


def test_builders_and_traversals_with_options(tmp_path):
    """Options reach the builder and the traversal; each variant is its own labelled cell."""
    text = """\
scenes = ["cornell-box"]
builders = [{key = "bvh2.binned_sah", max_leaf_size = 1}]
traversals = ["bvh2.restart_trail", {key = "bvh2.restart_trail", short_stack = 3}]
threads = [1]
build_repeats = 1
validate = 50
passes = ["build", "counters"]

[rays]
kinds = ["primary"]
width = 16
height = 12
"""
    config = parse_config(text)
    builder = "bvh2.binned_sah[max_leaf_size=1]"
    assert config.builders == (builder,)
    assert config.traversals[builder] == (
        "bvh2.restart_trail", "bvh2.restart_trail[short_stack=3]",
    )
    assert config.variant(builder) == ("bvh2.binned_sah", {"max_leaf_size": 1})
    sweep(config, tmp_path / "results.jsonl")
    _, records = read_results(tmp_path / "results.jsonl")
    assert all(r["status"] == "ok" for r in records)
    (build,) = [r for r in records if r["kind"] == "build"]
    assert build["builder"] == builder
    assert build["info"]["mean_leaf_size"] == 1.0
    nodes = {r["traversal"]: r["nodes_per_ray"] for r in records if r["kind"] == "counters"}
    assert all(r["mismatches"] == 0 for r in records if r["kind"] == "counters")
    # A 3-entry short stack saves restarts from the root: fewer nodes per ray
    assert nodes["bvh2.restart_trail[short_stack=3]"] < nodes["bvh2.restart_trail"]
