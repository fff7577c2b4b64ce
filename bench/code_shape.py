"""The shape of roslab/'s code, as issue reviews measure it: size, the largest modules, functions
over 60 lines, pyinfra facts and operations per module, and import cycles through folders.

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


def _is_operation(node: ast.AST) -> bool:
    return any(isinstance(d, ast.Call) and getattr(d.func, "id", getattr(d.func, "attr", "")) == "operation"
               or getattr(d, "id", None) == "operation" for d in getattr(node, "decorator_list", []))


def _is_fact(node: ast.AST) -> bool:
    return isinstance(node, ast.ClassDef) and any(
        getattr(base, "id", getattr(base, "attr", "")) in ("FactBase", "ShortFactBase") for base in node.bases)


def shape(root: Path) -> dict:
    package = root / "roslab"
    modules, long_functions, facts, operations = {}, [], Counter(), Counter()
    for path in sorted(package.rglob("*.py")):
        name = str(path.relative_to(root))
        text = path.read_text()
        modules[name] = len(text.splitlines())
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > LONG:
                    long_functions.append((length, f"{name}:{node.lineno} {node.name}"))
                if _is_operation(node):
                    operations[name] += 1
            if _is_fact(node):
                facts[name] += 1
    loose = sorted(p.name for p in package.glob("*.py") if p.name != "__init__.py")
    folders = sorted(p.parent.name for p in package.glob("*/__init__.py"))
    return {"lines": sum(modules.values()), "modules": modules, "long": sorted(long_functions, reverse=True),
            "facts": facts, "operations": operations, "loose": loose, "folders": folders}


def folder_cycles(root: Path) -> list[list[str]]:
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "layout", Path(__file__).resolve().parent.parent / "tests/unit/test_layout.py")
    layout = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(layout)
    layout.ROOT = root / "roslab"
    folders = {f"roslab.{name}" for name in shape(root)["folders"]}
    return [c for c in layout.cycles(layout.import_edges()) if folders & set(c)]


def main(argv: list[str]) -> int:
    root = Path(argv[1]).resolve() if len(argv) > 1 else Path(__file__).resolve().parent.parent
    found = shape(root)
    print(f"## roslab/ at {root}\n")
    print(f"- {found['lines']} lines in {len(found['modules'])} modules; {len(found['loose'])} loose modules "
          f"at the top, {len(found['folders'])} folders ({', '.join(found['folders'])})")
    print(f"- functions over {LONG} lines: {len(found['long'])}")
    print(f"- facts: {sum(found['facts'].values())} in {len(found['facts'])} modules; operations: "
          f"{sum(found['operations'].values())} in {len(found['operations'])} modules")
    cycles = folder_cycles(root)
    print(f"- import cycles through a folder: {len(cycles)} {cycles if cycles else ''}")
    print("\nLargest modules:\n")
    for name, lines in sorted(found["modules"].items(), key=lambda item: -item[1])[:8]:
        print(f"- {name}: {lines}")
    print(f"\nFunctions over {LONG} lines:\n")
    for length, where in found["long"]:
        print(f"- {where}: {length}")
    print("\nFacts and operations per module:\n")
    for name in sorted(set(found["facts"]) | set(found["operations"])):
        print(f"- {name}: {found['facts'][name]} facts, {found['operations'][name]} operations")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
