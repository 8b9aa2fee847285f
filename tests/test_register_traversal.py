"""Every registered CPU traversal has the public form ``register_traversal`` gives it."""

from __future__ import annotations

import inspect

import pytest

from rayaccel import registry

TRAVERSALS = [v for v in registry.variants("traversal") if v.backend == "cpu"]


@pytest.mark.parametrize("variant", TRAVERSALS, ids=lambda v: v.key)
def test_public_signature_and_docstring(variant):
    signature = inspect.signature(variant.func)
    names = list(signature.parameters)
    assert names[1:] == ["mesh", "rays", "query", "stats", "options", "cache"]
    keyword = [p.name for p in signature.parameters.values() if p.kind is p.KEYWORD_ONLY]
    assert keyword == ["query", "stats", "options", "cache"]
    assert signature.parameters["query"].default == "closest"
    assert signature.parameters["options"].annotation == f"{variant.options.__name__} | None"
    assert signature.return_annotation == "HitBatch"
    assert variant.func.__name__ == "trace_" + variant.key.replace(".", "_")
    doc = variant.func.__doc__
    assert "Parameters\n----------" in doc
    assert f"options : {variant.options.__name__}" in doc
    assert "Returns\n-------\nHitBatch" in doc
