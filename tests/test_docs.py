"""Cheap checks of the user-facing pages (``make docs`` builds and checks the site itself).

README.md is also the package's PyPI page: it stays short, its links into ``docs/``
resolve, and nothing users receive points at folders outside the repository.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MAX_README_LINES = 200
#: A path outside the repository that only the developers' machines have.
OUTSIDE = "../shared"
#: Tracked paths allowed to mention it: test and benchmark discovery of the scene folder.
ALLOWED_PREFIXES = ("tests/", "benchmarks/", ".ci/")
ALLOWED_FILES = ("Makefile",)
#: Markdown link targets: ``[text](target)`` (an optional ``#anchor`` is dropped).
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)\s]*)?\)")


def test_readme_is_short():
    n_lines = len(README.read_text(encoding="utf-8").splitlines())
    assert n_lines <= MAX_README_LINES, (
        f"README.md has {n_lines} lines (at most {MAX_README_LINES}); move detail into docs/"
    )


def test_readme_has_no_outside_paths():
    assert OUTSIDE not in README.read_text(encoding="utf-8")


def test_readme_links_into_docs_exist():
    targets = LINK.findall(README.read_text(encoding="utf-8"))
    docs_links = [t for t in targets if t.startswith("docs/")]
    assert docs_links, "README.md should link to the docs pages"
    missing = [t for t in docs_links if not (REPO / t).is_file()]
    assert not missing, f"README.md links to missing files: {missing}"


def _tracked_files() -> list[str]:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout")
    result = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True)
    return [name for name in result.stdout.decode().split("\0") if name]


def test_no_tracked_file_points_outside_the_repository():
    offenders = []
    for name in _tracked_files():
        if name.startswith(ALLOWED_PREFIXES) or name in ALLOWED_FILES:
            continue
        path = REPO / name
        if not path.is_file():  # deleted in the working tree, not yet committed
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:  # binary file
            continue
        if OUTSIDE in text:
            offenders.append(name)
    assert not offenders, f"these tracked files mention {OUTSIDE!r}: {offenders}"
