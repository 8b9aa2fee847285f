"""The variant registry: every builder and traversal, enumerable by key (STYLE §6).

Builders register as ``<structure>.<algorithm>`` (``bvh2.binned_sah``),
traversals as ``<structure>.<method>`` (``bvh2.stack``) and build steps as
``<structure>+<name>`` (``bvh2+reinsert``), each with an options dataclass whose
fields are the keyword options users may pass. The CLI, the benchmark matrix and the
conformance tests enumerate the registry, so a new variant edits none of them.

A build key may chain steps after the builder: ``bvh2.lbvh+presplit+reinsert+collapse``
(:func:`get_chain`). Each step has a *stage*: ``"after"`` steps (the default) are
post-processes of the built structure and run in key order; a ``"before"`` step
(``bvh2+presplit``) runs ahead of the builder and makes the references
(:class:`rayaccel.bvh.builders.refs.BuildRefs`) it builds over, for builders that take
``refs=`` (:attr:`Variant.takes_refs`). Modules are imported lazily from the explicit
:data:`BUILTIN_MODULES` tuple the first time the registry is read.
"""

from __future__ import annotations

import difflib
import importlib
from collections.abc import Callable
from typing import Any

from rayaccel._variant import (
    PAUSABLE,
    REGISTRY,
    STEP_SEPARATOR,
    Role,
    Stage,
    Variant,
    register,
    register_pausable,
)
from rayaccel.errors import InvalidInputError, UnknownVariantError

__all__ = [
    "BUILTIN_MODULES",
    "CONFIGURATIONS",
    "DEFAULT_BUILD_KEY",
    "Role",
    "Stage",
    "Variant",
    "build_keys",
    "configurations",
    "default_builder",
    "default_traversal",
    "get",
    "get_chain",
    "keys",
    "pausable",
    "register",
    "register_pausable",
    "structures",
    "variants",
]

#: The build key :func:`rayaccel.build` uses when none is named.
DEFAULT_BUILD_KEY = "bvh2.binned_sah"

#: Every module that registers variants (tests/test_layers.py checks that each module with
#: an ``@register`` decorator is listed).
BUILTIN_MODULES: tuple[str, ...] = (
    "rayaccel.bvh.builders.binned_sah",
    "rayaccel.bvh.builders.insertion",
    "rayaccel.bvh.builders.lbvh",
    "rayaccel.bvh.builders.ploc",
    "rayaccel.bvh.builders.sbvh",
    "rayaccel.bvh.builders.sweep_sah",
    "rayaccel.bvh.steps.collapse",
    "rayaccel.bvh.steps.presplit",
    "rayaccel.bvh.steps.reinsert",
    "rayaccel.bvh.steps.rotate",
    "rayaccel.bvh.steps.treelet",
    "rayaccel.bvh.traverse.stack",
    "rayaccel.bvh.traverse.skip",
    "rayaccel.bvh.traverse.parent_link",
    "rayaccel.bvh.traverse.bitstack",
    "rayaccel.bvh.traverse.restart_trail",
    "rayaccel.bvh.traverse.perfect_hash",
    "rayaccel.bvh.traverse.wide",
    "rayaccel.bvh.traverse.packet",
    "rayaccel.kdtree.builders.sah",
    "rayaccel.kdtree.builders.median",
    "rayaccel.kdtree.traverse.stack",
    "rayaccel.kdtree.traverse.restart",
    "rayaccel.kdtree.traverse.backtrack",
    "rayaccel.kdtree.traverse.short_stack",
    "rayaccel.kdtree.traverse.ropes",
    "rayaccel.grid.builders.uniform",
    "rayaccel.grid.builders.skip",
    "rayaccel.grid.builders.two_level",
    "rayaccel.grid.builders.irregular",
    "rayaccel.grid.traverse.dda",
)

#: Composed build keys enumerated beside the plain builders: the eight configurations of
#: the Devillers thesis's BVH comparison (LBVH, PLOC, SAH, SBVH, each without and with
#: reinsertion). ``rayaccel list``, the bench matrix and the conformance suite use them.
CONFIGURATIONS: tuple[str, ...] = (
    "bvh2.lbvh",
    "bvh2.lbvh+reinsert",
    "bvh2.ploc",
    "bvh2.ploc+reinsert",
    "bvh2.binned_sah",
    "bvh2.binned_sah+reinsert",
    "bvh2.sbvh",
    "bvh2.sbvh+reinsert",
)


_loaded = False


def _load() -> None:
    global _loaded
    if not _loaded:
        _loaded = True
        for module in BUILTIN_MODULES:
            importlib.import_module(module)


def variants(role: Role | None = None, structure: str | None = None) -> list[Variant]:
    """Return registered variants, sorted by key, optionally filtered."""
    _load()
    return [
        v
        for key, v in sorted(REGISTRY.items())
        if (role is None or v.role == role) and (structure is None or v.structure == structure)
    ]


def keys(role: Role | None = None, structure: str | None = None) -> list[str]:
    """Return registered keys, sorted."""
    return [v.key for v in variants(role, structure)]


def structures() -> list[str]:
    """Return every structure some builder builds, sorted (``["bvh2", ...]``)."""
    return sorted({v.structure for v in variants("builder")})


def _default(role: Role, structure: str) -> str:
    marked = [v.key for v in variants(role, structure) if v.default]
    if not marked:
        known = ", ".join(structures())
        raise InvalidInputError(
            f"no default {role} is registered for structure {structure!r} (structures: {known})"
        )
    if len(marked) > 1:
        raise ValueError(f"structure {structure!r} has several default {role}s: {marked}")
    return marked[0]


def default_builder(structure: str) -> str:
    """Return the builder registered with ``default=True`` for ``structure``."""
    return _default("builder", structure)


def default_traversal(structure: str) -> str:
    """Return the traversal registered with ``default=True`` for ``structure``.

    It is the structure's reference traversal: the conformance tests pair every builder
    with it and the study counts its steps. Queries that name no traversal use
    :func:`query_traversal`.
    """
    return _default("traversal", structure)


#: The traversal a query uses when it names none, where it is not the structure's
#: default (reference) one: the fastest correct CPU traversal, measured on the preset
#: and other cameras of the benchmark scenes (docs/performance.md, "The default
#: query traversal").
FASTEST_TRAVERSAL = {"bvh2": "bvh2.wide"}
#: The traversal a query uses when it names none and its batch is coherent: faster than
#: :data:`FASTEST_TRAVERSAL` on camera and shadow rays, slower on diffuse bounces
#: (docs/performance.md, "The default query traversal").
COHERENT_TRAVERSAL = {"bvh2": "bvh2.packet"}
#: The share of coherent packets (:func:`rayaccel.rays.coherence.packet_coherence`) from
#: which a batch counts as coherent.
COHERENT_SHARE = 0.5


def query_traversal(structure: str, coherence: float | None = None) -> str:
    """Return the traversal ``Accel.trace``, ``intersect`` and ``occluded`` use by default.

    For a batch whose ``coherence`` (the share of its packets that are coherent, when
    measured) reaches :data:`COHERENT_SHARE`, the structure's packet traversal
    (:data:`COHERENT_TRAVERSAL`); otherwise the fastest correct CPU traversal of
    ``structure`` (:data:`FASTEST_TRAVERSAL`), else its default traversal.
    """
    coherent = COHERENT_TRAVERSAL.get(structure)
    if coherent is not None and coherence is not None and coherence >= COHERENT_SHARE:
        return coherent
    fastest = FASTEST_TRAVERSAL.get(structure)
    if fastest is not None and get(fastest, "traversal").structure == structure:
        return fastest
    return default_traversal(structure)


def pausable(structure: str) -> tuple[str, Callable[..., Any]]:
    """Return ``(key, start)`` of the pausable traversal of ``structure``.

    Raises
    ------
    InvalidInputError
        No traversal of ``structure`` can pause and resume.
    """
    _load()
    for key in sorted(PAUSABLE):
        if REGISTRY[key].structure == structure:
            return key, PAUSABLE[key]
    raise InvalidInputError(
        f"no traversal of {structure!r} can pause and resume "
        f"(pausable: {', '.join(sorted(PAUSABLE)) or 'none'})"
    )


def configurations() -> list[str]:
    """Return :data:`CONFIGURATIONS` (each checked to resolve to a builder chain)."""
    for key in CONFIGURATIONS:
        get_chain(key)
    return list(CONFIGURATIONS)


def build_keys() -> list[str]:
    """Return every plain builder key, then the composed configurations not among them."""
    plain = keys("builder")
    return plain + [key for key in configurations() if key not in plain]


def get(key: str, role: Role | None = None) -> Variant:
    """Return the variant ``key``; unknown keys raise with close matches."""
    _load()
    variant = REGISTRY.get(key)
    if variant is None or (role is not None and variant.role != role):
        candidates = keys(role)
        close = difflib.get_close_matches(key, candidates, n=3, cutoff=0.5)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        kind = role or "variant"
        raise UnknownVariantError(f"unknown {kind} {key!r}{hint} (known: {', '.join(candidates)})")
    return variant


def get_chain(key: str) -> tuple[Variant, list[Variant]]:
    """Split a build key ``builder[+step...]`` into the builder and its steps, in order.

    ``"bvh2.lbvh+reinsert"`` gives the ``bvh2.lbvh`` builder and the ``bvh2+reinsert``
    step. Unknown builders and steps, and steps of another structure, raise with
    close matches.
    """
    base, *names = key.split(STEP_SEPARATOR)
    builder = get(base, "builder")
    steps = []
    for name in names:
        step_key = f"{builder.structure}{STEP_SEPARATOR}{name}"
        if step_key not in REGISTRY or REGISTRY[step_key].role != "step":
            known = [v.key.split(STEP_SEPARATOR, 1)[1] for v in variants("step", builder.structure)]
            close = difflib.get_close_matches(name, known, n=3, cutoff=0.5)
            hint = f"; did you mean {', '.join(close)}?" if close else ""
            raise UnknownVariantError(
                f"unknown build step {name!r} for {builder.structure!r} in {key!r}{hint} "
                f"(known: {', '.join(known) or 'none'})"
            )
        steps.append(REGISTRY[step_key])
    return builder, steps
