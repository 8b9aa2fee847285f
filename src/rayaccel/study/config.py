"""A sweep's configuration: a TOML file naming scenes, builders, traversals, ray sets and threads.

Example (``benchmarks/study/bundled.toml`` is the committed one)::

    scenes = ["cornell-box", "teapot"]
    builders = ["bvh2.binned_sah", "bvh2.sbvh+reinsert", "kdtree.sah", "grid.uniform",
                {key = "bvh2.binned_sah", max_leaf_size = 2}]   # a builder with options
    traversals = "all"            # or a list; each builder runs its structure's traversals
    # traversals = ["bvh2.stack", {key = "bvh2.restart_trail", short_stack = 3}]
    threads = [2]
    peers = ["embree"]            # timed round-robin with each timing cell, on its rays
    repeats = 5                   # timed passes per timing cell
    build_repeats = 3
    validate = 200                # rays per cell checked against the oracle
    passes = ["build", "counters", "timing"]   # the kinds of cell to run (all by default)

    [rays]
    kinds = ["path", "primary", "diffuse", "shadow"]
    width = 128
    height = 96
    seed = 0

    [rays.path]                   # the path tracer's recorded sets
    spp = 2
    max_depth = 2

Ray-set kinds: ``primary``, ``diffuse``, ``shadow`` are the benchmark's generated
sets (:mod:`rayaccel.bench.raysets`); ``path`` renders the scene with the path
tracer and records its rays (:mod:`rayaccel.study.recording`), giving the sets
``path-primary``, ``path-bounce`` (every depth) and ``path-shadow``.

A builder or traversal given as an inline table ``{key = ..., option = value}``
runs with those options (a step's options are a table named after the step:
``{key = "bvh2.lbvh+reinsert", reinsert = {iterations = 2}}``); its label in the
results and the report is ``key[option=value,...]`` (:func:`variant_label`), so one
sweep can compare, say, short stacks of 1, 3 and 8 entries.

Every name and option is checked before any work starts; an error names the file's line.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from rayaccel import registry
from rayaccel.api import check_build_options
from rayaccel.bench.peers import peer_names
from rayaccel.errors import InvalidInputError, UnknownVariantError
from rayaccel.scene import catalog

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: The ray-set kinds a sweep knows, and the query each is traced with.
GENERATED_KINDS = ("primary", "diffuse", "shadow")
PATH_SETS = {"path-primary": "closest", "path-bounce": "closest", "path-shadow": "any"}
QUERIES = {"primary": "closest", "diffuse": "closest", "shadow": "any", **PATH_SETS}

_TOP_KEYS = {"scenes", "builders", "traversals", "threads", "peers", "repeats",
             "build_repeats", "validate", "rays", "passes"}  # fmt: skip
#: The kinds of cell a sweep may run.
PASSES = ("build", "counters", "timing")
_RAY_KEYS = {"kinds", "width", "height", "seed", "path"}
_PATH_KEYS = {"spp", "max_depth", "rr_depth"}


class ConfigError(InvalidInputError):
    """A sweep configuration that names something unknown or holds a bad value."""


@dataclass(frozen=True, slots=True)
class RayConfig:
    """The ray sets of every scene."""

    kinds: tuple[str, ...] = ("primary", "diffuse", "shadow")
    width: int = 128
    height: int = 96
    seed: int = 0
    spp: int = 2
    max_depth: int = 2
    rr_depth: int = 2

    def digest(self) -> str:
        """Return a short hash of the parameters the rays depend on (part of cell keys)."""
        text = json.dumps(asdict(self), sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:10]

    def set_names(self) -> list[str]:
        """Return the names of the ray sets, in report order."""
        names: list[str] = []
        for kind in self.kinds:
            names += list(PATH_SETS) if kind == "path" else [kind]
        return names


@dataclass(frozen=True, slots=True)
class SweepConfig:
    """A whole sweep (see the module docstring for the file format)."""

    scenes: tuple[str, ...]
    builders: tuple[str, ...]
    traversals: dict[str, tuple[str, ...]]
    threads: tuple[int, ...] = (2,)
    peers: tuple[str, ...] = ()
    repeats: int = 5
    build_repeats: int = 3
    validate: int = 200
    rays: RayConfig = field(default_factory=RayConfig)
    passes: tuple[str, ...] = PASSES
    #: The registry key and options behind each builder or traversal label that has
    #: options (:func:`variant_label`); a plain key stands for itself.
    variants: dict[str, tuple[str, dict[str, Any]]] = field(default_factory=dict)

    def variant(self, label: str) -> tuple[str, dict[str, Any]]:
        """Return the registry key and options of a builder or traversal label."""
        key, options = self.variants.get(label, (label, {}))
        return key, dict(options)

    def as_record(self) -> dict[str, Any]:
        """Return the configuration as JSON-ready values (stored in the results header)."""
        record = asdict(self)
        record["traversals"] = {k: list(v) for k, v in self.traversals.items()}
        return record


def _line_of(text: str, needle: str) -> int | None:
    """Return the 1-based line where ``needle`` (a key or a quoted value) first stands."""
    for number, line in enumerate(text.splitlines(), start=1):
        if needle in line.split("#", 1)[0]:
            return number
    return None


def _fail(source: str, text: str, message: str, needle: str | None) -> ConfigError:
    line = _line_of(text, needle) if needle else None
    where = f"{source}:{line}" if line else source
    return ConfigError(f"{where}: {message}")


def _as_list(value: Any, name: str, source: str, text: str) -> list[Any]:
    if isinstance(value, str):
        return [value]
    if not isinstance(value, list) or not value:
        raise _fail(source, text, f"{name}: expected a non-empty list", name)
    return value


def _positive(value: Any, name: str, source: str, text: str, low: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise _fail(source, text, f"{name}: expected an integer >= {low}, got {value!r}", name)
    return value


def variant_label(key: str, options: dict[str, Any]) -> str:
    """Return the label of ``key`` with ``options``: ``key[a=1,b=true]`` (sorted, JSON values)."""
    if not options:
        return key
    items = ",".join(f"{k}={json.dumps(v, sort_keys=True)}" for k, v in sorted(options.items()))
    return f"{key}[{items}]"


def _variants(
    entries: list[Any], name: str, source: str, text: str
) -> list[tuple[str, str, dict[str, Any]]]:
    """Return ``(label, key, options)`` for each entry: a key, or a table with ``key``."""
    out: list[tuple[str, str, dict[str, Any]]] = []
    for entry in entries:
        if isinstance(entry, str):
            out.append((entry, entry, {}))
            continue
        if not isinstance(entry, dict) or not isinstance(entry.get("key"), str):
            raise _fail(source, text, f"{name}: expected a key or a table with a 'key', "
                        f"got {entry!r}", name)  # fmt: skip
        options = {k: v for k, v in entry.items() if k != "key"}
        out.append((variant_label(entry["key"], options), entry["key"], options))
    return out


def parse_config(text: str, source: str = "<config>") -> SweepConfig:
    """Parse and check a sweep configuration written in TOML.

    Raises
    ------
    ConfigError
        Naming ``source`` and the line: a TOML syntax error, an unknown key, scene,
        builder, traversal, peer or ray-set kind, or a bad number.
    """
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: {exc}") from exc
    for key in raw:
        if key not in _TOP_KEYS:
            raise _fail(source, text, f"unknown key {key!r} (keys: {sorted(_TOP_KEYS)})", key)
    if "scenes" not in raw or "builders" not in raw:
        raise ConfigError(f"{source}: 'scenes' and 'builders' are required")
    scenes = [str(s) for s in _as_list(raw["scenes"], "scenes", source, text)]
    for scene in scenes:
        try:
            catalog.resolve(scene)
        except (UnknownVariantError, InvalidInputError) as exc:
            raise _fail(source, text, str(exc), f'"{scene}"') from exc
    listed_builders = _as_list(raw["builders"], "builders", source, text)
    if listed_builders == ["all"]:
        listed_builders = list(registry.build_keys())
    variants: dict[str, tuple[str, dict[str, Any]]] = {}
    builders: list[str] = []
    for label, key, options in _variants(listed_builders, "builders", source, text):
        try:
            check_build_options(key, options)
        except (UnknownVariantError, InvalidInputError) as exc:
            raise _fail(source, text, str(exc), f'"{key}"') from exc
        builders.append(label)
        if options:
            variants[label] = (key, options)
    wanted = _as_list(raw.get("traversals", "all"), "traversals", source, text)
    listed_traversals = _variants([w for w in wanted if w != "all"], "traversals", source, text)
    structure_of: dict[str, str] = {}
    for label, key, options in listed_traversals:
        try:
            structure_of[label] = registry.get(key, "traversal").structure
            registry.get(key, "traversal").make_options(options)
        except (UnknownVariantError, InvalidInputError) as exc:
            raise _fail(source, text, str(exc), f'"{key}"') from exc
        if options:
            variants[label] = (key, options)
    traversals: dict[str, tuple[str, ...]] = {}
    for builder in builders:
        structure = registry.get_chain(variants.get(builder, (builder, {}))[0])[0].structure
        own = registry.keys("traversal", structure) if "all" in wanted else []
        chosen = own + [label for label, _, _ in listed_traversals
                        if structure_of[label] == structure and label not in own]  # fmt: skip
        if not chosen:
            raise _fail(source, text, f"no listed traversal runs on {builder!r}",
                        f'"{builder}"')  # fmt: skip
        traversals[builder] = tuple(chosen)
    listed = _as_list(raw.get("threads", [2]), "threads", source, text)
    threads = tuple(_positive(t, "threads", source, text) for t in listed)
    peers = tuple(str(p) for p in raw.get("peers", []))
    for peer in peers:
        if peer not in peer_names():
            raise _fail(source, text, f"unknown peer {peer!r} (peers: {peer_names()})",
                        f'"{peer}"')  # fmt: skip
    rays = _parse_rays(raw.get("rays", {}), source, text)
    passes = [str(p) for p in _as_list(raw.get("passes", list(PASSES)), "passes", source, text)]
    for name in passes:
        if name not in PASSES:
            raise _fail(source, text, f"unknown pass {name!r} (passes: {list(PASSES)})",
                        f'"{name}"')  # fmt: skip
    return SweepConfig(
        scenes=tuple(scenes),
        builders=tuple(builders),
        traversals=traversals,
        threads=threads,
        peers=peers,
        repeats=_positive(raw.get("repeats", 5), "repeats", source, text),
        build_repeats=_positive(raw.get("build_repeats", 3), "build_repeats", source, text),
        validate=_positive(raw.get("validate", 200), "validate", source, text, low=0),
        rays=rays,
        passes=tuple(p for p in PASSES if p in passes),
        variants=variants,
    )


def _parse_rays(raw: Any, source: str, text: str) -> RayConfig:
    if not isinstance(raw, dict):
        raise _fail(source, text, "rays: expected a table", "rays")
    for key in raw:
        if key not in _RAY_KEYS:
            raise _fail(source, text, f"rays: unknown key {key!r} (keys: {sorted(_RAY_KEYS)})",
                        key)  # fmt: skip
    kinds = [str(k) for k in _as_list(raw.get("kinds", list(GENERATED_KINDS)), "kinds", source,
                                      text)]  # fmt: skip
    for kind in kinds:
        if kind not in (*GENERATED_KINDS, "path"):
            raise _fail(source, text, f"rays: unknown kind {kind!r} (kinds: "
                        f"{[*GENERATED_KINDS, 'path']})", f'"{kind}"')  # fmt: skip
    path = raw.get("path", {})
    if not isinstance(path, dict):
        raise _fail(source, text, "rays.path: expected a table", "path")
    for key in path:
        if key not in _PATH_KEYS:
            raise _fail(source, text, f"rays.path: unknown key {key!r}", key)
    return RayConfig(
        kinds=tuple(dict.fromkeys(kinds)),
        width=_positive(raw.get("width", 128), "width", source, text),
        height=_positive(raw.get("height", 96), "height", source, text),
        seed=_positive(raw.get("seed", 0), "seed", source, text, low=0),
        spp=_positive(path.get("spp", 2), "spp", source, text),
        max_depth=_positive(path.get("max_depth", 2), "max_depth", source, text, low=0),
        rr_depth=_positive(path.get("rr_depth", 2), "rr_depth", source, text),
    )


def load_config(path: str | os.PathLike[str]) -> SweepConfig:
    """Read and check a sweep configuration file.

    Raises
    ------
    ConfigError
        When the file cannot be read or is not a valid configuration.
    """
    source = Path(path)
    try:
        text = source.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{source}: cannot read ({exc})") from exc
    return parse_config(text, str(source))
