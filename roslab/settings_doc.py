"""The docs' generated tables: the settings reference and the releases (docs/roster-and-settings.md)
and the robot profiles (docs/robots.md), from the schema (`roslab.settings`), the release records
(`roslab.ros.distro`) and the built-in profile files (`roslab/profiles/data`).

Every setting is declared once, with its type, default, allowed values and doc line, every
release is one record and every built-in profile one file; this module turns them into the
markdown tables between each page's markers, so the tables can't drift from the code (a new
profile file or release record is a new row). It also writes `roslab/host_fields.py`, the typed
dataclass of a host's settings the deploys read (one field per setting, then
roslab.settings.HOST_KEYS):

    python -m roslab.settings_doc            # print the tables
    python -m roslab.settings_doc --write    # rewrite them in their docs pages, and roslab/host_fields.py
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
from pathlib import Path

from roslab import settings

BEGIN_MARKER = "<!-- BEGIN settings table (python -m roslab.settings_doc --write) -->"
END_MARKER = "<!-- END settings table -->"
PROFILES_BEGIN_MARKER = "<!-- BEGIN profiles table (python -m roslab.settings_doc --write) -->"
PROFILES_END_MARKER = "<!-- END profiles table -->"
RELEASES_BEGIN_MARKER = "<!-- BEGIN releases table (python -m roslab.settings_doc --write) -->"
RELEASES_END_MARKER = "<!-- END releases table -->"
BOARDS_BEGIN_MARKER = "<!-- BEGIN boards table (python -m roslab.settings_doc --write) -->"
BOARDS_END_MARKER = "<!-- END boards table -->"
REPO = Path(__file__).resolve().parent.parent
SETTINGS_PAGE = REPO / "docs/roster-and-settings.md"  # the settings and the releases tables
PROFILES_PAGE = REPO / "docs/robots.md"  # the profiles and the boards tables
HOST_FIELDS = Path(__file__).resolve().parent / "host_fields.py"
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


def _profile_settings(profile) -> str:
    parts = []
    for setting in profile.settings.values():
        values = ", ".join(setting.allowed) if setting.allowed else (setting.pattern and "a value")
        required = "required" if setting.required else f"default {setting.default}" if setting.default else "optional"
        parts.append(f"`{setting.name}` ({values}; {required})" if values else f"`{setting.name}` ({required})")
    return "; ".join(parts) or "none"


def _runs(side, absent: str) -> str:
    """What a side starts: its launch and its services, and what its `when` blocks choose instead."""
    if side is None:
        return absent
    started = [f"`{side.launch}`"] if side.launch else []
    started += [f"service `{service['name']}`" for service in side.services]
    for block in side.when:
        chosen = [f"`{block['side'].launch}`"] if block["side"].launch else []
        chosen += [f"service `{service['name']}`" for service in block["side"].services]
        if chosen:
            condition = ", ".join(f"{name}: {value}" for name, value in block["if"].items())
            started.append(f"{' and '.join(chosen)} when {condition}")
    return "; ".join(started) or "nothing"


def profiles_table() -> str:
    """One row per built-in profile file: what it is, where it runs, what each side runs."""
    from roslab.profiles.library import builtin_profiles

    columns = ("profile", "what it is", "distros", "robot runs", "main runs", "its settings", "verify hears")
    rows = [f"| {' | '.join(columns)} |", "|" + "---|" * len(columns)]
    for name, profile in sorted(builtin_profiles().items()):
        distros = "all" if profile.declared_distros == ("all",) else ", ".join(profile.distros)
        cells = (f"`{name}`", profile.description, distros, _runs(profile.sides.get("robot"), "no robot"),
                 _runs(profile.sides.get("main"), "no main"), _profile_settings(profile),
                 f"`{profile.verify_topic}`" if profile.verify_topic else "nothing (no topic to check)")
        rows.append("| " + " | ".join(_cell(cell) for cell in cells) + " |")
    return "\n".join(rows)


def _between(text: str, begin: str, end: str, table: str) -> str:
    head, sep, rest = text.partition(begin)
    _, sep2, tail = rest.partition(end)
    if not sep or not sep2:
        raise ValueError(f"the page lacks the markers {begin} ... {end}")
    return f"{head}{begin}\n{table}\n{end}{tail}"


def page_with_settings(page_text: str, table: str) -> str:
    return _between(page_text, BEGIN_MARKER, END_MARKER, table)


def page_with_profiles(page_text: str, table: str) -> str:
    return _between(page_text, PROFILES_BEGIN_MARKER, PROFILES_END_MARKER, table)


def releases_table() -> str:
    """The Ubuntu releases roslab knows (roslab.ros.distro.PLATFORMS), each with its default ROS 2
    distro and the packages a main and a robot get by default: a new release record is a new row."""
    from roslab.ros.distro import PLATFORMS

    main, robot = settings.SETTINGS["ros_variant_main"].default, settings.SETTINGS["ros_variant_robot"].default
    rows = ["| Ubuntu on the host | ROS 2 distro by default | main hosts get | robots get |", "|---|---|---|---|"]
    for platform in sorted(PLATFORMS, key=lambda p: p.release, reverse=True):
        rows.append(f"| {platform.release} {platform.codename} | {platform.distro.capitalize()} "
                    f"| `ros-{platform.distro}-{main}` | `ros-{platform.distro}-{robot}` |")
    return "\n".join(rows)


def page_with_releases(page_text: str, table: str) -> str:
    return _between(page_text, RELEASES_BEGIN_MARKER, RELEASES_END_MARKER, table)


def boards_table() -> str:
    """The boards a host can be (roslab.boards.BOARDS): a new board record is a new row."""
    from roslab import boards

    rows = ["| `board` | what it is | boot partition (config.txt, cmdline.txt) | first Ubuntu image (older releases are refused) |",
            "|---|---|---|---|"]
    for board in boards.BOARDS:
        rows.append(f"| `{board.name}` | {board.title} | {'yes' if board.raspberry_pi else 'no'} "
                    f"| {board.first_release or 'no limit recorded'} |")
    return "\n".join(rows)


def page_with_boards(page_text: str, table: str) -> str:
    return _between(page_text, BOARDS_BEGIN_MARKER, BOARDS_END_MARKER, table)


def _comment(text: str) -> list[str]:
    return textwrap.wrap(text, 108, initial_indent="    # ", subsequent_indent="    # ", break_on_hyphens=False)


def host_fields_module() -> str:
    """roslab/host_fields.py: the dataclass with one typed field per setting and host key."""
    lines = [
        '"""A host\'s settings, typed: one field per setting of a host\'s data (roslab.settings.HOST_SETTINGS),',
        "then the keys the roster loader derives (roslab.settings.HOST_KEYS). Build one with",
        "roslab.host_settings.host_settings(host). Types only: each setting's doc is in the schema",
        "(roslab/settings.py) and the settings table of docs/roster-and-settings.md.",
        "",
        "Generated by `python -m roslab.settings_doc --write`; do not edit (declare a setting in",
        'roslab/settings.py; tests/unit/test_settings_doc.py fails when this file is stale)."""',
        "",
        "from __future__ import annotations",
        "",
        "from dataclasses import dataclass" + (", field" if any(key.secret for key in settings.HOST_KEYS) else ""),
        "from typing import Any",
        "",
        "from roslab.profiles.resolve import ResolvedProfile",
        "",
        "",
        "@dataclass(frozen=True)",
        "class HostSettings:",
    ]
    concern = None
    for s in settings.HOST_SETTINGS:
        if s.concern != concern:
            concern = s.concern
            lines.append(f"    # --- {concern} ---")
        lines.append(f"    {s.key}: {settings.annotation(s)}")
    lines.append("    # --- derived by the roster loader (None in a hand-made inventory that lacks it) ---")
    for key in settings.HOST_KEYS:
        lines.append(f"    {key.key}: {key.annotation} | None" + (" = field(repr=False)" if key.secret else ""))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help="rewrite the tables in their docs pages")
    args = parser.parse_args(argv)
    table, profiles, releases, boards = markdown_table(), profiles_table(), releases_table(), boards_table()
    if args.write:
        SETTINGS_PAGE.write_text(page_with_releases(page_with_settings(SETTINGS_PAGE.read_text(), table), releases))
        PROFILES_PAGE.write_text(page_with_boards(page_with_profiles(PROFILES_PAGE.read_text(), profiles), boards))
        HOST_FIELDS.write_text(host_fields_module())
    else:
        print(f"{releases}\n\n{table}\n\n{profiles}\n\n{boards}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
