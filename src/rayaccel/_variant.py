"""Variant records and the ``register`` decorator (layer 0, so every family can register).

:mod:`rayaccel.registry` (layer 5) loads the built-in modules and looks variants up;
this module only holds the table, so structure modules can register themselves
without importing upward.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import re
import typing
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from rayaccel._docstrings import SECTION, insert_sections
from rayaccel.errors import InvalidInputError, UnknownVariantError

Role = Literal["builder", "traversal", "step"]
#: When a build step runs: ``"before"`` the builder (it returns the references the builder
#: builds over) or ``"after"`` it (a post-process of the built structure).
Stage = Literal["before", "after"]

#: Separates a builder key from the build steps chained after it (``bvh2.lbvh+reinsert``).
STEP_SEPARATOR = "+"


@dataclass(frozen=True, slots=True)
class Variant:
    """A registered builder or traversal.

    Attributes
    ----------
    key : str
        ``<structure>.<algorithm or method>``; a step is ``<structure>+<name>``.
    role : {"builder", "traversal", "step"}
    structure : str
        The structure the variant builds or traverses (``"bvh2"``).
    func : callable
        Builder: ``func(mesh, options) -> structure``; a builder that can build over
        pre-split references also takes ``refs=`` (:attr:`takes_refs`). Step of stage
        ``"after"``: ``func(structure, mesh, options) -> structure`` (a post-process
        chained after a builder). Step of stage ``"before"``: ``func(mesh, options) ->
        BuildRefs`` (:mod:`rayaccel.bvh.builders.refs`), the references the builder then
        builds over. Traversal: see :mod:`rayaccel.api`.
    options : type
        Frozen dataclass of keyword options with defaults.
    summary : str
        One line for ``rayaccel list``.
    reference : str
        The paper it implements.
    backend : {"cpu", "cuda"}
    stage : {"before", "after"}
        When a step runs relative to the builder (see ``func``); ``"after"`` for
        builders and traversals.
    default : bool
        The builder or traversal used for its structure when none is named (one of
        each per structure; the conformance tests pair every variant with it).
    """

    key: str
    role: Role
    structure: str
    func: Callable[..., Any]
    options: type
    summary: str
    reference: str = ""
    backend: Literal["cpu", "cuda"] = "cpu"
    stage: Stage = "after"
    default: bool = False

    @property
    def takes_refs(self) -> bool:
        """Whether this builder accepts ``refs=`` (references made by a ``"before"`` step)."""
        try:
            parameters = inspect.signature(self.func).parameters
        except (TypeError, ValueError):
            return False
        return self.role == "builder" and "refs" in parameters

    def make_options(self, values: Mapping[str, Any] | None = None) -> Any:
        """Return ``options(**values)``; unknown names raise with a suggestion."""
        values = dict(values or {})
        names = [f.name for f in dataclasses.fields(self.options)]
        for name in values:
            if name not in names:
                close = difflib.get_close_matches(name, names, n=3)
                hint = f"; did you mean {', '.join(close)}?" if close else ""
                known = ", ".join(names) if names else "none"
                raise UnknownVariantError(
                    f"{self.key}: unknown option {name!r}{hint} (options: {known})"
                )
        hints = _option_types(self.options)
        coerced = {name: coerce_option(self.key, name, value, hints.get(name))
                   for name, value in values.items()}  # fmt: skip
        try:
            return self.options(**coerced)
        except TypeError as exc:
            raise InvalidInputError(f"{self.key}: {exc}") from exc


@functools.cache
def _option_types(options: type) -> dict[str, Any]:
    """Return the resolved annotation of each field of an options dataclass."""
    return typing.get_type_hints(options)


def coerce_option(key: str, name: str, value: Any, kind: Any) -> Any:
    """Return ``value`` as the plain Python value of the option's annotated type.

    One check for every option of every variant, so no builder or traversal sees a
    value of the wrong type: an ``int`` option takes an integer (Python or numpy, not
    a bool and not a float, which would be truncated), a ``float`` option a real
    number that is not NaN (ints are widened), a ``bool`` option ``True`` or
    ``False`` only (so ``"no"`` is not taken as true), a ``str`` option a string.
    Range checks stay with each options class (``__post_init__``).

    Raises
    ------
    InvalidInputError
        Naming the variant, the option, the value and the type it needs.
    """

    def fail(expected: str) -> InvalidInputError:
        return InvalidInputError(
            f"{key}: option {name!r} expects {expected}, got {value!r} ({type(value).__name__})"
        )

    if kind is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        raise fail("True or False")
    if kind is int:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise fail("an integer")
        return int(value)
    if kind is float:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer,
                                                                         np.floating)):  # fmt: skip
            raise fail("a number")
        if np.isnan(value):
            raise fail("a number, not NaN")
        return float(value)
    if kind is str and not isinstance(value, str):
        raise fail("a string")
    return value


#: The numpydoc sections every traversal shares (they all take the same arguments), which
#: :func:`register` adds to its docstring: ``{name}`` and ``{kind}`` are the first
#: parameter's name and type, ``{options}`` the options class.
TRAVERSAL_SECTIONS = """\
Parameters
----------
{name} : {kind}
    The structure to trace; the layouts derived from it are memoised in ``cache``.
mesh : TriangleMesh
    The mesh ``{name}`` was built over.
rays : RayBatch
    The rays to trace.
query : {{"closest", "any"}}
    ``"any"`` stops each ray at the first hit found.
stats : bool
    Also return per-ray counters in ``hits.stats``.
options : {options}, optional
    The traversal's options (their defaults when None).
cache : dict, optional
    Memo for the derived layouts (an ``Accel`` passes its own).

Returns
-------
HitBatch
    For ``query="any"``, ``prim >= 0`` marks occluded rays (some hit, not the closest).
"""

#: The numpydoc sections every builder shares, added by :func:`register` like
#: :data:`TRAVERSAL_SECTIONS` (``{refs}``: the ``refs`` entry, for builders that take it).
BUILDER_SECTIONS = """\
Parameters
----------
mesh : TriangleMesh
    The mesh to build over.
options : {options}, optional
    The builder's options (their defaults when None).
{refs}
Returns
-------
{kind}
    The canonical structure.
"""

_REFS_ENTRY = """\
refs : BuildRefs, optional
    References to build over (e.g. pre-split triangle parts); default one per triangle.
"""

def _type_name(annotation: Any) -> str:
    """Return a numpydoc type for an annotation (``"A | B | None"`` -> ``"A or B"``)."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", "")
    names = [name.strip() for name in str(text).split("|") if name.strip() != "None"]
    return " or ".join(filter(None, (", ".join(names[:-1]), names[-1])))


def shared_sections(func: Callable[..., Any], role: Role) -> str:
    """Return the numpydoc sections a ``role`` variant shares with its kind ("" for steps)."""
    signature = inspect.signature(func)
    parameters = list(signature.parameters.values())
    if role == "step" or "options" not in signature.parameters:
        return ""
    options = _type_name(signature.parameters["options"].annotation)
    if role == "traversal":
        first = parameters[0]
        return TRAVERSAL_SECTIONS.format(
            name=first.name, kind=_type_name(first.annotation), options=options
        )
    refs = _REFS_ENTRY if "refs" in signature.parameters else ""
    return BUILDER_SECTIONS.format(
        options=options, refs=refs, kind=_type_name(signature.return_annotation)
    )


def with_shared_sections(func: Callable[..., Any], role: Role) -> None:
    """Add the shared sections to ``func``'s docstring (:func:`insert_sections`)."""
    insert_sections(func, shared_sections(func, role))


REGISTRY: dict[str, Variant] = {}
#: Traversals that can pause and resume, by key: ``start(structure, mesh, rays, cache=None)``
#: returns a state whose ``next_hits()`` resumes every ray (see :func:`register_pausable`).
PAUSABLE: dict[str, Callable[..., Any]] = {}


def annotated_options(func: Callable[..., Any]) -> type:
    """Return the options dataclass that ``func``'s ``options`` parameter is annotated with.

    ``options: SbvhOptions | None = None`` gives ``SbvhOptions``: a variant states its
    options type once, in its signature, and the registry reads it from there.
    """
    parameter = inspect.signature(func).parameters.get("options")
    annotation = getattr(parameter, "annotation", inspect.Parameter.empty)
    if isinstance(annotation, str):
        # A postponed annotation: the names it holds are the module's own.
        annotation = eval(annotation, func.__globals__)
    found = [t for t in typing.get_args(annotation) or (annotation,) if t is not type(None)]
    options = found[0] if len(found) == 1 else None
    if not isinstance(options, type) or not dataclasses.is_dataclass(options):
        raise TypeError(f"{func.__qualname__}: annotate 'options' with one options dataclass")
    return options


def docstring_summary(func: Callable[..., Any]) -> str:
    """Return the first line of ``func``'s docstring without its full stop.

    A variant says what it is once, in its docstring; the registry lists that line.
    """
    summary = inspect.cleandoc(func.__doc__ or "").partition("\n")[0].strip()
    if not summary:
        raise ValueError(f"{func.__qualname__}: a registered variant needs a docstring")
    return summary.removesuffix(".")


def docstring_reference(func: Callable[..., Any]) -> str:
    """Return the ``References`` section of ``func``'s docstring as one line ("" if none)."""
    doc = inspect.cleandoc(func.__doc__ or "")
    found = re.search(r"^References\n-{3,}\n", doc, re.MULTILINE)
    if found is None:
        return ""
    following = SECTION.search(doc, found.end())
    section = doc[found.end() : following.start() if following else len(doc)]
    return " ".join(section.split()).removesuffix(".")


def register(
    role: Role,
    key: str,
    *,
    options: type | None = None,
    backend: Literal["cpu", "cuda"] = "cpu",
    stage: Stage = "after",
    default: bool = False,
) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Return a decorator that registers ``func`` as the variant ``key``.

    ``options`` defaults to the dataclass ``func``'s ``options`` parameter is annotated
    with (:func:`annotated_options`). The summary that ``rayaccel list`` shows is the
    docstring's first line, the reference its ``References`` section
    (:func:`docstring_summary`, :func:`docstring_reference`).

    ``stage`` applies to steps only: ``"after"`` (default) for a post-process of the
    built structure, ``"before"`` for a step that makes the references the builder
    builds over (see :class:`Variant`). ``default`` marks the builder or traversal of
    its structure used when none is named. Builders and traversals, which share their
    arguments, have the shared numpydoc sections added to their docstrings
    (:func:`with_shared_sections`), so each docstring says only what is its own.
    """
    structure = key.replace(STEP_SEPARATOR, ".").split(".", 1)[0]
    if (role == "step") != (STEP_SEPARATOR in key):
        raise ValueError(f"variant {key!r}: steps, and only steps, are named <structure>+<name>")
    if stage not in ("before", "after") or (role != "step" and stage != "after"):
        raise ValueError(f"variant {key!r}: stage must be 'before' or 'after' (steps only)")
    if default and role == "step":
        raise ValueError(f"variant {key!r}: only builders and traversals can be the default")

    def decorate(func: Callable[..., Any]) -> Callable[..., Any]:
        if key in REGISTRY and REGISTRY[key].func is not func:
            raise ValueError(f"variant {key!r} registered twice")
        options_type = annotated_options(func) if options is None else options
        summary, reference = docstring_summary(func), docstring_reference(func)
        REGISTRY[key] = Variant(
            key, role, structure, func, options_type, summary, reference, backend, stage, default
        )
        with_shared_sections(func, role)
        return func

    return decorate


def register_pausable(key: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Return a decorator that registers ``start`` as the pausable form of traversal ``key``.

    ``start(structure, mesh, rays, cache=None)`` returns a state object whose
    ``next_hits()`` resumes every ray where it stopped and returns its next hit, and
    whose ``all_hits()`` collects every hit (Binder & Keller 2016, building block 5).
    """

    def decorate(start: Callable[..., Any]) -> Callable[..., Any]:
        if key in PAUSABLE and PAUSABLE[key] is not start:
            raise ValueError(f"pausable traversal {key!r} registered twice")
        PAUSABLE[key] = start
        return start

    return decorate
