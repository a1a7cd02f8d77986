"""docs/paper.md stays true as the code changes: every module it names exists and defines every name it cites.

A reference is a backticked ``condtrack_cli/...py`` path, optionally followed by ``: name`` (or
``: Class.method``, or several names separated by commas). The names are looked up with ``ast`` in the
module's source: a top-level function, class or assignment, or a method/attribute of a top-level class.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = ("docs/paper.md",)
#: `condtrack_cli/x/y.py` or `condtrack_cli/x/y.py: Name, Other.method`
REFERENCE = re.compile(r"`(condtrack_cli/[\w/]+\.py)(?::\s*([\w.]+(?:\s*,\s*[\w.]+)*))?`")


def references(text: str) -> list[tuple[str, list[str]]]:
    """(module path, [names]) of every reference in ``text``."""
    return [(path, [n.strip() for n in names.split(",")] if names else []) for path, names in REFERENCE.findall(text)]


def _assigned(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Assign):
        return [t.id for t in node.targets if isinstance(t, ast.Name)]
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
        return [node.target.id]
    return []


def definitions(source: str) -> set[str]:
    """Top-level names (functions, classes, assignments) and ``Class.member`` for members of top-level classes."""
    names: set[str] = set()
    for node in ast.parse(source).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
            if isinstance(node, ast.ClassDef):
                for member in node.body:
                    if isinstance(member, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                        names.add(f"{node.name}.{member.name}")
                    names.update(f"{node.name}.{n}" for n in _assigned(member))
        names.update(_assigned(node))
    return names


def test_the_reference_pattern():
    text = "see `condtrack_cli/filters/cnlf.py: propagate` and `condtrack_cli/a/b.py: X.y, z` and `condtrack_cli/c.py`"
    assert references(text) == [("condtrack_cli/filters/cnlf.py", ["propagate"]),
                                ("condtrack_cli/a/b.py", ["X.y", "z"]), ("condtrack_cli/c.py", [])]
    source = "A = 1\ndef f(): pass\nclass C:\n    k: int = 2\n    def m(self): pass\n"
    assert definitions(source) == {"A", "f", "C", "C.k", "C.m"}


@pytest.mark.parametrize("doc", DOCS)
def test_every_module_and_name_the_doc_cites_exists(doc):
    found = references((REPO / doc).read_text(encoding="utf-8"))
    assert len(found) >= 50, f"{doc}: expected the module references to be found, got {len(found)}"
    missing = []
    sources: dict[str, set[str]] = {}
    for path, names in found:
        module = REPO / path
        if not module.is_file():
            missing.append(f"{path}: no such file")
            continue
        if path not in sources:
            sources[path] = definitions(module.read_text(encoding="utf-8"))
        missing += [f"{path}: {name} is not defined there" for name in names if name not in sources[path]]
    assert not missing, f"{doc} cites what the code does not have:\n" + "\n".join(sorted(set(missing)))


def test_the_readme_links_the_paper_page():
    assert "docs/paper.md" in (REPO / "README.md").read_text(encoding="utf-8")
