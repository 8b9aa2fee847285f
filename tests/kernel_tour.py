"""Run every CPU kernel of rayaccel at least once, and say which ones did not run.

The bounds-check tier (``tests/test_boundscheck.py --full``, issue 20) runs
:mod:`rayaccel.precompile`'s jobs (every build key and every serial traversal kernel)
and then :func:`tour`: the build steps, the parallel traversal kernels, the all-hits and
geometry queries, refit, float64 structures, the bounce rays, the path tracer and the
heatmap. :func:`kernels_not_run` compares the kernels that ran in this process with
every function the package decorates with ``cpu_kernel`` (found by reading the source),
so a kernel added later and left out of the tour is named instead of passing unseen.
"""

from __future__ import annotations

import ast
import gc
import re
from pathlib import Path

import numpy as np

#: A closure kernel's qualified name ends in its closure digest (``rayaccel._jit``).
_DIGEST = re.compile(r"_[0-9a-f]{16}$")


def declared_kernels() -> set[str]:
    """Return ``module:qualname`` of every function the package decorates with ``cpu_kernel``."""
    import rayaccel

    root = Path(rayaccel.__file__).parent
    found: set[str] = set()
    for path in sorted(root.rglob("*.py")):
        module = ".".join(("rayaccel", *path.relative_to(root).with_suffix("").parts))
        module = module.removesuffix(".__init__")
        tree = ast.parse(path.read_text(encoding="utf-8"))

        def visit(node: ast.AST, prefix: str, module: str = module) -> None:
            for child in ast.iter_child_nodes(node):
                if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                    name = prefix + child.name
                    for deco in child.decorator_list:
                        call = deco.func if isinstance(deco, ast.Call) else deco
                        if isinstance(call, ast.Name) and call.id == "cpu_kernel":
                            found.add(f"{module}:{name}")
                    visit(child, name + ".<locals>.")
                elif isinstance(child, ast.ClassDef):
                    visit(child, prefix + child.name + ".")
                else:
                    visit(child, prefix)

        visit(tree, "")
    return found


def kernels_run() -> set[str]:
    """Return ``module:qualname`` of every rayaccel CPU kernel compiled in this process.

    A kernel loaded from numba's cache does not compile the kernels it calls, so the
    answer is complete only in a process that compiles everything it runs (the
    bounds-check tier, with a cache folder of its own).
    """
    from numba.core.registry import CPUDispatcher

    ran: set[str] = set()
    for obj in gc.get_objects():
        if isinstance(obj, CPUDispatcher) and obj.overloads:
            func = obj.py_func
            if func.__module__.startswith("rayaccel"):
                ran.add(f"{func.__module__}:{_DIGEST.sub('', func.__qualname__)}")
    return ran


def kernels_not_run() -> list[str]:
    """Return the declared kernels that no call in this process has run, sorted."""
    return sorted(declared_kernels() - kernels_run())


def tour() -> None:
    """Call what :mod:`rayaccel.precompile`'s serial jobs leave out, on small inputs."""
    import rayaccel
    from rayaccel.kernels.brute_force import brute_force_trace
    from rayaccel.rays.batch import RayBatch
    from rayaccel.rays.bounce import ambient_occlusion_rays, diffuse_rays, shadow_rays
    from rayaccel.rays.camera import PinholeCamera
    from rayaccel.render.heatmap import HeatScale, heatmap_image, trace_counters
    from rayaccel.render.lights import AreaLights
    from rayaccel.render.materials import scene_materials
    from rayaccel.render.path import PathOptions, path_trace
    from rayaccel.render.shading import shade
    from rayaccel.scene import procedural
    from rayaccel.trace.run import PARALLEL_MIN_RAYS

    rng = np.random.Generator(np.random.PCG64(5))
    soup = procedural.triangle_soup(600, seed=1)
    ball = procedural.sphereflake(0, sphere_subdivisions=2, ground=False)
    n = PARALLEL_MIN_RAYS
    origin = rng.uniform(-0.5, 1.5, (n, 3))
    rays = RayBatch(origin, rng.uniform(0.0, 1.0, (n, 3)) - origin)

    # Build steps, and parallel builds on a larger soup.
    for key in ("bvh2.lbvh+collapse", "bvh2.lbvh+rotate", "bvh2.lbvh+treelet",
                "bvh2.binned_sah+presplit"):  # fmt: skip
        rayaccel.build(soup, key).validate()
    rayaccel.build(soup, "bvh2.lbvh", emission="karras").validate()
    rayaccel.build(soup, "bvh2.lbvh+rotate", rotate={"method": "anneal"}).validate()
    rayaccel.build(soup, "bvh2.binned_sah+presplit", presplit={"method": "evh"}).validate()
    big = procedural.triangle_soup(40_000, seed=2)
    for key in ("bvh2.binned_sah", "bvh2.sbvh", "bvh2.ploc", "kdtree.sah", "grid.two_level"):
        rayaccel.build(big, key).validate()

    # Parallel traversal kernels (a batch of PARALLEL_MIN_RAYS rays), every option variant.
    main = (("bvh2.binned_sah", ("bvh2.stack", "bvh2.wide")), ("kdtree.sah", ("kdtree.stack",)),
            ("grid.uniform", ("grid.dda",)))  # fmt: skip
    for key, traversals in main:
        accel = rayaccel.build(soup, key)
        for traversal in traversals:
            for query in ("closest", "any"):
                accel.trace(rays, query=query, traversal=traversal, stats=True)
    accel = rayaccel.build(soup, "bvh2.binned_sah")
    few = rays.subset(slice(0, 16))
    accel.trace(few, traversal="bvh2.wide", width=4)
    accel.trace(few, traversal="bvh2.wide", any_order="lanes", query="any")
    accel.trace(few, traversal="bvh2.wide", collapse="greedy")
    accel.trace(few, traversal="bvh2.restart_trail", short_stack=3)
    # The default queries release a tree's boxes; a named traversal restores them.
    fresh = rayaccel.build(soup, "bvh2.binned_sah")
    fresh.trace(rays)
    fresh.trace(few, traversal="bvh2.stack")
    accel.info(epo=True, lcv_rays=few)
    state = accel.traversal_state(few.origin, few.direction)
    while (state.next_hits().prim >= 0).any():
        pass
    brute_force_trace(soup.hit_rows(), few.origin, few.direction, few.tmin, few.tmax)

    # All hits, the geometry queries and refit.
    closed = rayaccel.build(ball, "bvh2.binned_sah")
    points = rng.uniform(-1.0, 1.0, (64, 3)) * ball.vertices.max(axis=0)
    for accel in (rayaccel.build(soup, "bvh2.binned_sah"), closed):
        accel.count_intersections(rays.origin[:64], rays.direction[:64])
        accel.list_intersections(rays.origin[:64], rays.direction[:64])
        accel.compute_closest_points(points)
        accel.compute_distance(points)
    for method in ("winding", "parity"):
        closed.compute_signed_distance(points, method=method)
        closed.compute_occupancy(points, method=method)
    closed.refit(ball.vertices * 1.01)
    import trimesh

    from rayaccel.trimesh import RayMeshIntersector

    drop_in = RayMeshIntersector(trimesh.Trimesh(ball.vertices, ball.faces, process=False))
    drop_in.intersects_location(rays.origin[:64], rays.direction[:64], multiple_hits=True)
    drop_in.intersects_first(rays.origin[:64], rays.direction[:64])
    drop_in.contains_points(points)

    # float64 structures of every family.
    soup64 = rayaccel.TriangleMesh(soup.vertices, soup.faces, precision="float64")
    rays64 = RayBatch(rays.origin[:64], rays.direction[:64], precision="float64")
    pairs = (("bvh2.binned_sah", "bvh2.stack"), ("bvh2.binned_sah", "bvh2.wide"),
             ("kdtree.sah", "kdtree.stack"), ("grid.uniform", "grid.dda"))  # fmt: skip
    for key, traversal in pairs:
        accel64 = rayaccel.build(soup64, key)
        accel64.validate()
        accel64.trace(rays64, traversal=traversal)
    rayaccel.build(soup64, "bvh2.binned_sah").compute_closest_points(points)

    # Bounce rays, shading, the path tracer and a heatmap.
    hits = accel.trace(rays)
    normals = soup.normals()
    diffuse_rays(rays, hits, normals, seed=1)
    shadow_rays(rays, hits, normals, np.array([0.5, 2.0, 0.5]), seed=1)
    ambient_occlusion_rays(rays, hits, normals, seed=1)
    box = procedural.cornell_box()
    camera = PinholeCamera(eye=(278, 273, -800), target=(278, 273, 0), up=(0, 1, 0),
                           fov_deg=39.3, width=16, height=16)  # fmt: skip
    box_accel = rayaccel.build(box)
    materials = scene_materials(box)
    path_trace(box_accel, camera, materials=materials,
               lights=AreaLights.from_materials(box, materials),
               options=PathOptions(spp=1, max_depth=2, seed=3))  # fmt: skip
    shade(box_accel, camera)
    values = trace_counters(box_accel, camera, "nodes")
    heatmap_image(values, HeatScale.fit([values], "nodes"))
