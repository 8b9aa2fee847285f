"""Numpydoc sections shared by several functions, written once and added to each docstring.

Builders and traversals get their shared ``Parameters`` and ``Returns`` from the registry
(:func:`rayaccel._variant.with_shared_sections`); other families of functions with the
same arguments take theirs with :func:`with_sections`.
"""

from __future__ import annotations

import inspect
import re
from collections.abc import Callable
from typing import Any, TypeVar

F = TypeVar("F", bound=Callable[..., Any])

#: A numpydoc section header: a title line underlined with dashes.
SECTION = re.compile(r"^\w[\w ]*\n-{3,}$", re.MULTILINE)


def insert_sections(func: Callable[..., Any], sections: str) -> None:
    """Add ``sections`` to ``func``'s docstring, before its own sections (if any).

    A docstring that has its own ``Parameters`` section, or none at all, is left as it is.
    """
    doc = inspect.cleandoc(func.__doc__ or "")
    if not doc or not sections or re.search(r"^Parameters\n-{3,}$", doc, re.MULTILINE):
        return
    match = SECTION.search(doc)
    at = match.start() if match else len(doc)
    head = doc[:at].rstrip()
    tail = doc[at:].strip()
    func.__doc__ = "\n\n".join(part for part in (head, sections.strip(), tail) if part) + "\n"


def with_sections(sections: str) -> Callable[[F], F]:
    """Return a decorator that adds ``sections`` to a function's docstring (see above)."""

    def decorate(func: F) -> F:
        insert_sections(func, sections)
        return func

    return decorate
