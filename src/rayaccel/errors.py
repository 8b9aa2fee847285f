"""The one exception hierarchy of rayaccel (STYLE §7).

Kernels never raise; wrappers validate at the Python boundary and raise one of
these with a message naming the argument, the expectation and the value received.
"""

from __future__ import annotations


class RayAccelError(Exception):
    """Base class of every error rayaccel raises on purpose."""


class InvalidInputError(RayAccelError, ValueError):
    """An argument has the wrong shape, dtype, range or content."""


class SceneFileError(InvalidInputError):
    """A scene file is missing or malformed; the message names the path (and line)."""


class AccelFileError(SceneFileError):
    """A saved accel file is missing, truncated, tampered with, foreign or of another version."""


class UnknownVariantError(RayAccelError, KeyError):
    """A registry key or an option name is unknown; the message suggests close matches."""

    def __str__(self) -> str:
        # KeyError.__str__ quotes its argument; show the message as written instead.
        return str(self.args[0]) if self.args else ""


class StructureInvariantError(RayAccelError):
    """``validate()`` found a broken invariant in an acceleration structure."""


class TraversalOverflowError(RayAccelError):
    """A traversal ran out of its fixed stack (the tree is deeper than the stack)."""


class BackendUnavailableError(RayAccelError, ImportError):
    """An optional dependency is missing; the message names the extra to install."""
