"""Fuzz targets for the scene-file loaders, shared by the CI tests and the long run.

Targets: OBJ, ASCII PLY, binary PLY, ASCII STL, binary STL, gzip (the
decompression layer and the PLY reader behind it) and GLB (the container checks
and trimesh behind them).

A target is a file suffix, valid seed files and a way to make inputs: hypothesis
mutates a seed (byte flips, overwrites with boundary integers, number tokens
swapped for hostile ones, truncation, insertion, deletion, duplication), or
draws random bytes, optionally after a seed's header. :func:`check_input` writes
the input to a file and loads it; the contract
(``docs/reliability.md``, "Files") is that it either loads into a valid
:class:`~rayaccel.scene.mesh.TriangleMesh` or raises
:class:`~rayaccel.errors.SceneFileError` naming the file. Anything else fails the
example:

* another exception type (a crash);
* an example running past :data:`EXAMPLE_DEADLINE_S` (a hang; a ``SIGALRM``
  watchdog interrupts it);
* a peak of traced allocations above :data:`ALLOCATION_BUDGET` (the inputs are a
  few kilobytes, so only an allocation sized by a declared count can reach it).

Used by ``tests/scene/test_fuzz_loaders.py`` (a few seconds per target) and
``benchmarks/fuzz_loaders.py --minutes N`` (the long run).
"""

from __future__ import annotations

import contextlib
import gzip
import os
import signal
import struct
import tempfile
import tracemalloc
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import numpy as np
from hypothesis import strategies as st

from rayaccel.errors import SceneFileError
from rayaccel.scene.io import load_mesh
from rayaccel.scene.mesh import TriangleMesh

#: Wall-clock seconds one example may take before it counts as a hang.
EXAMPLE_DEADLINE_S = 5.0
#: Peak traced bytes one example may allocate (inputs are at most a few KiB).
ALLOCATION_BUDGET = 64 * 2**20
#: Size limit handed to ``load_mesh``: gzip seeds include a bomb that exceeds it.
MAX_BYTES = 2**20

# ----------------------------------------------------------------------------- seeds

_SQUARE = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, 1)]
_POLYGONS = [(0, 1, 4), (0, 1, 2, 3), (0, 1, 2, 3, 4), (1, 2, 4)]

OBJ_SEED = b"""# a pyramid
mtllib pyramid.mtl
o pyramid
v 0 0 0
v 1 0 0
v\t1 1 0
v 0 1 0 1.0
v 0.5 0.5 1 0.2 0.3 0.4
vt 0 0
vn 0 0 1
g sides
usemtl white
s off
f 1 4 3 2
f 1/1 2/1 5/1
f 2//1 3//1 5//1
f -3/1/1 -2/1/1 -1/1/1
f 4 1 \\
  5
"""


def _ply(
    fmt: str, faces: list[tuple[int, ...]], *, coord: str = "float", count: str = "uchar"
) -> bytes:
    header = (
        f"ply\nformat {fmt} 1.0\ncomment seed\nelement vertex {len(_SQUARE)}\n"
        f"property {coord} x\nproperty {coord} y\nproperty {coord} z\nproperty uchar red\n"
        f"element face {len(faces)}\nproperty list {count} int vertex_indices\n"
        "property float quality\nend_header\n"
    ).encode()
    if fmt == "ascii":
        rows = [f"{x} {y} {z} 7" for x, y, z in _SQUARE]
        rows += [" ".join(map(str, (len(f), *f, 0.5))) for f in faces]
        return header + ("\n".join(rows) + "\n").encode()
    order = "<" if fmt == "binary_little_endian" else ">"
    c, n = {"float": "f", "double": "d"}[coord], {"uchar": "B", "int": "i", "ushort": "H"}[count]
    body = b"".join(struct.pack(f"{order}3{c}B", *v, 7) for v in _SQUARE)
    for face in faces:
        body += struct.pack(f"{order}{n}{len(face)}if", len(face), *face, 0.5)
    return header + body


PLY_ASCII_SEEDS = [
    _ply("ascii", _POLYGONS),
    _ply("ascii", [(0, 1, 2), (0, 2, 3)]),
]
PLY_BINARY_SEEDS = [
    _ply("binary_little_endian", [(0, 1, 2), (0, 2, 3), (0, 1, 4)]),
    _ply("binary_little_endian", _POLYGONS, count="int"),
    _ply("binary_big_endian", _POLYGONS, coord="double", count="ushort"),
]
_TRIANGLES = [[_SQUARE[i] for i in tri] for tri in [(0, 1, 2), (0, 2, 3), (0, 1, 4)]]
STL_ASCII_SEED = (
    "solid pyramid\n"
    + "".join(
        "facet normal 0 0 1\n outer loop\n"
        + "".join(f"  vertex {x} {y} {z}\n" for x, y, z in tri)
        + " endloop\nendfacet\n"
        for tri in _TRIANGLES
    )
    + "endsolid pyramid\n"
).encode()
STL_BINARY_SEEDS = [
    header.ljust(80, b" ")
    + struct.pack("<I", len(_TRIANGLES))
    + b"".join(struct.pack("<12fH", 0, 0, 1, *np.ravel(tri), 0) for tri in _TRIANGLES)
    for header in (b"binary", b"solid looks like ascii")
]


def _glb_seeds() -> list[bytes]:
    import trimesh

    faces = np.asarray([(0, 1, 2), (0, 2, 3), (0, 1, 4)])
    mesh = trimesh.Trimesh(np.asarray(_SQUARE, dtype=np.float64), faces, process=False)
    blob = mesh.export(file_type="glb")
    return [blob if isinstance(blob, bytes) else bytes(blob)]


GLB_SEEDS = _glb_seeds()
_BOMB = gzip.compress(PLY_BINARY_SEEDS[0] + bytes(2 * MAX_BYTES), compresslevel=9)


# ----------------------------------------------------------------------------- inputs

#: Numbers a mutation writes in place of a number token or a binary integer.
INTERESTING = [0, 1, 2, 3, 4, 5, 7, 8, 127, 128, 255, 256, 65535, 65536, 2**31 - 1, 2**31,
               2**32 - 1, 2**32, 2**63 - 1, -1, -2, -(2**31)]  # fmt: skip
_TOKENS = [str(v).encode() for v in INTERESTING] + [
    b"nan", b"inf", b"-inf", b"1e39", b"1e400", b"-0", b"0.5", b"1e-45", b"0x10", b"",
    b"99999999999999999999999",
]  # fmt: skip


def _mutate(data: bytearray, draw: Callable[[st.SearchStrategy[int]], int], kind: int) -> None:
    """Apply one mutation of ``kind`` in place (positions drawn from ``draw``)."""
    if kind == 0 and data:  # overwrite a byte
        data[draw(st.integers(0, len(data) - 1))] = draw(st.integers(0, 255))
    elif kind == 1 and data:  # flip a bit
        data[draw(st.integers(0, len(data) - 1))] ^= 1 << draw(st.integers(0, 7))
    elif kind == 2:  # truncate
        del data[draw(st.integers(0, len(data))) :]
    elif kind == 3:  # insert bytes
        at = draw(st.integers(0, len(data)))
        data[at:at] = draw(st.binary(min_size=1, max_size=16))  # type: ignore[arg-type]
    elif kind == 4 and data:  # delete a range
        at = draw(st.integers(0, len(data) - 1))
        del data[at : at + draw(st.integers(1, 32))]
    elif kind == 5 and data:  # duplicate a range elsewhere
        at = draw(st.integers(0, len(data) - 1))
        chunk = bytes(data[at : at + draw(st.integers(1, 64))])
        to = draw(st.integers(0, len(data)))
        data[to:to] = chunk
    elif kind == 6:  # swap a decimal number token for a hostile one
        starts = [
            i
            for i in range(len(data))
            if 48 <= data[i] <= 57 and (i == 0 or not 48 <= data[i - 1] <= 57)
        ]
        if starts:
            at = starts[draw(st.integers(0, len(starts) - 1))]
            end = at
            while end < len(data) and (48 <= data[end] <= 57 or data[end] == 46):
                end += 1
            data[at:end] = _TOKENS[draw(st.integers(0, len(_TOKENS) - 1))]
    elif kind == 7 and data:  # overwrite with a boundary integer, 1, 2 or 4 bytes, either order
        size = (1, 2, 4)[draw(st.integers(0, 2))]
        value = INTERESTING[draw(st.integers(0, len(INTERESTING) - 1))] % (1 << (8 * size))
        order = "little" if draw(st.integers(0, 1)) else "big"
        at = draw(st.integers(0, len(data) - 1))
        data[at : at + size] = value.to_bytes(size, order)


@st.composite
def mutated(draw: st.DrawFn, seeds: list[bytes], max_mutations: int = 6) -> bytes:
    """A seed after up to ``max_mutations`` mutations."""
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(0, max_mutations))):
        _mutate(data, draw, draw(st.integers(0, 7)))
    return bytes(data)


def inputs(seeds: list[bytes]) -> st.SearchStrategy[bytes]:
    """Mutated seeds (mostly), random bytes, and a seed's first bytes then random bytes."""
    prefixes = st.tuples(st.sampled_from(seeds), st.integers(0, 400), st.binary(max_size=512))
    return st.one_of(
        mutated(seeds),
        mutated(seeds),
        mutated(seeds),
        st.binary(max_size=2048),
        prefixes.map(lambda t: t[0][: t[1]] + t[2]),
    )


@dataclass(frozen=True)
class Target:
    """One loader to fuzz: the file suffix it is read under and its input strategy."""

    name: str
    suffix: str
    strategy: st.SearchStrategy[bytes]


def _gz_inputs() -> st.SearchStrategy[bytes]:
    plain = PLY_BINARY_SEEDS + PLY_ASCII_SEEDS
    compressed = [gzip.compress(seed) for seed in plain] + [_BOMB]
    return st.one_of(
        inputs(compressed),  # the gzip layer itself
        inputs(plain).map(gzip.compress),  # the PLY reader behind it
    )


TARGETS: dict[str, Target] = {
    t.name: t
    for t in [
        Target("obj", ".obj", inputs([OBJ_SEED])),
        Target("ply_ascii", ".ply", inputs(PLY_ASCII_SEEDS)),
        Target("ply_binary", ".ply", inputs(PLY_BINARY_SEEDS)),
        Target("stl_ascii", ".stl", inputs([STL_ASCII_SEED])),
        Target("stl_binary", ".stl", inputs(STL_BINARY_SEEDS)),
        Target("gz", ".ply.gz", _gz_inputs()),
        Target("glb", ".glb", inputs(GLB_SEEDS)),
    ]
}


# ----------------------------------------------------------------------------- oracle


class ExampleHangError(Exception):
    """An example ran past :data:`EXAMPLE_DEADLINE_S`."""


class ExampleAllocationError(Exception):
    """An example allocated more than :data:`ALLOCATION_BUDGET`."""


def _on_alarm(signum: int, frame: FrameType | None) -> None:
    raise ExampleHangError(f"example ran past {EXAMPLE_DEADLINE_S} s")


@contextlib.contextmanager
def scratch_folder() -> Iterator[Path]:
    """Yield a temporary folder for the inputs, in memory (``/dev/shm``) where there is one.

    Every example writes its input to a file; on a disk-backed ``/tmp`` that write
    costs milliseconds, more than loading it.
    """
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None
    with tempfile.TemporaryDirectory(prefix="rayaccel-fuzz-", dir=base) as name:
        yield Path(name)


@contextlib.contextmanager
def traced() -> Iterator[None]:
    """Trace allocations (numpy's included) while fuzzing; :func:`check_input` reads the peak."""
    started = not tracemalloc.is_tracing()
    if started:
        tracemalloc.start()
    try:
        yield
    finally:
        if started:
            tracemalloc.stop()


def check_input(target: Target, data: bytes, folder: Path) -> str:
    """Load ``data`` as a ``target`` file; return ``"loaded"`` or ``"refused"``.

    Raises whatever breaks the contract: another exception, :class:`ExampleHangError`,
    :class:`ExampleAllocationError`, or an ``AssertionError`` for a refusal that does not
    name the file or a mesh that is not valid.
    """
    path = folder / f"fuzz{target.suffix}"
    path.write_bytes(data)
    tracing = tracemalloc.is_tracing()
    if tracing:
        tracemalloc.reset_peak()
    previous = signal.signal(signal.SIGALRM, _on_alarm)
    signal.setitimer(signal.ITIMER_REAL, EXAMPLE_DEADLINE_S)
    try:
        mesh = load_mesh(path, max_bytes=MAX_BYTES)
    except SceneFileError as exc:
        if str(path) not in str(exc):
            raise AssertionError(f"the error does not name the file: {exc}") from exc
        outcome = "refused"
    else:
        assert isinstance(mesh, TriangleMesh)
        assert mesh.n_triangles >= 1
        assert np.isfinite(mesh.vertices).all()
        assert mesh.faces.min() >= 0
        assert mesh.faces.max() < mesh.n_vertices
        outcome = "loaded"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
    if tracing:
        peak = tracemalloc.get_traced_memory()[1]
        if peak > ALLOCATION_BUDGET:
            raise ExampleAllocationError(
                f"peak allocation {peak} bytes for a {len(data)}-byte input"
            )
    return outcome
