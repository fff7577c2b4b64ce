"""The shape of roslab's code, as issue reviews measure it: size, the largest modules, functions
over 40 and over 60 lines, pyinfra facts and operations per module (those of roslab/ops/, one
module per tool, apart), and import cycles through folders and between files. It walks roslab/, deploy/ and deploy.py (TREES): the deploys are held to the same rule
(tests/unit/test_layout.py fails on a function over 60 lines in any of them).

    python bench/code_shape.py [ROOT]     # ROOT: a checkout (default: this one)

Read-only; prints markdown. Cycles are counted as tests/unit/test_layout.py counts them (lazy
imports inside functions included).
"""

from __future__ import annotations

import ast
import sys
from collections import Counter
from pathlib import Path

LONG = 60
MEDIUM = 40
# What is measured: the package, the deploys and the file pyinfra runs (a folder or a file).
TREES = ("roslab", "deploy", "deploy.py")
# roslab's package of pyinfra facts and operations, one module per tool.
TOOLS = "roslab/ops/"


def _is_operation(node: ast.AST) -> bool:
    return any(isinstance(d, ast.Call) and getattr(d.func, "id", getattr(d.func, "attr", "")) == "operation"
               or getattr(d, "id", None) == "operation" for d in getattr(node, "decorator_list", []))


def _is_fact(node: ast.AST) -> bool:
    return isinstance(node, ast.ClassDef) and any(
        getattr(base, "id", getattr(base, "attr", "")) in ("FactBase", "ShortFactBase") for base in node.bases)


def source_files(root: Path) -> list[Path]:
    """Every Python file of TREES under `root`, tree by tree (a tree the checkout lacks: none)."""
    found = []
    for tree in TREES:
        path = root / tree
        found += sorted(path.rglob("*.py")) if path.is_dir() else [path] if path.is_file() else []
    return found


def tree_of(name: str) -> str:
    """The tree of TREES a module (a path relative to the root) belongs to."""
    return name.split("/")[0]


def shape(root: Path) -> dict:
    package = root / "roslab"
    modules, long_functions, medium, facts, operations = {}, [], Counter(), Counter(), Counter()
    for path in source_files(root):
        name = str(path.relative_to(root))
        text = path.read_text()
        modules[name] = len(text.splitlines())
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > LONG:
                    long_functions.append((length, f"{name}:{node.lineno} {node.name}"))
                if length > MEDIUM:
                    medium[tree_of(name)] += 1
                if _is_operation(node):
                    operations[name] += 1
            if _is_fact(node):
                facts[name] += 1
    loose = sorted(p.name for p in package.glob("*.py") if p.name != "__init__.py")
    folders = sorted(p.parent.name for p in package.glob("*/__init__.py"))
    trees = {tree: {"lines": sum(lines for name, lines in modules.items() if tree_of(name) == tree),
                    "modules": sum(tree_of(name) == tree for name in modules),
                    "over_medium": medium[tree],
                    "over_long": sum(tree_of(where) == tree for _, where in long_functions)}
             for tree in TREES}
    return {"lines": sum(modules.values()), "modules": modules, "long": sorted(long_functions, reverse=True),
            "trees": trees, "facts": facts, "operations": operations, "loose": loose, "folders": folders}


def _layout():
    """tests/unit/test_layout.py, whose cycle finder this counts with."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "layout", Path(__file__).resolve().parent.parent / "tests/unit/test_layout.py")
    layout = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layout)
    return layout


def folder_cycles(root: Path) -> list[list[str]]:
    layout = _layout()
    layout.ROOT = root / "roslab"
    folders = {f"roslab.{name}" for name in shape(root)["folders"]}
    return [c for c in layout.cycles(layout.import_edges()) if folders & set(c)]


def file_cycles(root: Path) -> list[list[str]]:
    """Import cycles between files (each module a node) in roslab/ and in deploy/."""
    layout = _layout()
    return [cycle for tree in ("roslab", "deploy") if (root / tree).is_dir()
            for cycle in layout.cycles(layout.file_import_edges(root / tree))]


def main(argv: list[str]) -> int:
    root = Path(argv[1]).resolve() if len(argv) > 1 else Path(__file__).resolve().parent.parent
    found = shape(root)
    print(f"## {', '.join(TREES)} at {root}\n")
    print(f"- {found['lines']} lines in {len(found['modules'])} modules; roslab/: {len(found['loose'])} loose "
          f"modules at the top, {len(found['folders'])} folders ({', '.join(found['folders'])})")
    for tree, figures in found["trees"].items():
        print(f"- {tree}: {figures['lines']} lines in {figures['modules']} modules; functions over {MEDIUM} lines: "
              f"{figures['over_medium']}, over {LONG}: {figures['over_long']}")
    print(f"- functions over {LONG} lines: {len(found['long'])}")
    print(f"- facts: {sum(found['facts'].values())} in {len(found['facts'])} modules; operations: "
          f"{sum(found['operations'].values())} in {len(found['operations'])} modules")
    holders = sorted(set(found["facts"]) | set(found["operations"]))
    tools = [name for name in holders if name.startswith(TOOLS)]
    print(f"- modules holding facts or operations: {len(holders)}, {len(tools)} of them tool modules in "
          f"{TOOLS} ({sum(found['facts'][n] for n in tools)} facts, {sum(found['operations'][n] for n in tools)} "
          f"operations), {len(holders) - len(tools)} elsewhere")
    cycles = folder_cycles(root)
    print(f"- import cycles through a folder: {len(cycles)} {cycles if cycles else ''}")
    cycles = file_cycles(root)
    print(f"- import cycles between files: {len(cycles)} {cycles if cycles else ''}")
    print("\nLargest modules:\n")
    for name, lines in sorted(found["modules"].items(), key=lambda item: -item[1])[:8]:
        print(f"- {name}: {lines}")
    print(f"\nFunctions over {LONG} lines:\n")
    for length, where in found["long"]:
        print(f"- {where}: {length}")
    print(f"\nFacts and operations per tool module ({TOOLS}):\n")
    for name in tools:
        print(f"- {name}: {found['facts'][name]} facts, {found['operations'][name]} operations")
    print("\nFacts and operations in other modules:\n")
    for name in holders:
        if name not in tools:
            print(f"- {name}: {found['facts'][name]} facts, {found['operations'][name]} operations")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
