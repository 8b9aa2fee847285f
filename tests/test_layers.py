"""Import layering (STYLE §2), checked by parsing every module's imports with ``ast``.

Layers, lowest first: 0 ``_jit _inline_copy dtypes errors counters config queries _variant
_docstrings _atomic _hugepages _work``; 1 ``kernels``; 2 ``scene rays``; 3 ``trace`` (the
family-neutral traversal core); 4 ``bvh kdtree grid``; 5 ``cuda``; 6 ``registry metrics``; 7
``api``; 8 ``render bench precompile trimesh``; 9 ``study``; 10 ``cli``. A module imports only from
its own layer or lower ones; sibling packages of one layer (``scene``/``rays``,
``bvh``/``kdtree``/``grid``, ``registry``/``metrics``, ``render``/``bench``) stay independent, so no
family imports another. No module imports another module's private (``_name``) names. The package
``__init__``/``__main__`` re-export and are exempt. Imports inside functions and under
``TYPE_CHECKING`` count too.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import rayaccel
from rayaccel import registry

SRC = Path(rayaccel.__file__).resolve().parent

LAYERS: dict[str, int] = {
    "_jit": 0,
    "_inline_copy": 0,  # not in STYLE §2: numba's inliner without its quadratic copy
    "dtypes": 0,
    "errors": 0,
    "counters": 0,
    "config": 0,
    "_variant": 0,
    "_docstrings": 0,  # not in STYLE §2: numpydoc sections shared by several functions
    "queries": 0,  # not in STYLE §2: query kinds, shared by the oracle and every family
    "_hugepages": 0,  # not in STYLE §2: huge-page advice for arrays allocated in kernels
    "_atomic": 0,  # not in STYLE §2 yet: stdlib-only atomic file writes
    "_work": 0,  # not in STYLE §2: work distribution of parallel kernels (shared counter)
    "validation": 0,  # not in STYLE §2: argument checks shared by every entry point
    "kernels": 1,
    "scene": 2,
    "rays": 2,
    "trace": 3,  # not in STYLE §2 yet: what every family's traversals share
    "bvh": 4,
    "kdtree": 4,
    "grid": 4,
    "cuda": 5,
    "registry": 6,
    "metrics": 6,
    "chunked": 6,  # not in STYLE §2: huge numpy batches in chunks, Dask arrays of rays
    "refit": 6,  # not in STYLE §2: refit or rebuild a structure for moved vertices
    "persist": 6,  # not in STYLE §2: saved accel files (npz + JSON header, hashed)
    "api": 7,
    "render": 8,
    "bench": 8,
    "precompile": 8,
    "trimesh": 8,  # not in STYLE §2: trimesh's ray interface on a BVH (drop-in for mesh.ray)
    "study": 9,  # not in STYLE §2: the thesis's study (path-traced rays, sweeps, reports)
    "cli": 10,
}
#: Layer-0 modules are one foundation and may import each other; packages may not.
FOUNDATION = 0
EXEMPT = {"__init__", "__main__"}
#: Third-party imports reserved to some layers (STYLE §2).
RESERVED = {"matplotlib": 8, "rich": 8}


def _modules() -> list[tuple[str, Path]]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).with_suffix("")
        out.append((".".join(("rayaccel", *rel.parts)), path))
    return out


def _component(module: str) -> str | None:
    """The layer component of ``rayaccel.x.y`` (``x``), or None for the package root."""
    parts = module.split(".")
    if parts[0] != "rayaccel" or len(parts) < 2:
        return None
    return parts[1]


def _imports(path: Path, module: str) -> list[tuple[int, str]]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                found.append((node.lineno, "." * node.level + (node.module or "")))
            elif node.module == "rayaccel":
                found += [(node.lineno, f"rayaccel.{a.name}") for a in node.names]
            else:
                found.append((node.lineno, node.module or ""))
    return found


MODULES = _modules()


def test_every_module_has_a_layer():
    unknown = {_component(m) for m, _ in MODULES} - set(LAYERS) - EXEMPT - {None}
    assert not unknown, f"modules outside every layer (add them to STYLE §2): {unknown}"


@pytest.mark.parametrize(("module", "path"), MODULES, ids=[m for m, _ in MODULES])
def test_imports_respect_layers(module, path):
    own = _component(module)
    problems = []
    for line, target in _imports(path, module):
        if target.startswith("."):
            problems.append(f"line {line}: relative import {target!r} (imports are absolute)")
            continue
        top = target.split(".")[0]
        if top in RESERVED and own not in EXEMPT and LAYERS.get(own, 99) < RESERVED[top]:
            problems.append(f"line {line}: {target} is reserved to layers >= {RESERVED[top]}")
        if (target == "numba.cuda" or target.startswith("numba.cuda.")) and own != "cuda":
            problems.append(f"line {line}: only rayaccel.cuda imports numba.cuda")
        if top != "rayaccel" or own in EXEMPT:
            continue
        other = _component(target)
        if other is None or other in EXEMPT:
            problems.append(f"line {line}: imports the package root ({target})")
            continue
        if other == own or other not in LAYERS:
            continue
        mine, theirs = LAYERS[own], LAYERS[other]
        if theirs > mine:
            problems.append(
                f"line {line}: layer {mine} ({own}) imports upward: {target} (layer {theirs})"
            )
        elif theirs == mine and mine != FOUNDATION:
            problems.append(f"line {line}: {own} imports its sibling {other} ({target})")
    assert not problems, f"{module}:\n" + "\n".join(problems)


def _private_imports(path: Path) -> list[tuple[int, str]]:
    """``(line, "module.name")`` for every ``from rayaccel... import _name``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("rayaccel"):
            found += [
                (node.lineno, f"{node.module}.{a.name}")
                for a in node.names
                if a.name.startswith("_") and not a.name.startswith("__")
            ]
    return found


TEST_FILES = sorted(Path(__file__).resolve().parent.rglob("*.py"))


@pytest.mark.parametrize(
    "path",
    [p for _, p in MODULES] + TEST_FILES,
    ids=[m for m, _ in MODULES] + [p.name for p in TEST_FILES],
)
def test_no_private_names_imported(path):
    found = _private_imports(path)
    assert not found, f"{path.name} imports private names: {found}"


def test_private_import_checker(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text(
        "from rayaccel.bvh.builders.sbvh import _split, public\nfrom rayaccel import __version__\n"
    )
    assert _private_imports(bad) == [(1, "rayaccel.bvh.builders.sbvh._split")]


def test_families_never_import_each_other():
    families = [name for name, layer in LAYERS.items() if layer == LAYERS["bvh"]]
    for module, path in MODULES:
        own = _component(module)
        if own not in families:
            continue
        others = {_component(t) for _, t in _imports(path, module)} & set(families)
        assert others <= {own}, f"{module} imports the family {others - {own}}"


def test_checker_catches_violations(tmp_path):
    """The parser sees upward, sibling, relative and in-function imports."""
    bad = tmp_path / "bad.py"
    bad.write_text(
        "from rayaccel import api\n"
        "from . import layout\n"
        "def f():\n    import rayaccel.rays.batch\n"
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from rayaccel.registry import get\n"
    )
    targets = sorted(t for _, t in _imports(bad, "rayaccel.scene.bad"))
    assert targets == sorted(
        ["rayaccel.api", ".", "rayaccel.rays.batch", "typing", "rayaccel.registry"]
    )


def _registers(path: Path) -> bool:
    """Whether the module decorates something with ``@register(...)``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            for deco in node.decorator_list:
                func = deco.func if isinstance(deco, ast.Call) else deco
                if isinstance(func, ast.Name) and func.id == "register":
                    return True
    return False


def _variant_modules() -> set[str]:
    """Every module that registers a variant under src.

    (The CUDA kernels register nothing: ``device="cuda"`` runs a registered traversal's
    own per-ray body, see :mod:`rayaccel.cuda`.)
    """
    return {module for module, path in MODULES if _registers(path)}


def test_builtin_modules_list_every_variant_module():
    listed = set(registry.BUILTIN_MODULES)
    missing = _variant_modules() - listed
    assert not missing, f"registry.BUILTIN_MODULES misses {sorted(missing)}"
    assert len(listed) == len(registry.BUILTIN_MODULES), "duplicates in BUILTIN_MODULES"
    assert _variant_modules(), "no registering module found (wrong source path?)"


def test_builtin_modules_exist_and_register():
    from rayaccel._variant import REGISTRY

    registry.keys()  # load
    registering = {v.func.__module__ for v in REGISTRY.values()}
    for module in registry.BUILTIN_MODULES:
        importlib.import_module(module)
        assert module in registering, f"{module} registers no variant"
    # Every registered variant comes from a listed module (nothing registers by accident).
    stray = registering - set(registry.BUILTIN_MODULES)
    assert not stray, f"variants registered outside BUILTIN_MODULES: {stray}"
