"""The traversal core that every structure family shares.

Query kinds, the per-ray set-up, the leaf loop, the parallel worker skeleton and the
Python-side driver live here. A traversal of any family (``bvh2.stack``,
``kdtree.rope``, ``grid.dda``) supplies only its per-ray body and the scratch arrays
one worker needs (:func:`rayaccel.trace.skeleton.trace_kernel`); chunking rays over
workers, storing hits and counting stack overflows happen here once.
:func:`rayaccel.trace.run.run_trace` validates the query, allocates the outputs, picks
the serial or parallel variant and wraps the hits. The per-ray constants
(:mod:`rayaccel.trace.ray_setup`) and the triangle-range loop
(:mod:`rayaccel.trace.leaf`) are the same arithmetic in every family, so every
structure returns the oracle's hits bit for bit.
"""
