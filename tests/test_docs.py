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


# --- README.md: the module list and the command summary cover the package and the command line (issue 47) ---


def readme_block(heading: str, fence: str) -> str:
    """The first ``fence`` code block (```text, ```sh) after ``heading`` in README.md."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index(f"{fence}\n", text.index(f"\n{heading}\n"))
    return text[start + len(fence) + 1:text.index("```", start + len(fence))]


def layout_sections(block: str) -> dict[str, str]:
    """The layout tree's entries under ``condtrack_cli/``: entry name (``api.py``, ``motion/``,
    ``frames/synthetic/``) -> its text (the entry's line and the deeper-indented lines after it)."""
    sections: dict[str, str] = {}
    name = None
    for line in block.splitlines()[1:]:
        entry = re.match(r"^  (\S+)", line)
        if entry:
            name = entry.group(1)
            sections[name] = line
        elif name is not None:
            sections[name] += "\n" + line
    return sections


def package_modules() -> list[str]:
    """Every module of the package, relative to ``condtrack_cli/`` (``motion/local/level.py``)."""
    package = REPO / "condtrack_cli"
    return sorted(str(path.relative_to(package)) for path in package.rglob("*.py")
                  if path.name != "__init__.py" or path.parent == package or path.parent.name == "cli")


def test_the_readme_layout_names_every_module():
    sections = layout_sections(readme_block("## How the code is laid out", "```text"))
    assert {"api.py", "cli/", "motion/", "frames/synthetic/"} <= set(sections)
    missing = []
    for module in package_modules():
        folder, _, name = module.rpartition("/")
        if not folder:
            found = module in sections
        else:
            owner = max((key for key in sections if (folder + "/").startswith(key)), key=len, default=None)
            rest = (folder + "/")[len(owner):] if owner else ""
            found = owner is not None and all(re.search(rf"(?<![\w/]){re.escape(part)}", sections[owner])
                                              for part in [*(f"{d}/" for d in rest.split("/") if d), name])
        if not found:
            missing.append(module)
    assert not missing, "README.md's layout does not name: " + ", ".join(missing)


def command_chunks(block: str) -> dict[str, str]:
    """The command summary's text per command: each ``condtrack NAME`` line with its continuation lines, and
    the OVERLAY OPTIONS placeholder replaced by the options its comment line lists."""
    chunks: dict[str, str] = {}
    name = None
    for line in block.splitlines():
        command = re.match(r"^condtrack (\w+)", line)
        if command:
            name = command.group(1)
            chunks[name] = chunks.get(name, "") + "\n" + line
        elif name is not None:
            chunks[name] += "\n" + line
    overlay = re.search(r"OVERLAY OPTIONS:(.*)", block)
    return {key: text.replace("[OVERLAY OPTIONS]", overlay.group(1) if overlay else "") for key, text in chunks.items()}


def test_the_readme_command_summary_names_every_option_of_every_command():
    import click

    from condtrack_cli.cli import cli

    chunks = command_chunks(readme_block("## The command line", "```sh"))
    context = click.Context(cli)
    missing = []
    for name in cli.list_commands(context):
        command = cli.get_command(context, name)
        if name not in chunks:
            missing.append(f"condtrack {name}")
            continue
        for option in command.params:
            if isinstance(option, click.Option) and not option.hidden and not any(
                    re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", chunks[name]) for flag in option.opts):
                missing.append(f"condtrack {name} {option.opts[-1]}")
    assert not missing, "README.md's command summary does not name: " + ", ".join(missing)


def test_the_readme_and_the_configs_cite_nothing_outside_the_repository():
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    assert "configs/paper.yaml" in readme
    for config in sorted((REPO / "configs").glob("*.yaml")):
        comments = "\n".join(line.partition("#")[2] for line in config.read_text(encoding="utf-8").splitlines())
        assert "DESIGN.md" not in comments and not re.search(r"(?<![\w.])/(work|home|tmp)/", comments), config.name
