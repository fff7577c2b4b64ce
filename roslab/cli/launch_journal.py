"""What a `ros2 launch` service's journal says of its nodes: which died, and the line that says why.

`ros2 launch` prefixes each node's output with `[<executable>-<n>]` and reports a node's end
as `[ERROR] [<executable>-<n>]: process has died [pid ..., exit code ..., cmd '...']`; with
`respawn=True` (the JPL rover's launch) the node starts again and dies again, and systemd sees
the launch itself running. `roslab status` and `roslab verify` read the last minute of the
journal of a profile's service that runs a launch: status shows one line per node that died,
verify fails the team (a running unit is not a working robot), each with the node's own last
error line (a Python exception, a FATAL log line): "roboclaw_wrapper: Unable to connect to
serial port /dev/serial1", "rover: ModuleNotFoundError: No module named 'tf2_ros'".
"""

from __future__ import annotations

import re

# The journal is read for the last WINDOW_SECONDS only, and only the lines that matter (a
# death, an error line): a node that respawns ~200 times a minute was "died 3 times" in the
# last 400 lines of everything. JOURNAL_LINES bounds what one host sends back.
WINDOW_SECONDS = 60
JOURNAL_LINES = 2000
_KEPT = "process has died|Error|Exception|FATAL|ERROR"

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_DIED = re.compile(r"^\[ERROR\] \[(?P<node>[A-Za-z0-9_.-]+?)-\d+\]: process has died \[pid \d+, exit code (?P<code>-?\d+)")
_OUTPUT = re.compile(r"^\[(?P<node>[A-Za-z0-9_.-]+?)-\d+\] (?P<text>.*)$")
# a node's line that says why it ended: an exception's last line, a FATAL or ERROR log line
_EXCEPTION = re.compile(r"^([A-Za-z_][A-Za-z0-9_.]*(Error|Exception|Interrupt)|Exception)(: .*)?$")
_LOGGED = re.compile(r"^\[(FATAL|ERROR)\] \[[0-9.]+\] \[[^\]]*\]: (?P<text>.*)$")
_TEXT_LIMIT = 160


def command(unit: str) -> str:
    """The read of a launch service's journal of the last WINDOW_SECONDS: its deaths and error
    lines (the unit name is checked and quoted by the caller)."""
    return (f"journalctl -u {unit} --since=-{WINDOW_SECONDS}s --no-pager -o cat 2>/dev/null"
            f" | grep -E '{_KEPT}' | tail -n {JOURNAL_LINES}")


def _reason(text: str) -> str | None:
    text = _ANSI.sub("", text).strip()
    logged = _LOGGED.match(text)
    if logged:
        return logged.group("text").strip()
    if _EXCEPTION.match(text):
        return text
    return None


def died_nodes(lines) -> dict[str, tuple[int, str]]:
    """{node: (times it died, why)} for each node that died in `lines` (with `respawn` a node
    starts again after each death, so dying at all is what counts). `why` is the node's last
    error line before its last death, else that death's exit code."""
    last_reason: dict[str, str] = {}
    deaths: dict[str, tuple[int, str]] = {}
    for raw in lines:
        line = _ANSI.sub("", str(raw)).rstrip()
        died = _DIED.match(line)
        if died:
            node = died.group("node")
            count = deaths.get(node, (0, ""))[0] + 1
            deaths[node] = (count, last_reason.get(node) or f"exit code {died.group('code')}")
            continue
        output = _OUTPUT.match(line)
        if output:
            reason = _reason(output.group("text"))
            if reason:
                last_reason[output.group("node")] = reason
    return {node: (count, _clip(why)) for node, (count, why) in sorted(deaths.items())}


def _clip(text: str) -> str:
    return text if len(text) <= _TEXT_LIMIT else text[:_TEXT_LIMIT - 1] + "…"


def summary(unit: str, lines) -> list[str]:
    """One line per node of `unit`'s launch that died in the last minute:
    "osr_startup: rover died 3 times in the last minute: ..."."""
    return [death_line(unit, node, count, why) for node, (count, why) in died_nodes(lines).items()]


def death_line(unit: str, node: str, count: int, why: str) -> str:
    """"osr_startup: rover died 3 times in the last minute: <why>"."""
    return f"{unit}: {node} died {'once' if count == 1 else f'{count} times'} in the last minute: {why}"
