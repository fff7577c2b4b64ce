"""What a colcon build on a host is doing, while it runs: which package, how many of how many.

A build runs for minutes on a Pi (the micro-ROS agent: ~20 minutes), and the run's "still
running on HOST (N s)" line said nothing more. Each build script (the students' workspace,
roslab/ros/workspace.py; an underlay, roslab/sources/underlay.py) now runs colcon through
`build_lines`: colcon's whole output still goes to the build's log, and one line per package
event goes to the command's stdout as it happens (`roslab-progress: building NAME`, `built
NAME`, after `roslab-progress: packages N` from `colcon list`). `install()` lets pyinfra's
SSH connector hand each such line, as it arrives, to `seen()`, and the run's compact output
(roslab/reporting/summary.py) says `team2-robot: building micro_ros_agent (3 of 5 built)`.
The lines are not shown otherwise: a failed build's output is logged without them.
"""

from __future__ import annotations

import re
import shlex
import threading

PREFIX = "roslab-progress: "
_HOST = re.compile(r"\[([^\]\s]+)\]")
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")

# colcon's console_start_end lines (its default console output): "Starting >>> NAME",
# "Finished <<< NAME [1.2s]", "Failed   <<< NAME [...]".
_SED = (r"s/^Starting >>> \([^ ]*\).*/" + PREFIX + r"building \1/p;"
        r"s/^Finished <<< \([^ ]*\).*/" + PREFIX + r"built \1/p;"
        r"s/^Failed *<<< \([^ ]*\).*/" + PREFIX + r"failed \1/p")


def build_lines(colcon: str, log: str, list_arguments: str = "") -> tuple[str, str]:
    """(the line that says how many packages there are, the condition that runs `colcon`),
    for a bash script's `if CONDITION; then`: colcon's output into `log` (as `> log 2>&1`
    would), a progress line per package event on stdout, colcon's exit status kept.

    + colcon: the `colcon build ...` command (quoted)
    + log: the build log (relative to the script's folder)
    + list_arguments: what tells `colcon list` the same packages (``--base-paths src``)
    """
    count = (f'echo "{PREFIX}packages $(colcon list --names-only {list_arguments} 2>/dev/null | wc -l)"')
    condition = f"( set -o pipefail; {colcon} 2>&1 | tee {log} | sed -un {shlex.quote(_SED)} )"
    return count, condition


class Builds:
    """Each host's build as its progress lines told it (thread- and greenlet-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._hosts: dict[str, dict] = {}

    def seen(self, host: str, line: str) -> None:
        """Take one progress line of `host`'s build (other lines are ignored)."""
        if not line.startswith(PREFIX):
            return
        event, _, value = line[len(PREFIX):].strip().partition(" ")
        with self._lock:
            build = self._hosts.setdefault(host, {"total": None, "building": [], "built": 0})
            if event == "packages":
                build.update(total=int(value) if value.isdigit() else None, building=[], built=0)
            elif event == "building" and value not in build["building"]:
                build["building"].append(value)
            elif event in ("built", "failed"):
                build["building"] = [name for name in build["building"] if name != value]
                build["built"] += event == "built"

    def words(self, host: str) -> str | None:
        """`building NAME (3 of 5 built)`, or None when no build of `host` was seen."""
        with self._lock:
            build = self._hosts.get(host)
            if not build or (not build["building"] and not build["built"]):
                return None
            total = f" of {build['total']}" if build["total"] else ""
            doing = f"building {', '.join(build['building'])}" if build["building"] else "between packages"
            return f"{doing} ({build['built']}{total} built)"

    def clear(self) -> None:
        """Forget every build (a new step starts: its builds are its own)."""
        with self._lock:
            self._hosts.clear()


BUILDS = Builds()


def tapped(lines, print_prefix: str):
    """`lines` (a command's stdout, as pyinfra reads it), each progress line also told to BUILDS."""
    match = _HOST.search(_ANSI.sub("", print_prefix or ""))
    host = match.group(1) if match else None
    for line in lines:
        if host is not None:
            text = line.decode("utf-8", "replace") if isinstance(line, bytes) else line
            if text.startswith(PREFIX):
                BUILDS.seen(host, text.rstrip("\n"))
        yield line


def install() -> None:
    """Let pyinfra's SSH connector hand each stdout line to `tapped` as it arrives. Idempotent."""
    from pyinfra.connectors import ssh as pyinfra_ssh, util as pyinfra_util

    original = pyinfra_util.read_output_buffers
    if getattr(original, "roslab_progress", False):
        return

    def read_output_buffers(stdout_buffer, stderr_buffer, timeout, print_output, print_prefix):
        return original(tapped(stdout_buffer, print_prefix), stderr_buffer, timeout=timeout,
                        print_output=print_output, print_prefix=print_prefix)

    read_output_buffers.roslab_progress = True  # type: ignore[attr-defined]  # the patch's marker (getattr above)
    pyinfra_util.read_output_buffers = read_output_buffers
    if getattr(pyinfra_ssh, "read_output_buffers", None) is original:
        pyinfra_ssh.read_output_buffers = read_output_buffers
