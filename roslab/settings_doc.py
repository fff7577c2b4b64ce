"""The README's settings reference, generated from the deploys' DEFAULTS.

Each deploy module documents its settings in one place: the comment lines right
above a key in its `DEFAULTS` dict. This module turns those into the markdown
table between the README's markers, so the table can't drift from the code:

    python -m roslab.settings_doc            # print the table
    python -m roslab.settings_doc --write    # rewrite it in README.md
"""

from __future__ import annotations

import argparse
import ast
import importlib
import inspect
import sys
from dataclasses import dataclass
from pathlib import Path

import deploy

BEGIN_MARKER = "<!-- BEGIN settings table (python -m roslab.settings_doc --write) -->"
END_MARKER = "<!-- END settings table -->"
README = Path(__file__).resolve().parent.parent / "README.md"


@dataclass(frozen=True)
class Setting:
    key: str
    default: str
    doc: str
    module: str


def module_settings(module_name: str) -> list[Setting]:
    """The settings of one deploy module, in source order, with their comments."""
    module = importlib.import_module(f"deploy.{module_name}")
    source = inspect.getsource(module)
    lines = source.splitlines()
    for node in ast.parse(source).body:
        targets = node.targets if isinstance(node, ast.Assign) else []
        if any(isinstance(t, ast.Name) and t.id == "DEFAULTS" for t in targets):
            defaults_node = node.value
            break
    else:
        raise ValueError(f"deploy.{module_name} has no DEFAULTS dict")
    if not isinstance(defaults_node, ast.Dict):
        raise ValueError(f"deploy.{module_name}: DEFAULTS must be a dict literal")

    settings = []
    for key_node, value_node in zip(defaults_node.keys, defaults_node.values):
        comment = []
        line_no = key_node.lineno - 2  # the line above the key, 0-based
        while line_no >= 0 and lines[line_no].strip().startswith("#"):
            comment.insert(0, lines[line_no].strip().lstrip("#").strip())
            line_no -= 1
        default = " ".join(ast.get_source_segment(source, value_node).split())
        settings.append(Setting(key_node.value, default, " ".join(comment), module_name))
    return settings


def all_settings() -> list[Setting]:
    return [s for name in deploy.DEPLOY_MODULES for s in module_settings(name)]


def markdown_table(settings: list[Setting]) -> str:
    rows = ["| key | default | what it does | deploy |", "|---|---|---|---|"]
    for s in settings:
        doc = s.doc.replace("|", "\\|")
        default = s.default.replace("|", "\\|")
        rows.append(f"| `{s.key}` | `{default}` | {doc} | `{s.module}` |")
    return "\n".join(rows)


def readme_with_table(readme_text: str, table: str) -> str:
    head, sep, rest = readme_text.partition(BEGIN_MARKER)
    _, sep2, tail = rest.partition(END_MARKER)
    if not sep or not sep2:
        raise ValueError("README.md lacks the settings table markers")
    return f"{head}{BEGIN_MARKER}\n{table}\n{END_MARKER}{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="rewrite the table in README.md")
    args = parser.parse_args(argv)
    table = markdown_table(all_settings())
    if args.write:
        README.write_text(readme_with_table(README.read_text(), table))
    else:
        print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
