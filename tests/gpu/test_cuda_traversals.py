"""The CUDA traversals return the CPU kernels' hits, ray for ray (issue: GPU traversal kernels).

Under numba's CUDA simulator (the default in tests: ``tests/conftest.py`` sets
``NUMBA_ENABLE_CUDASIM=1`` unless ``RAYACCEL_CUDA_TESTS=gpu``) every kernel runs its
per-ray body as Python, on a small scene and a few dozen rays. With
``RAYACCEL_CUDA_TESTS=gpu`` on a machine with a GPU the same tests run the compiled
kernels. ``test_compiles_for_the_gpu`` compiles every kernel to PTX for a Hopper GPU
with NVVM alone, so the real target's typing and lowering are checked without a GPU.

What "the same hits" means: the same hit mask on every ray and the same primitive
(except a near-tie, re-checked against the oracle), ``t`` within a few float32 ulps and
barycentrics within 1e-6: the GPU's compiler fuses multiply-adds where the CPU's does not
(the simulator evaluates without fusing at all), which moves the last bits of ``t``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tests.gpu import ptx_check
from tests.reference import mixed_rays

import rayaccel as ra
from rayaccel.cuda import device as cuda_device
from rayaccel.errors import InvalidInputError
from rayaccel.scene import procedural

cuda = pytest.importorskip("numba.cuda", reason="numba-cuda is part of the test extra")
ON_GPU = os.environ.get("RAYACCEL_CUDA_TESTS") == "gpu"

CASES = ptx_check.CASES
N_RAYS = 48 if not ON_GPU else 4000


@pytest.fixture(scope="module")
def mesh():
    return procedural.cornell_box()


@pytest.fixture(scope="module")
def rays(mesh):
    return mixed_rays(mesh, N_RAYS, seed=3)


@pytest.fixture(scope="module")
def accels(mesh):
    return {}


def _accel(accels, mesh, builder):
    if builder not in accels:
        accels[builder] = ra.build(mesh, builder)
    return accels[builder]


def t_tolerance(mesh, rays) -> np.ndarray:
    """Per-ray bound on how far a fused multiply-add may move ``t``.

    The watertight test's ``t`` is a sum of products of corner coordinates relative to
    the origin, so its rounding error scales with the corners' distance from the origin
    (in units of the direction's length), not with ``t``: 16 float32 ulps of that.
    """
    lo, hi = (np.asarray(b, dtype=np.float64) for b in mesh.bounds())
    reach = np.linalg.norm(rays.origin - 0.5 * (lo + hi), axis=1) + np.linalg.norm(hi - lo)
    return 2.0**-19 * reach / np.linalg.norm(rays.direction.astype(np.float64), axis=1)


def assert_same_hits(cpu, gpu, tolerance, label: str) -> None:
    """The GPU's hits against the CPU kernel's (see the module docstring)."""
    hit = cpu.prim >= 0
    assert np.array_equal(hit, gpu.prim >= 0), f"hit mask differs [{label}]"
    assert np.all(np.isposinf(gpu.t[~hit]))
    assert np.all(gpu.prim[~hit] == -1)
    # Where the primitive differs it is a near-tie: the other triangle at (almost) the
    # same distance.
    gap = np.where(hit, np.abs(cpu.t.astype(np.float64) - np.where(hit, gpu.t, 0)), 0.0)
    far = np.flatnonzero(gap > tolerance)
    assert far.size == 0, (
        f"{far.size} rays: t differs beyond the rounding bound [{label}]; first ray {far[0]}: "
        f"cpu t={cpu.t[far[0]]!r} prim={cpu.prim[far[0]]}, gpu t={gpu.t[far[0]]!r} "
        f"prim={gpu.prim[far[0]]}, bound {tolerance[far[0]]:.3g}"
    )
    same = cpu.prim == gpu.prim
    assert np.allclose(cpu.u[same], gpu.u[same], atol=1e-5, rtol=0), f"u differs [{label}]"
    assert np.allclose(cpu.v[same], gpu.v[same], atol=1e-5, rtol=0), f"v differs [{label}]"


@pytest.mark.parametrize(("builder", "traversal"), CASES, ids=[f"{b}-{t}" for b, t in CASES])
def test_closest_any_and_stats_match_the_cpu(mesh, rays, accels, builder, traversal):
    accel = _accel(accels, mesh, builder)
    label = f"{builder} {traversal}"
    closest_cpu = accel.trace(rays, traversal=traversal, stats=True)
    closest_gpu = accel.trace(rays, traversal=traversal, device="cuda")
    assert_same_hits(closest_cpu, closest_gpu, t_tolerance(mesh, rays), label)
    any_gpu = accel.trace(rays, traversal=traversal, query="any", device="cuda")
    assert np.array_equal(any_gpu.prim >= 0, closest_cpu.prim >= 0), f"any-hit mask [{label}]"
    # Statistics on the device: the same hits as the plain kernel, and the CPU's counters.
    counted = accel.trace(rays, traversal=traversal, stats=True, device="cuda")
    for name in ("t", "prim", "u", "v"):
        assert getattr(counted, name).tobytes() == getattr(closest_gpu, name).tobytes()
    agree = np.ones(rays.n_rays, dtype=bool)
    for name, column in closest_cpu.stats.items():
        agree &= counted.stats[name] == column
    # A t moved by a fused multiply-add can cull one box differently; nothing else may differ.
    exact_t = closest_cpu.t.view(np.int32) == closest_gpu.t.view(np.int32)
    assert np.all(agree[exact_t]), f"counters differ on rays with identical hits [{label}]"
    assert counted.stats["nodes"].sum() + counted.stats["cells"].sum() > 0


def test_device_arrays_in_and_out(mesh, rays, accels):
    accel = _accel(accels, mesh, "bvh2.binned_sah").to_device()
    memo = accel._cache["cuda.arrays"]
    held = {key: device for key, (_, device) in memo.items()}
    assert held, "to_device() copied nothing"
    origins = cuda.to_device(rays.origin)
    directions = cuda.to_device(rays.direction)
    tmax = cuda.to_device(rays.tmax)
    hits = accel.intersect(origins, directions, rays.tmin, tmax, device="cuda")
    assert cuda_device.is_device_array(hits.t)
    assert cuda_device.is_device_array(hits.prim)
    host = accel.intersect(rays.origin, rays.direction, rays.tmin, rays.tmax, device="cuda")
    assert isinstance(host.t, np.ndarray)
    for name in ("t", "prim", "u", "v"):
        assert np.array_equal(getattr(hits, name).copy_to_host(), getattr(host, name))
    blocked = accel.occluded(origins, directions, rays.tmin, tmax, device="cuda")
    assert cuda_device.is_device_array(blocked)
    assert np.array_equal(blocked.copy_to_host(), host.prim >= 0)
    # Nothing was copied again: the layout stayed on the device between queries.
    assert all(memo[key][1] is device for key, device in held.items())
    counted = accel.intersect(origins, directions, device="cuda", stats=True)
    assert cuda_device.is_device_array(counted.stats["nodes"])


def test_refit_drops_the_device_copies(mesh, accels):
    accel = ra.build(mesh, "bvh2.binned_sah").to_device()
    assert accel._cache.get("cuda.arrays")
    accel.refit(mesh.vertices * 1.5)
    assert not accel._cache.get("cuda.arrays")
    o = np.array([[0.0, 0.0, -100.0]], np.float32)
    d = np.array([[0.0, 0.0, 1.0]], np.float32)
    assert np.array_equal(accel.intersect(o, d, device="cuda").t, accel.intersect(o, d).t)


def test_bad_requests_fail_clearly(mesh, rays, accels):
    accel = _accel(accels, mesh, "bvh2.binned_sah")
    with pytest.raises(InvalidInputError, match="no CUDA kernel"):
        accel.trace(rays, traversal="bvh2.wide", device="cuda")
    with pytest.raises(InvalidInputError, match="device"):
        accel.trace(rays, device="gpu")
    with pytest.raises(InvalidInputError, match="short_stack must be at most"):
        accel.trace(rays, traversal="bvh2.restart_trail", short_stack=64, device="cuda")
    with pytest.raises(InvalidInputError, match=r"\(n, 3\) float32"):
        accel.intersect(cuda.to_device(rays.origin.astype(np.float64)),
                        cuda.to_device(rays.direction), device="cuda")  # fmt: skip
    wide = ra.TriangleMesh(mesh.vertices, mesh.faces, precision="float64")
    with pytest.raises(InvalidInputError, match="float32"):
        ra.build(wide).intersect(rays.origin, rays.direction, device="cuda")


def test_empty_batch(mesh, accels):
    accel = _accel(accels, mesh, "bvh2.binned_sah")
    hits = accel.intersect(np.zeros((0, 3)), np.zeros((0, 3)), device="cuda")
    assert len(hits) == 0


def test_on_a_real_gpu():
    """Where a GPU was asked for, the kernels above really ran on it."""
    if not ON_GPU:
        pytest.skip("no GPU asked for: the kernels ran under numba's CUDA simulator "
                    "(set RAYACCEL_CUDA_TESTS=gpu on a machine with an NVIDIA GPU)")  # fmt: skip
    assert not cuda.config.ENABLE_CUDASIM
    assert cuda.is_available()


def test_compiles_for_the_gpu():
    """Every kernel compiles to PTX for a Hopper GPU (NVVM alone, no simulator, no GPU)."""
    script = Path(__file__).with_name("ptx_check.py")
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "0"}
    run = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True,
                         timeout=900)  # fmt: skip
    if run.returncode == ptx_check.NO_NVVM:
        pytest.skip(run.stdout.strip().splitlines()[-1])
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-4000:]
    assert run.stdout.count(" ok\n") == 3 * len(CASES), run.stdout
