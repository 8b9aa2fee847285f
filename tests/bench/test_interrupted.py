"""``rayaccel bench`` killed at random moments keeps whole records and resumes to the full set.

Issue 20 (interrupted runs): the bench is started as a subprocess, killed with SIGINT or
SIGKILL after a random delay, many times in a row on one results file. After every kill
the file must parse (whole JSON lines only) and still hold every record it held before,
unchanged and in order; ``--resume`` runs then complete the set, each cell exactly once.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from rayaccel.bench import harness, report

TRAVERSALS = ("bvh2.stack", "bvh2.parent_link", "bvh2.bitstack")
KINDS = ("primary", "diffuse", "shadow")
COMMAND = [
    sys.executable, "-m", "rayaccel", "bench", "cornell-box", "--accel", "bvh2.binned_sah",
    "--traversal", ",".join(TRAVERSALS), "--rays", ",".join(KINDS), "--peers", "none",
    "--width", "16", "--height", "12", "--repeats", "2", "--build-repeats", "1",
    "--validate", "20", "--warmup-triangles", "64", "--threads", "1", "--no-progress",
]  # fmt: skip
#: The cells a complete run records: one per traversal and ray set.
EXPECTED = {("cornell-box", f"bvh2.binned_sah+{t}", 1, k) for t in TRAVERSALS for k in KINDS}


def _records(path):
    return report.read_jsonl(path) if path.exists() else []


def _cells(records):
    """The measurement cells of ``trace``/``invalid`` records, in file order."""
    return [harness.cell_key(r) for r in records if r.get("record") in ("trace", "invalid")]


def _run(path, timeout=600):
    return subprocess.run([*COMMAND, "--json", str(path), "--resume"], capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip


def test_kills_at_random_moments_lose_nothing_and_resume_completes(tmp_path, request):
    path = tmp_path / "bench.jsonl"
    # One whole run first: every kernel compiled (a cold cache would make early kills land
    # in compilation only) and the time a run takes, to aim the kills inside it.
    warm = tmp_path / "warm.jsonl"
    started = time.monotonic()
    first = _run(warm)
    assert first.returncode == 0, first.stderr[-2000:]
    span = time.monotonic() - started
    assert set(_cells(_records(warm))) == EXPECTED
    rng = np.random.default_rng(20)
    kills = 12 if request.config.getoption("--full") else 4
    for attempt in range(kills):
        before = _records(path)
        sig = signal.SIGINT if attempt % 2 == 0 else signal.SIGKILL
        process = subprocess.Popen([*COMMAND, "--json", str(path), "--resume"],
                                   stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)  # fmt: skip
        time.sleep(float(rng.uniform(0.2, 1.1)) * span)
        process.send_signal(sig)
        process.wait(timeout=120)
        after = _records(path)  # parses: whole JSON lines only
        assert after[: len(before)] == before, f"kill {attempt} ({sig.name}) changed records"
        keys = _cells(after)
        assert len(keys) == len(set(keys)), f"a cell measured twice after kill {attempt}"
        assert set(keys) <= EXPECTED
    final = _run(path)
    assert final.returncode == 0, final.stderr[-2000:]
    keys = _cells(_records(path))
    assert sorted(keys) == sorted(EXPECTED)
    # A resume of a finished file measures nothing more.
    again = _run(path)
    assert again.returncode == 0
    assert len(_cells(_records(path))) == len(EXPECTED)


def test_resume_needs_a_results_file():
    run = subprocess.run([*COMMAND, "--resume"], capture_output=True, text=True, timeout=300,
                         env={**os.environ})  # fmt: skip
    assert run.returncode != 0
    assert "--resume: needs --json" in run.stderr


@pytest.mark.parametrize("garbage", [b'{"record": "trace", "scene"', b"not json\n"])
def test_a_damaged_results_file_is_refused_untouched(tmp_path, garbage):
    path = tmp_path / "damaged.jsonl"
    path.write_bytes(b'{"record": "header"}\n' + garbage)
    run = _run(path, timeout=300)
    assert run.returncode != 0
    assert "not JSON" in run.stderr
    assert path.read_bytes() == b'{"record": "header"}\n' + garbage
