"""Adapters that run other ray tracers on the same rays: Embree, Open3D, Mitsuba 3, Warp, trimesh.

A peer is measured exactly like a rayaccel system, on the same
:class:`~rayaccel.rays.batch.RayBatch` objects, and appears as an extra row of
the benchmark table. Every adapter has the same small vocabulary (trimesh's
``ray/parent.py`` and Embree's intersect/occluded split):

``available()``        whether its package imports (``unavailable_reason()`` says why not)
``set_threads(n)``     limit its threads where the library allows it
``build(mesh)``        build its acceleration structure; returns the build time in ms
``prepare(rays)``      convert rays to the library's own format (untimed)
``intersect(rays)``    closest hit: ``(t, prim)``, ``inf``/``-1`` on a miss
``occluded(rays)``     any hit in ``[tmin, tmax]``: ``(n,)`` bool

``intersect``/``occluded`` accept a :class:`RayBatch` or the result of
``prepare``. The peers:

* ``embree``: Intel Embree 4 through ``embreex`` (the wrapper trimesh uses). Its
  ``run`` loops over rays **on one thread** (``rtcIntersect1``), with no thread
  control and ``tnear = 0`` fixed; per-ray ``tfar`` is passed. Build is the
  mesh upload plus the first query, which commits the scene.
* ``open3d``: Open3D's ``RaycastingScene``, also Embree, but multi-threaded
  (``nthreads``): the fastest route from Python to Embree, and the reference of
  the ``ratio`` column. Its occlusion test takes one scalar ``tnear``/``tfar``
  for all rays, so a batch whose rays differ in ``tmax`` is refused. Open3D
  builds lazily on the first query, so build time covers ``add_triangles`` and
  a one-ray cast. On Debian it needs ``libusb-1.0-0``.
* ``mitsuba``: Mitsuba 3's ``llvm_ad_rgb`` variant: ``ray_intersect_preliminary``
  and ``ray_test`` over the whole batch as one Dr.Jit wavefront (Embree's BVH
  inside, traced by Dr.Jit's thread pool, whose size ``set_threads`` sets for
  the whole process). ``Ray3f`` has no ``tmin``. The thesis compared against
  Mitsuba's packets; this is the route its Python users take.
* ``warp``: NVIDIA Warp's ``mesh_query_ray`` / ``mesh_query_ray_anyhit`` over
  ``wp.Mesh`` (Warp's own BVH) in a Warp kernel on the CPU device, which Warp
  runs on one thread. Kernels compile on first use and are cached by Warp.
* ``trimesh``: ``trimesh.ray.ray_triangle.RayMeshIntersector``, pure numpy over
  an r-tree (needs the ``rtree`` package). It is orders of magnitude slower, so
  it only runs on the first :attr:`TrimeshPeer.max_rays` rays of a set, with at
  most :attr:`TrimeshPeer.max_repeats` timed passes, and on meshes up to
  :attr:`TrimeshPeer.max_triangles` triangles; the table says so.

The rays' ``tmin`` must be 0 for ``embree``, ``mitsuba`` and ``warp``, and equal
for all rays for ``open3d`` (every standard ray set satisfies both: secondary
rays offset their origins instead of using ``tmin``).
"""

from __future__ import annotations

import importlib
import time
from typing import Any

import numpy as np

from rayaccel.dtypes import INDEX, REAL, BoolArray, FloatArray, IntArray
from rayaccel.errors import BackendUnavailableError, InvalidInputError
from rayaccel.rays.batch import RayBatch
from rayaccel.scene.mesh import TriangleMesh


class Peer:
    """Base class of the peer adapters (see the module docstring for the protocol).

    Attributes
    ----------
    name : str
        Key used by ``--peers`` and in records.
    label : str
        Human-readable system name for tables.
    package : str
        The import the adapter needs.
    extra : str
        How to install it.
    threads_note : str
        How its thread count relates to ``--threads``.
    max_rays : int or None
        Run only the first ``max_rays`` rays of each set (None: all).
    max_triangles : int or None
        Skip meshes with more triangles (None: no limit).
    max_repeats : int or None
        Cap on the timed passes per measurement (None: as configured).
    """

    name = "peer"
    label = "peer"
    package = ""
    extra = "pip install 'rayaccel[peers]'"
    threads_note = ""
    max_rays: int | None = None
    max_triangles: int | None = None
    max_repeats: int | None = None

    def __init__(self) -> None:
        self.threads = 0
        self._mesh: TriangleMesh | None = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    # -- availability ---------------------------------------------------------------------------

    def unavailable_reason(self) -> str | None:
        """Return why the peer cannot run here, or None if it can."""
        for module in self.package.split(","):
            try:
                importlib.import_module(module)
            except Exception as exc:  # broken native libraries raise OSError and friends
                return f"{self.name}: cannot import {module} ({exc}); {self.extra}"
        return None

    def available(self) -> bool:
        """Return whether the peer's package imports."""
        return self.unavailable_reason() is None

    def require(self) -> None:
        """Raise ``BackendUnavailableError`` unless the peer is available."""
        reason = self.unavailable_reason()
        if reason is not None:
            raise BackendUnavailableError(reason)

    def skip_reason(self, mesh: TriangleMesh) -> str | None:
        """Return why the peer skips ``mesh`` (too large), or None."""
        if self.max_triangles is not None and mesh.n_triangles > self.max_triangles:
            return (
                f"{self.name} skipped: {mesh.n_triangles:,} triangles > "
                f"{self.max_triangles:,} (too slow)"
            )
        return None

    # -- protocol -------------------------------------------------------------------------------

    def set_threads(self, n: int) -> None:
        """Limit the peer to ``n`` threads where the library allows it (0: automatic)."""
        self.threads = int(n)

    def build(self, mesh: TriangleMesh) -> float:
        """Build the peer's structure over ``mesh``; return the build time in milliseconds."""
        self.require()
        start = time.perf_counter()
        self._build(mesh)
        self._mesh = mesh
        return (time.perf_counter() - start) * 1e3

    def limit(self, rays: RayBatch) -> RayBatch:
        """Return the rays this peer runs: all, or the first :attr:`max_rays`."""
        if self.max_rays is not None and rays.n_rays > self.max_rays:
            return rays.subset(slice(0, self.max_rays))
        return rays

    def prepare(self, rays: RayBatch) -> Any:
        """Return ``rays`` in the library's own format (conversion stays out of timings)."""
        return rays

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Return closest hits ``(t, prim)``, (n,) float32 and int32; ``inf``/``-1`` on a miss."""
        raise NotImplementedError

    def occluded(self, rays: Any) -> BoolArray:
        """Return ``(n,)`` bool: whether each ray hits anything in ``[tmin, tmax]``."""
        raise NotImplementedError

    def _build(self, mesh: TriangleMesh) -> None:
        raise NotImplementedError

    def _prepared(self, rays: Any) -> Any:
        return self.prepare(rays) if isinstance(rays, RayBatch) else rays


def _require_zero_tmin(name: str, rays: RayBatch) -> None:
    if np.any(rays.tmin != 0):
        raise InvalidInputError(
            f"{name}: rays with tmin != 0 are not supported (its tnear is fixed at 0)"
        )


class EmbreePeer(Peer):
    """Embree 4 through ``embreex``: one ray at a time on the calling thread."""

    name = "embree"
    label = "embree (embreex, 1 thread)"
    package = "embreex"
    threads_note = "embreex has no thread control: it always traces on one thread"

    def _build(self, mesh: TriangleMesh) -> None:
        from embreex import rtcore_scene
        from embreex.mesh_construction import TriangleMesh as EmbreeMesh

        self._scene = rtcore_scene.EmbreeScene()
        self._geometry = EmbreeMesh(self._scene, mesh.vertices, mesh.faces)
        # The first query commits the scene, i.e. builds the BVH
        origin = np.zeros((1, 3), dtype=REAL)
        direction = np.ones((1, 3), dtype=REAL)
        self._scene.run(origin, direction, dists=np.ones(1, dtype=REAL))

    def prepare(self, rays: RayBatch) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Return ``(origin, direction, tfar)`` float32 arrays (``tmin`` must be 0)."""
        _require_zero_tmin(self.name, rays)
        return rays.origin, rays.direction, np.ascontiguousarray(rays.tmax, dtype=REAL)

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Closest hits, see :meth:`Peer.intersect`."""
        origin, direction, tfar = self._prepared(rays)
        out = self._scene.run(origin, direction, dists=tfar.copy(), query="INTERSECT", output=1)
        prim = np.asarray(out["primID"], dtype=INDEX)
        t = np.where(prim >= 0, out["tfar"], np.inf).astype(REAL)
        return t, prim

    def occluded(self, rays: Any) -> BoolArray:
        """Any-hit test, see :meth:`Peer.occluded`."""
        origin, direction, tfar = self._prepared(rays)
        out = self._scene.run(origin, direction, dists=tfar.copy(), query="OCCLUDED")
        occluded: BoolArray = np.asarray(out) != -1
        return occluded


class Open3DPeer(Peer):
    """Open3D's ``RaycastingScene`` (Embree inside, multi-threaded)."""

    name = "open3d"
    label = "open3d (Embree)"
    package = "open3d"
    extra = "pip install open3d (on Debian also apt-get install libusb-1.0-0)"
    threads_note = "open3d: nthreads={n} passed to every query"

    def _build(self, mesh: TriangleMesh) -> None:
        import open3d

        self._o3d = open3d
        self._scene = open3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            open3d.core.Tensor(np.ascontiguousarray(mesh.vertices)),
            open3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
        )
        # Open3D builds lazily: one cast commits the scene
        one = open3d.core.Tensor(np.array([[0, 0, 0, 1, 1, 1]], dtype=REAL))
        self._scene.cast_rays(one, nthreads=self.threads)

    def prepare(self, rays: RayBatch) -> tuple[Any, float, float]:
        """Return ``(rays (n, 6) tensor, tnear, tfar)``; ``tmin`` must be 0 for all rays.

        ``tfar`` is the common ``tmax`` (only occlusion queries use it).
        """
        import open3d

        _require_zero_tmin(self.name, rays)
        tfar = float(rays.tmax[0]) if rays.n_rays else float("inf")
        if rays.n_rays and np.any(rays.tmax != rays.tmax[0]):
            tfar = float("nan")  # per-ray tmax: only a closest-hit query with tmax=inf works
        packed = np.ascontiguousarray(np.hstack([rays.origin, rays.direction]), dtype=REAL)
        return open3d.core.Tensor(packed), 0.0, tfar

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Closest hits, see :meth:`Peer.intersect` (rays' ``tmax`` must be infinite)."""
        tensor, _, tfar = self._prepared(rays)
        if not tfar == np.inf:
            raise InvalidInputError(
                f"{self.name}: closest-hit queries need tmax = inf for every ray, got {tfar}"
            )
        out = self._scene.cast_rays(tensor, nthreads=self.threads)
        t = out["t_hit"].numpy().astype(REAL)
        ids = out["primitive_ids"].numpy()
        invalid = np.uint32(self._o3d.t.geometry.RaycastingScene.INVALID_ID)
        prim = np.where(ids == invalid, -1, ids).astype(INDEX)
        return np.where(prim >= 0, t, np.inf).astype(REAL), prim

    def occluded(self, rays: Any) -> BoolArray:
        """Any-hit test with one ``tfar`` shared by all rays, see :meth:`Peer.occluded`."""
        tensor, tnear, tfar = self._prepared(rays)
        if np.isnan(tfar):
            raise InvalidInputError(
                f"{self.name}: occlusion queries need one tmax shared by every ray"
            )
        out = self._scene.test_occlusions(tensor, tnear=tnear, tfar=tfar, nthreads=self.threads)
        return np.asarray(out.numpy(), dtype=bool)


class TrimeshPeer(Peer):
    """trimesh's pure-numpy ray/triangle intersector (slow; runs on a subset)."""

    name = "trimesh"
    label = "trimesh (numpy)"
    package = "trimesh,rtree"
    extra = "pip install trimesh rtree"
    threads_note = "trimesh: numpy, single-threaded"
    max_rays = 256
    max_triangles = 100_000
    max_repeats = 2
    #: Rays per call of trimesh's intersector (bounds its candidate arrays).
    chunk = 32

    def _build(self, mesh: TriangleMesh) -> None:
        import trimesh
        from trimesh.ray.ray_triangle import RayMeshIntersector

        tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, validate=False)
        self._intersector = RayMeshIntersector(tm)
        # The r-tree of triangle bounds is built lazily: force it now
        _ = tm.triangles_tree
        self._normals = np.asarray(mesh.normals(), dtype=np.float64)

    def prepare(self, rays: RayBatch) -> RayBatch:
        """Return the first :attr:`max_rays` rays."""
        return self.limit(rays)

    def _all_hits(self, rays: RayBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return every hit ``(tri, ray, t)`` inside each ray's ``[tmin, tmax]``.

        trimesh tests every triangle whose box meets a ray's box, all at once in
        float64; rays go in chunks of :attr:`chunk` to bound that memory.
        """
        from trimesh.ray.ray_triangle import ray_triangle_id

        mesh = self._intersector.mesh
        triangles, tree = mesh.triangles, mesh.triangles_tree
        parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for begin in range(0, rays.n_rays, self.chunk):
            end = min(begin + self.chunk, rays.n_rays)
            origin, direction = rays.origin[begin:end], rays.direction[begin:end]
            # Zero normals of degenerate triangles make their plane test fail: never hit
            tri, ray, location = ray_triangle_id(
                triangles,
                origin,
                direction,
                triangles_normal=self._normals,
                tree=tree,
                multiple_hits=True,
            )
            if len(tri) == 0:
                continue
            d = direction[ray].astype(np.float64)
            t = np.einsum("ij,ij->i", location - origin[ray], d) / np.einsum("ij,ij->i", d, d)
            ray = ray + begin
            keep = (t >= rays.tmin[ray]) & (t <= rays.tmax[ray])
            parts.append((tri[keep], ray[keep], t[keep]))
        if not parts:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty, np.zeros(0)
        return tuple(np.concatenate(column) for column in zip(*parts, strict=True))  # type: ignore[return-value]

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Closest hits on the first :attr:`max_rays` rays, see :meth:`Peer.intersect`."""
        batch = self._prepared(rays)
        tri, ray, t = self._all_hits(batch)
        best_t = np.full(batch.n_rays, np.inf)
        prim = np.full(batch.n_rays, -1, dtype=INDEX)
        order = np.lexsort((t, ray))  # by ray, then distance
        first = np.ones(len(order), dtype=bool)
        first[1:] = ray[order][1:] != ray[order][:-1]
        chosen = order[first]
        best_t[ray[chosen]] = t[chosen]
        prim[ray[chosen]] = tri[chosen]
        return best_t.astype(REAL), prim

    def occluded(self, rays: Any) -> BoolArray:
        """Any-hit test on the first :attr:`max_rays` rays, see :meth:`Peer.occluded`."""
        batch = self._prepared(rays)
        _, ray, _ = self._all_hits(batch)
        blocked = np.zeros(batch.n_rays, dtype=bool)
        blocked[ray] = True
        return blocked


class MitsubaPeer(Peer):
    """Mitsuba 3's ``llvm_ad_rgb`` variant: wavefront queries through Dr.Jit (Embree inside)."""

    name = "mitsuba"
    label = "mitsuba 3 (llvm_ad_rgb)"
    package = "mitsuba,drjit"
    extra = "pip install mitsuba (the llvm variants need libLLVM, e.g. Debian's libllvm15)"
    threads_note = "mitsuba: Dr.Jit's thread pool set to {n} threads"
    #: The variant: the CPU one whose queries run vectorised over the whole batch.
    variant = "llvm_ad_rgb"

    def unavailable_reason(self) -> str | None:
        """Also check that the LLVM variant loads (it needs a system libLLVM)."""
        reason = super().unavailable_reason()
        if reason is not None:
            return reason
        import mitsuba

        try:
            mitsuba.set_variant(self.variant)
        except Exception as exc:  # no libLLVM: ImportError or a Dr.Jit RuntimeError
            return f"{self.name}: variant {self.variant} does not load ({exc}); {self.extra}"
        return None

    def set_threads(self, n: int) -> None:
        """Size Dr.Jit's thread pool (process-wide) to ``n`` threads; 0 leaves it as it is."""
        super().set_threads(n)
        if n > 0 and self.available():
            import drjit

            drjit.set_thread_count(int(n))

    def _build(self, mesh: TriangleMesh) -> None:
        import drjit
        import mitsuba

        mitsuba.set_variant(self.variant)
        self._mi, self._dr = mitsuba, drjit
        shape = mitsuba.Mesh(
            "rayaccel",
            vertex_count=mesh.n_vertices,
            face_count=mesh.n_triangles,
            has_vertex_normals=False,
            has_vertex_texcoords=False,
        )
        params = mitsuba.traverse(shape)
        params["vertex_positions"] = mitsuba.Float(np.ravel(mesh.vertices).astype(REAL))
        params["faces"] = mitsuba.UInt32(np.ravel(mesh.faces).astype(np.uint32))
        params.update()
        self._scene = mitsuba.load_dict({"type": "scene", "mesh": shape})
        # One query compiles the kernels that later queries reuse from Dr.Jit's cache
        self.intersect(RayBatch(np.zeros((1, 3)), np.ones((1, 3))))

    def prepare(self, rays: RayBatch) -> Any:
        """Return a ``mitsuba.Ray3f`` over the batch (``tmin`` must be 0: Ray3f has none)."""
        _require_zero_tmin(self.name, rays)
        mi = self._mi
        o, d = rays.origin, rays.direction
        ray = mi.Ray3f(
            o=mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), d=mi.Vector3f(d[:, 0], d[:, 1], d[:, 2])
        )
        ray.maxt = mi.Float(np.ascontiguousarray(rays.tmax, dtype=REAL))
        self._dr.eval(ray)
        return ray

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Closest hits through ``ray_intersect_preliminary``, see :meth:`Peer.intersect`."""
        found = self._scene.ray_intersect_preliminary(self._prepared(rays), coherent=False)
        self._dr.eval(found.t, found.prim_index)
        self._dr.sync_thread()
        t = np.array(found.t, dtype=REAL)
        hit = np.isfinite(t)
        prim = np.where(hit, np.array(found.prim_index).astype(np.int64), -1).astype(INDEX)
        return np.where(hit, t, np.inf).astype(REAL), prim

    def occluded(self, rays: Any) -> BoolArray:
        """Any-hit test through ``ray_test``, see :meth:`Peer.occluded`."""
        blocked = self._scene.ray_test(self._prepared(rays), coherent=False)
        self._dr.eval(blocked)
        self._dr.sync_thread()
        return np.array(blocked, dtype=bool)


class WarpPeer(Peer):
    """NVIDIA Warp's ``mesh_query_ray`` on the CPU (its own BVH; kernels compiled by Warp)."""

    name = "warp"
    label = "warp (CPU)"
    package = "warp"
    extra = "pip install warp-lang"
    threads_note = "warp: CPU kernels run on one thread"
    #: Warp device the queries run on.
    device = "cpu"

    def _build(self, mesh: TriangleMesh) -> None:
        from rayaccel.bench import warp_kernels

        warp: Any = importlib.import_module("warp")  # untyped: Warp's stubs describe its DSL

        warp.config.quiet = True
        warp.init()
        self._wp, self._kernels = warp, warp_kernels
        self._points = warp.array(mesh.vertices.astype(REAL), dtype=warp.vec3, device=self.device)
        self._indices = warp.array(
            np.ravel(mesh.faces).astype(np.int32), dtype=warp.int32, device=self.device
        )
        self._mesh_wp = warp.Mesh(points=self._points, indices=self._indices)
        # Compile (or load from Warp's cache) both kernels now, outside any timing
        warmup = self.prepare(RayBatch(np.zeros((1, 3)), np.ones((1, 3))))
        self.intersect(warmup)
        self.occluded(warmup)

    def prepare(self, rays: RayBatch) -> tuple[Any, Any, Any, int]:
        """Return Warp arrays ``(origins, directions, tmax, n)`` (``tmin`` must be 0)."""
        _require_zero_tmin(self.name, rays)
        wp = self._wp
        return (
            wp.array(rays.origin, dtype=wp.vec3, device=self.device),
            wp.array(rays.direction, dtype=wp.vec3, device=self.device),
            wp.array(
                np.ascontiguousarray(rays.tmax, dtype=REAL), dtype=wp.float32, device=self.device
            ),
            rays.n_rays,
        )

    def _launch(self, kernel: Any, rays: Any, *dtypes: Any) -> list[np.ndarray]:
        """Run a kernel of :mod:`~rayaccel.bench.warp_kernels`; return its outputs, one per dtype.

        The kernel takes the mesh and the prepared rays, then one output array of
        ``n`` values per entry of ``dtypes``.
        """
        wp = self._wp
        origins, directions, tmax, n = self._prepared(rays)
        outputs = [wp.empty(n, dtype=dtype, device=self.device) for dtype in dtypes]
        if n:
            wp.launch(
                kernel,
                dim=n,
                inputs=[self._mesh_wp.id, origins, directions, tmax],
                outputs=outputs,
                device=self.device,
            )
        return [output.numpy() for output in outputs]

    def intersect(self, rays: Any) -> tuple[FloatArray, IntArray]:
        """Closest hits, see :meth:`Peer.intersect`."""
        wp = self._wp
        t, prim = self._launch(self._kernels.closest_hits, rays, wp.float32, wp.int32)
        return t.astype(REAL), prim.astype(INDEX)

    def occluded(self, rays: Any) -> BoolArray:
        """Any-hit test, see :meth:`Peer.occluded`."""
        (hit,) = self._launch(self._kernels.any_hits, rays, self._wp.int32)
        occluded: BoolArray = hit.astype(bool)
        return occluded


#: Every peer adapter by name, in table order (Open3D first: it is the reference).
PEERS: dict[str, type[Peer]] = {
    "open3d": Open3DPeer,
    "embree": EmbreePeer,
    "mitsuba": MitsubaPeer,
    "warp": WarpPeer,
    "trimesh": TrimeshPeer,
}

#: The peer the ``ratio`` column divides by.
REFERENCE_PEER = "open3d"


def peer_names() -> list[str]:
    """Return the names of every peer adapter."""
    return list(PEERS)


def get_peer(name: str) -> Peer:
    """Return a new adapter for the peer ``name``.

    Raises
    ------
    InvalidInputError
        Unknown peer name.
    """
    try:
        return PEERS[name]()
    except KeyError:
        raise InvalidInputError(
            f"unknown peer {name!r}; expected some of {', '.join(PEERS)} or 'none'"
        ) from None


def parse_peers(spec: str | list[str] | tuple[str, ...] | None) -> list[str]:
    """Parse ``--peers``: ``"embree,open3d"``, ``"all"``, ``"none"`` or a list.

    Returns
    -------
    list of str
        Known peer names in :data:`PEERS` order (availability is not checked).
    """
    if spec is None:
        return list(PEERS)
    parts = [spec] if isinstance(spec, str) else list(spec)
    items = [item for part in parts for item in part.split(",")]
    names = [item.strip() for item in items if item.strip()]
    if names in (["none"], []):
        return []
    if names == ["all"]:
        return list(PEERS)
    for name in names:
        get_peer(name)
    return [name for name in PEERS if name in names]
