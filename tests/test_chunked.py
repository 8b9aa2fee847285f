"""Huge batches: numpy rays traced in chunks beyond the ray budget; Dask arrays of rays."""

from __future__ import annotations

import numpy as np
import pytest

import rayaccel
from rayaccel import chunked, config
from rayaccel.errors import InvalidInputError
from rayaccel.scene import catalog

da = pytest.importorskip("dask.array")
dask = pytest.importorskip("dask")


@pytest.fixture(scope="module")
def accel():
    return rayaccel.build(catalog.get("teapot"))


def _rays(n, seed=0):
    rng = np.random.default_rng(seed)
    origins = rng.uniform(-1, 1, (n, 3)) + np.array([0.0, 1.0, 6.0])
    targets = rng.uniform(-1.5, 1.5, (n, 3)) + np.array([0.0, 0.8, 0.0])
    return origins, targets - origins


def test_chunks_give_the_hits_of_one_batch(accel, monkeypatch):
    origins, directions = _rays(10_000)
    tmax = np.linspace(3.0, 10.0, len(origins))
    whole = accel.intersect(origins, directions, 0.0, tmax, stats=True)
    assert whole.hit.any()
    assert not whole.hit.all()
    monkeypatch.setattr(config, "RAY_BUDGET", 4096 * chunked.RAY_COPY_BYTES)
    calls = []
    trace = accel.trace
    monkeypatch.setattr(accel, "trace", lambda rays, **kw: calls.append(rays.n_rays) or
                        trace(rays, **kw))  # fmt: skip
    parts = accel.intersect(origins, directions, 0.0, tmax, stats=True)
    assert calls == [4096, 4096, 10_000 - 8192]
    np.testing.assert_array_equal(parts.prim, whole.prim)
    np.testing.assert_array_equal(parts.t, whole.t)
    np.testing.assert_array_equal(parts.u, whole.u)
    assert parts.stats is not None
    assert whole.stats is not None
    for name, values in whole.stats.items():
        np.testing.assert_array_equal(parts.stats[name], values)
    blocked = accel.occluded(origins, directions, 0.0, tmax)
    np.testing.assert_array_equal(blocked, whole.hit)
    # A (3,) origin is broadcast in every chunk; a bad chunk names its rays
    one = accel.intersect(origins[0], directions)
    np.testing.assert_array_equal(
        one.prim, accel.trace(rayaccel.RayBatch(origins[0], directions)).prim
    )
    bad = directions.copy()
    bad[9000] = np.nan
    bad_tmin = np.zeros(len(origins))
    bad_tmin[9000] = np.nan
    with pytest.raises(InvalidInputError, match=r"rays 8192\.\.9999: tmin"):
        accel.intersect(origins, directions, bad_tmin)
    with pytest.raises(InvalidInputError, match="shape"):
        accel.intersect(origins, directions, 0.0, np.ones(5))


def test_dask_arrays_in_dask_arrays_out(accel):
    origins, directions = _rays(5000, seed=1)
    tmax = np.linspace(3.0, 10.0, len(origins))
    expected = accel.intersect(origins, directions, 0.0, tmax)
    o = da.from_array(origins, chunks=(1200, 3))
    d = da.from_array(directions, chunks=(700, 3))  # other chunks: aligned to the origins'
    hits = accel.intersect(o, d, 0.0, da.from_array(tmax, chunks=900))
    assert isinstance(hits.t, da.Array)
    graph = dict(hits.t.__dask_graph__())
    shared = [k for k in graph if str(k).startswith("rayaccel-accel-")]
    assert len(shared) == 1  # the structure enters the graph once, however many blocks
    with dask.config.set(scheduler="synchronous"):
        t, prim, u = dask.compute(hits.t, hits.prim, hits.u)
        blocked = accel.occluded(o, d, 0.0, tmax).compute()
    np.testing.assert_array_equal(prim, expected.prim)
    np.testing.assert_array_equal(t, expected.t)
    np.testing.assert_array_equal(u, expected.u)
    np.testing.assert_array_equal(blocked, expected.hit)
    with pytest.raises(InvalidInputError, match="stats"):
        accel.intersect(o, d, stats=True)
    with pytest.raises(InvalidInputError, match=r"origins: expected shape \(n, 3\)"):
        accel.intersect(da.ones((10, 2)), d)
    with pytest.raises(InvalidInputError, match="directions: expected 5000 rows"):
        accel.intersect(o, da.ones((10, 3)))
