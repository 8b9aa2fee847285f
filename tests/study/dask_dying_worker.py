"""Run a sweep on a two-worker LocalCluster whose first counters cell kills its worker.

Run as a script by ``test_sweep.py`` (``python dask_dying_worker.py CONFIG RESULTS RAYS
MARKER``), so the Dask scheduler, client and their threads live in a process of their
own, not in the test process. Prints the sweep's summary as JSON.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import cloudpickle

from rayaccel.study import sweep as sweep_mod
from rayaccel.study.config import load_config


def dies_once(cell, config, mesh, rayset, accel=None, reference=None):
    """Kill the worker process the first time a counters cell runs (marker file)."""
    marker = Path(os.environ["RAYACCEL_TEST_MARKER"])
    if cell.kind == "counters" and not marker.exists():
        marker.write_text(cell.key)
        os._exit(1)
    from rayaccel.study.cells import run_cell

    return run_cell(cell, config, mesh, rayset, accel, reference)


def main() -> None:
    config, results, rays, marker = sys.argv[1:5]
    os.environ["RAYACCEL_TEST_MARKER"] = marker
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    sweep_mod.run_cell = dies_once
    summary = sweep_mod.sweep(load_config(config), results, workers=2, rays_folder=rays)
    print(json.dumps({"ran": summary.ran, "failed": summary.failed}))


if __name__ == "__main__":
    main()
