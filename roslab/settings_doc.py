"""The README's settings reference, generated from the schema (`roslab.settings`).

Every setting is declared once, with its type, default, allowed values and doc line;
this module turns the schema into the markdown table between the README's markers,
so the table can't drift from the code:

    python -m roslab.settings_doc            # print the table
    python -m roslab.settings_doc --write    # rewrite it in README.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from roslab import settings

BEGIN_MARKER = "<!-- BEGIN settings table (python -m roslab.settings_doc --write) -->"
END_MARKER = "<!-- END settings table -->"
README = Path(__file__).resolve().parent.parent / "README.md"
COLUMNS = ("key", "type", "default", "allowed", "where", "what it does", "deploy")


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def _default(setting: settings.Setting) -> str:
    if setting.required:
        return "required"
    return json.dumps(setting.default, ensure_ascii=False)


def _where(setting: settings.Setting) -> str:
    return "any" if setting.levels == settings.ANY else ", ".join(setting.levels)


def markdown_table(schema: list[settings.Setting] = settings.SCHEMA) -> str:
    rows = [f"| {' | '.join(COLUMNS)} |", "|" + "---|" * len(COLUMNS)]
    for s in schema:
        cells = (f"`{s.key}`", s.type_text(), f"`{_default(s)}`", s.allowed_text(), _where(s),
                 s.doc, f"`{s.concern}`")
        rows.append("| " + " | ".join(_cell(cell) for cell in cells) + " |")
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
    table = markdown_table()
    if args.write:
        README.write_text(readme_with_table(README.read_text(), table))
    else:
        print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
