"""Fuzz the scene-file loaders for a given time (the long run of the CI fuzz tests).

Runs the same targets and oracle (``tests/scene/fuzz_targets.py``: OBJ, PLY
ASCII, PLY binary, STL ASCII, STL binary, gzip, GLB) with many more examples. Each
target gets an equal share of the time, in rounds of ``--round`` hypothesis
examples with a fresh random seed each, taken in turn so an interrupted run is
still balanced. A contract breach (an exception other than SceneFileError, a
refusal not naming the file, an invalid mesh, an example past the per-example
deadline, or a peak allocation past the budget) is shrunk by hypothesis, counted
as a crash, and its minimal input saved to ``--crash-dir``::

    nice -n 19 python benchmarks/fuzz_loaders.py --minutes 60
    python benchmarks/fuzz_loaders.py --cpu-minutes 60   # one CPU-hour, however loaded

Prints, per target, the examples run, how many loaded and were refused, the
crashes found and the time spent, and writes them as JSON to ``--out``; SIGINT or
SIGTERM end the run early with the same report.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import sys
import time
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, Phase, given, seed, settings

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from scene.fuzz_targets import (  # noqa: E402 - needs the tests folder on the path
    TARGETS,
    Target,
    check_input,
    scratch_folder,
    traced,
)


def fuzz_round(
    target: Target, examples: int, round_seed: int, folder: Path, counts: dict[str, Any]
) -> dict[str, Any] | None:
    """Run one hypothesis round of ``examples`` inputs, counting into ``counts`` as it goes.

    Returns the crash (seed, error, shrunk input) if the round found one, else ``None``.
    """
    failing: list[bytes] = []

    @seed(round_seed)
    @settings(
        max_examples=examples,
        deadline=None,  # check_input enforces the per-example deadline itself
        database=None,
        phases=[Phase.generate, Phase.shrink],
        suppress_health_check=list(HealthCheck),
    )
    @given(data=target.strategy)
    def run(data: bytes) -> None:
        counts["examples"] += 1
        try:
            counts[check_input(target, data, folder)] += 1
        except BaseException:
            failing.append(data)  # the last one is hypothesis's shrunk example
            raise

    crash = None
    try:
        run()
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # any breach of the contract is a crash to report
        crash = {
            "seed": round_seed,
            "error": f"{type(exc).__name__}: {exc}"[:2000],
            "input": failing[-1] if failing else b"",
        }
    return crash


def main(argv: list[str] | None = None) -> int:
    """Parse the arguments, fuzz every chosen target for its share of time, report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=5.0, help="total wall-clock budget")
    parser.add_argument(
        "--cpu-minutes",
        type=float,
        default=None,
        help="share the time by CPU time instead (a loaded machine still gets the full budget)",
    )
    parser.add_argument("--targets", nargs="+", choices=list(TARGETS), default=list(TARGETS))
    parser.add_argument("--round", type=int, default=1000, help="examples per hypothesis round")
    parser.add_argument("--seed", type=int, default=None, help="seed of the round seeds")
    parser.add_argument("--crash-dir", type=Path, default=Path("fuzz-crashes"))
    parser.add_argument("--out", type=Path, default=None, help="write the summary as JSON here")
    args = parser.parse_args(argv)
    # SIGTERM (and SIGINT, which a shell may ignore in background jobs) stop the run and
    # report what ran.
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    signal.signal(signal.SIGINT, signal.default_int_handler)

    master = random.Random(args.seed)
    # The budget is wall time, or CPU time with --cpu-minutes: on a shared machine a wall
    # budget buys less fuzzing than it says.
    clock = "seconds" if args.cpu_minutes is None else "cpu"
    budget = args.minutes if args.cpu_minutes is None else args.cpu_minutes
    share = budget * 60.0 / len(args.targets)
    totals = {
        name: {"examples": 0, "loaded": 0, "refused": 0, "crashes": 0, "seconds": 0.0, "cpu": 0.0}
        for name in args.targets
    }
    crashes: list[dict[str, Any]] = []
    start = time.monotonic()
    with scratch_folder() as folder, traced():
        try:
            while True:
                pending = [n for n in args.targets if totals[n][clock] < share]
                if not pending:
                    break
                for name in pending:
                    round_seed = master.getrandbits(32)
                    wall, cpu = time.monotonic(), time.process_time()
                    total = totals[name]
                    try:
                        found = fuzz_round(TARGETS[name], args.round, round_seed, folder, total)
                    finally:
                        total["seconds"] += time.monotonic() - wall
                        total["cpu"] += time.process_time() - cpu
                    if found is not None:
                        total["crashes"] += 1
                        crash = {"target": name, **found}
                        args.crash_dir.mkdir(parents=True, exist_ok=True)
                        saved = args.crash_dir / f"{name}-{round_seed}{TARGETS[name].suffix}"
                        saved.write_bytes(crash.pop("input"))
                        crash["file"] = str(saved)
                        crashes.append(crash)
                        print(f"CRASH {name} (seed {round_seed}): {crash['error'][:300]}")
                        print(f"      input saved to {saved}")
                    print(
                        f"{name:<11} {total['examples']:>9} examples  {total['crashes']} crashes  "
                        f"{total['seconds']:7.1f} s",
                        flush=True,
                    )
        except KeyboardInterrupt:
            print("interrupted; reporting what ran")
    elapsed = time.monotonic() - start

    print(
        f"\n{'target':<11} {'examples':>9} {'loaded':>8} {'refused':>9} {'crashes':>8} {'CPU s':>8}"
    )
    for name, total in totals.items():
        print(
            f"{name:<11} {total['examples']:>9} {total['loaded']:>8} {total['refused']:>9} "
            f"{total['crashes']:>8} {total['cpu']:>8.1f}"
        )
    examples = sum(t["examples"] for t in totals.values())
    cpu = sum(t["cpu"] for t in totals.values())
    n_crashes = sum(t["crashes"] for t in totals.values())
    print(
        f"{'all':<11} {examples:>9} {'':>8} {'':>9} {n_crashes:>8} {cpu:>8.1f}"
        f"   ({elapsed / 60:.1f} wall minutes, {cpu / 60:.1f} CPU minutes)"
    )
    if args.out is not None:
        summary = {
            "command": " ".join(sys.argv),
            "wall_seconds": elapsed,
            "cpu_seconds": cpu,
            "examples": examples,
            "crashes": n_crashes,
            "targets": totals,
            "crash_reports": crashes,
        }
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(summary, indent=2) + "\n")
    return 1 if n_crashes else 0


if __name__ == "__main__":
    raise SystemExit(main())
