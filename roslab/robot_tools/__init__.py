"""Commands a robot brings with it: a profile names them (`tools: [opencr-update]`), and each is a
module here, `roslab/robot_tools/<tool, - as _>.py`, with `register(commands)` adding its
`roslab <tool>` subcommand (TurtleBot3's OpenCR flash: opencr_update.py).

The CLI adds the tools that the built-in profiles name; no list of robots or tools lives in it.
"""

from __future__ import annotations

import importlib


def register_profile_tools(commands) -> None:
    """Add `roslab <tool>` for each tool a built-in profile names (profiles check the names
    against this folder's modules: roslab.profiles.schema.known_tools)."""
    from roslab.profiles.library import builtin_profiles

    for name in sorted({tool for profile in builtin_profiles().values() for tool in profile.tools}):
        importlib.import_module(f"{__name__}.{name.replace('-', '_')}").register(commands)
