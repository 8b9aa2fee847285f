"""A bounded fuzz run of every scene-file loader (the long run: benchmarks/fuzz_loaders.py).

Each target mutates valid seed files (or draws random bytes) with hypothesis and
checks the contract of :func:`~.fuzz_targets.check_input`: the file loads into a
valid mesh or is refused with a SceneFileError naming it, within the per-example
deadline and allocation budget. A few seconds per target; ``--full`` runs more.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from scene import fuzz_targets
from scene.fuzz_targets import TARGETS, check_input, scratch_folder, traced

EXAMPLES = 120


@pytest.fixture(scope="module")
def folder():
    with scratch_folder() as path:
        yield path


@pytest.mark.parametrize("name", list(TARGETS))
def test_loader_contract_under_fuzzing(name, folder, request):
    target = TARGETS[name]
    examples = EXAMPLES * (10 if request.config.getoption("--full") else 1)
    outcomes = {"loaded": 0, "refused": 0}

    @settings(
        max_examples=examples,
        deadline=None,  # check_input enforces its own per-example deadline (a SIGALRM watchdog)
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    @given(data=target.strategy)
    def run(data: bytes) -> None:
        outcomes[check_input(target, data, folder)] += 1

    with traced():
        run()
    # Both outcomes occur: the seeds load, and most mutations are refused.
    assert outcomes["loaded"] > 0
    assert outcomes["refused"] > 0


def test_check_input_flags_contract_breaches(folder, monkeypatch):
    """The oracle itself fails on a foreign exception, a hang and a huge allocation."""
    target = TARGETS["ply_binary"]
    seed = fuzz_targets.PLY_BINARY_SEEDS[0]

    def crash(path, **kwargs):
        raise IndexError("boom")

    monkeypatch.setattr(fuzz_targets, "load_mesh", crash)
    with pytest.raises(IndexError):
        check_input(target, seed, folder)

    def hang(path, **kwargs):
        while True:
            pass

    monkeypatch.setattr(fuzz_targets, "EXAMPLE_DEADLINE_S", 0.2)
    monkeypatch.setattr(fuzz_targets, "load_mesh", hang)
    with pytest.raises(fuzz_targets.ExampleHangError):
        check_input(target, seed, folder)

    def hog(path, **kwargs):
        block = np.ones(fuzz_targets.ALLOCATION_BUDGET // 8 + 1024)
        raise fuzz_targets.SceneFileError(f"{path}: {block.size}")

    monkeypatch.setattr(fuzz_targets, "EXAMPLE_DEADLINE_S", 30.0)
    monkeypatch.setattr(fuzz_targets, "load_mesh", hog)
    with traced(), pytest.raises(fuzz_targets.ExampleAllocationError):
        check_input(target, seed, folder)
