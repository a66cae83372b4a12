"""Internal imports inside functions say why (issue 33): an import of a ``navcrafter`` module (absolute or relative)
inside a function of flows/ tasks/ schemas/ models/ is there only to defer a heavy dependency on purpose, and says so
in a one-line ``# deferred: <reason>`` comment directly above it, or above an earlier import of the contiguous group
of imports it belongs to (the reason then covers the rest of the group). Any other internal import belongs at the
module's top, where the import contract (``lint-imports``) sees it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("flows", "tasks", "schemas", "models")
MARK = "# deferred:"
# only a file with an indented internal import can fail: the others are not parsed (keeps the walk well under 2 s)
INDENTED_INTERNAL = re.compile(r"^[ \t]+(from[ \t]+(navcrafter\b|\.)|import[ \t]+navcrafter\b)", re.MULTILINE)


def _internal(node: ast.Import | ast.ImportFrom) -> bool:
    if isinstance(node, ast.ImportFrom):
        return node.level > 0 or (node.module or "").split(".")[0] == "navcrafter"
    return any(alias.name.split(".")[0] == "navcrafter" for alias in node.names)


def _marked(lines: list[str], node: ast.stmt) -> bool:
    return node.lineno >= 2 and lines[node.lineno - 2].strip().startswith(MARK)


def _blocks(node: ast.AST):
    """The statement lists directly inside ``node`` (bodies, else / finally branches, except and case clauses)."""
    for field in ("body", "orelse", "finalbody"):
        stmts = getattr(node, field, None)
        if isinstance(stmts, list) and stmts and isinstance(stmts[0], ast.stmt):
            yield stmts
    for clause in (*getattr(node, "handlers", ()), *getattr(node, "cases", ())):
        yield clause.body


def unexplained(source: str, name: str) -> list[str]:
    """``name:line`` of each in-function internal import of ``source`` without a ``# deferred:`` reason."""
    lines = source.splitlines()
    found: list[str] = []

    def visit(stmts: list[ast.stmt], in_function: bool) -> None:
        covered = False  # a reason above this import or an earlier one of its contiguous group
        for st in stmts:
            if isinstance(st, (ast.Import, ast.ImportFrom)):
                covered = covered or _marked(lines, st)
                if in_function and _internal(st) and not covered:
                    found.append(f"{name}:{st.lineno}")
            else:
                covered = False
            inner = in_function or isinstance(st, (ast.FunctionDef, ast.AsyncFunctionDef))
            for block in _blocks(st):
                visit(block, inner)

    visit(ast.parse(source).body, False)
    return found


def test_every_in_function_internal_import_says_why():
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]
    assert len(files) > 50  # the walk found the packages
    missing = []
    for path in files:
        rel = path.relative_to(ROOT).as_posix()
        source = path.read_text(encoding="utf-8")
        if INDENTED_INTERNAL.search(source):
            missing += unexplained(source, rel)
    assert not missing, (f"{len(missing)} internal import(s) inside functions without a one-line `{MARK} <reason>` "
                         "comment above them: move each to the module's top, or say which heavy dependency it "
                         "defers:\n  " + "\n  ".join(missing))


GOOD_GROUP = """
def f():
    # deferred: torch loads only when exporting
    import json
    from navcrafter.models import a
    from navcrafter.models import b
"""


@pytest.mark.parametrize(("source", "expected"), [
    ("from navcrafter.models import a\n", []),  # the module's top: not deferred
    ("def f():\n    import json\n    import numpy\n", []),  # not internal
    ("def f():\n    from navcrafter.models import a\n", ["m.py:2"]),
    ("def f():\n    # deferred: torch loads only when exporting\n    from navcrafter.models import a\n", []),
    (GOOD_GROUP, []),
    ("def f():\n    import json\n    # deferred: torch\n    from navcrafter.models import a\n    from .b import c\n",
     []),  # the reason covers the rest of its group
    ("def f():\n    from navcrafter.models import a\n    # deferred: torch\n    from navcrafter.models import b\n",
     ["m.py:2"]),  # but not the imports above it
    ("def f():\n    # deferred: torch\n\n    from navcrafter.models import a\n", ["m.py:4"]),  # not directly above
    ("def f():\n    # deferred: torch\n    import navcrafter.models\n    x = 1\n    from navcrafter.models import b\n",
     ["m.py:5"]),  # a second group needs its own reason
    ("def f():\n    from . import sibling\n", ["m.py:2"]),  # relative imports are internal
    ("class C:\n    def m(self):\n        if True:\n            from navcrafter.tasks import t\n", ["m.py:4"]),
    ("def f():\n    try:\n        pass\n    except ImportError:\n        from navcrafter.models import a\n",
     ["m.py:5"]),
    ("def f():\n    # a comment, not a reason\n    from navcrafter.models import a\n", ["m.py:3"]),
])
def test_the_check_finds_unexplained_imports(source, expected):
    assert unexplained(source, "m.py") == expected
