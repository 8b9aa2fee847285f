import json
import subprocess
import sys

import numba
import pytest
from PIL import Image

from rayaccel import precompile, registry
from rayaccel.cli import build_parser, main, parse_options
from rayaccel.counters import COUNTER_NAMES
from rayaccel.errors import InvalidInputError


def run(capsys, *args):
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_list_names_every_registered_variant_and_counter(capsys):
    code, out, _ = run(capsys, "list")
    assert code == 0
    for key in registry.keys("builder") + registry.keys("step") + registry.keys("traversal"):
        assert key in out
    for variant in registry.variants():
        assert variant.summary in out
        if variant.reference:
            assert variant.reference in out
    for name in COUNTER_NAMES:
        assert name in out


def test_list_json(capsys):
    code, out, _ = run(capsys, "list", "--json")
    assert code == 0
    data = json.loads(out)
    assert [v["key"] for v in data["builder"]] == registry.keys("builder")
    assert [v["key"] for v in data["traversal"]] == registry.keys("traversal")
    assert [v["key"] for v in data["step"]] == registry.keys("step")
    assert data["counters"] == list(COUNTER_NAMES)
    assert "cornell-box" in data["scenes"]


def test_info_json(capsys):
    code, out, _ = run(capsys, "info", "cornell-box", "--option", "max_leaf_size=2", "--json")
    assert code == 0
    data = json.loads(out)
    assert data["mesh"]["n_triangles"] == 32
    assert data["accel"]["builder"] == "bvh2.binned_sah"
    assert data["accel"]["options"]["max_leaf_size"] == 2


@pytest.mark.parametrize("view", ["shade", "heatmap"])
def test_render_writes_png_of_the_right_size(capsys, tmp_path, view):
    out = tmp_path / f"{view}.png"
    args = ["render", "cornell-box", "--view", view, "-o", str(out), "--width", "20",
            "--height", "12"]  # fmt: skip
    if view == "heatmap":
        args += ["--metric", "box_tests", "--legend", str(tmp_path / "legend.png")]
    else:
        args += ["--ao", "2"]
    code, _, err = run(capsys, *args)
    assert code == 0, err
    with Image.open(out) as image:
        assert image.format == "PNG"
        assert image.size == (20, 12)
    if view == "heatmap":
        with Image.open(tmp_path / "legend.png") as legend:
            assert legend.format == "PNG"


def test_render_several_structures_on_one_scale(capsys, tmp_path):
    out = tmp_path / "cmp.png"
    code, stdout, err = run(capsys, "render", "cornell-box", "--view", "heatmap", "--accel",
                            "all", "-o", str(out), "--width", "8", "--height", "8")  # fmt: skip
    assert code == 0, err
    for key in registry.keys("builder"):
        assert (tmp_path / f"cmp-{key}.png").exists()
    assert stdout.count("scale:") == 1


def test_bad_scene_is_one_line_and_exit_1(capsys, tmp_path):
    code, _out, err = run(capsys, "render", "no-such-scene", "-o", str(tmp_path / "x.png"))
    assert code == 1
    assert err.startswith("rayaccel: error: unknown scene 'no-such-scene'")
    assert err.count("\n") == 1
    assert "Traceback" not in err
    code, _, err = run(capsys, "--debug", "info", "no-such-scene")
    assert code == 1
    assert "Traceback" in err


def test_unknown_variant_suggests(capsys):
    code, _, err = run(capsys, "info", "cornell-box", "--accel", "bvh2.binned")
    assert code == 1
    assert "did you mean bvh2.binned_sah" in err


def test_usage_errors_exit_2(capsys):
    assert run(capsys, "frobnicate")[0] == 2
    assert run(capsys, "render", "cornell-box")[0] == 2  # no -o
    assert run(capsys, "bench", "cornell-box", "--threads", "0")[0] == 2


def test_every_command_prints_its_help(capsys):
    """argparse %-formats help strings: a stray ``%`` made ``bench --help`` crash."""
    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    assert "bench" in commands
    for command in [None, *commands]:
        args = ["--help"] if command is None else [command, "--help"]
        code, out, err = run(capsys, *args)
        assert (code, err) == (0, ""), command
        assert out.startswith("usage: rayaccel"), command


def test_parse_options():
    assert parse_options(["n_bins=16", "a=1.5,b=true", "c=name"]) == {
        "n_bins": 16, "a": 1.5, "b": True, "c": "name",
    }  # fmt: skip
    with pytest.raises(InvalidInputError):
        parse_options(["novalue"])


def test_cache_clear_removes_only_numba_files(capsys, tmp_path, monkeypatch):
    monkeypatch.setattr(numba.config, "CACHE_DIR", str(tmp_path))
    (tmp_path / "sub").mkdir()
    for name in ("a.nbi", "a.1.nbc", "sub/b.nbi", "keep.py"):
        (tmp_path / name).write_text("x")
    code, out, _ = run(capsys, "cache", "info")
    assert code == 0
    assert out.startswith("3 cache files")
    code, out, _ = run(capsys, "cache", "clear")
    assert code == 0
    assert "removed 3" in out
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["keep.py"]


def test_cache_warm_runs_each_job_and_names_bad_structures(capsys):
    code, out, _ = run(capsys, "cache", "warm", "--structure", "grid", "--serial-only",
                       "--jobs", "1")
    assert code == 0
    n_jobs = len(precompile.jobs(["grid"], parallel=False))
    assert f"compiling {n_jobs} kernel groups" in out
    assert f"[{n_jobs}/{n_jobs}]" in out
    assert "grid.dda any+stats serial" in out
    code, out, _ = run(capsys, "cache", "warm", "--structure", "grid", "--common-parallel",
                       "--jobs", "1", "--quiet")
    assert code == 0
    common = precompile.jobs(["grid"], variant_filter=precompile.common_parallel)
    assert len(common) < len(precompile.jobs(["grid"]))
    assert f"compiling {len(common)} kernel groups" in out
    code, _, err = run(capsys, "cache", "warm", "--structure", "octree")
    assert code == 1
    assert "octree" in err
    assert "grid" in err


def test_python_dash_m():
    result = subprocess.run([sys.executable, "-m", "rayaccel", "--version"],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0
    assert result.stdout.startswith("rayaccel ")
