"""What a `ros2 launch` service's journal says of its nodes: which died, and the line that says why.

`ros2 launch` prefixes each node's output with `[<executable>-<n>]` and reports a node's end
as `[ERROR] [<executable>-<n>]: process has died [pid ..., exit code ..., cmd '...']`; with
`respawn=True` (the JPL rover's launch) the node starts again and dies again, and systemd sees
the launch itself running. `roslab status` reads the last lines of the journal of a profile's
service that runs a launch and shows one line per node that died, with the node's own last
error line (a Python exception, a FATAL log line): "roboclaw_wrapper: Unable to connect to
serial port /dev/serial1", "rover: ModuleNotFoundError: No module named 'tf2_ros'".
"""

from __future__ import annotations

import re

# how many journal lines status reads per launch service (a respawning node repeats itself)
JOURNAL_LINES = 400

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_DIED = re.compile(r"^\[ERROR\] \[(?P<node>[A-Za-z0-9_.-]+?)-\d+\]: process has died \[pid \d+, exit code (?P<code>-?\d+)")
_OUTPUT = re.compile(r"^\[(?P<node>[A-Za-z0-9_.-]+?)-\d+\] (?P<text>.*)$")
# a node's line that says why it ended: an exception's last line, a FATAL or ERROR log line
_EXCEPTION = re.compile(r"^([A-Za-z_][A-Za-z0-9_.]*(Error|Exception|Interrupt)|Exception)(: .*)?$")
_LOGGED = re.compile(r"^\[(FATAL|ERROR)\] \[[0-9.]+\] \[[^\]]*\]: (?P<text>.*)$")
_TEXT_LIMIT = 160


def command(unit: str) -> str:
    """The read of a launch service's last journal lines (the unit name is checked by the caller)."""
    return f"journalctl -u {unit} -n {JOURNAL_LINES} --no-pager -o cat 2>/dev/null"


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
    """One line per node of `unit`'s launch that died: "osr_startup: rover died 3 times: ..."."""
    return [f"{unit}: {node} died {'once' if count == 1 else f'{count} times'}: {why}"
            for node, (count, why) in died_nodes(lines).items()]
