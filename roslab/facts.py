"""pyinfra facts roslab's deploys need beyond pyinfra's own.

Each fact is one remote command; none of them changes the host.
"""

from __future__ import annotations

from pyinfra.api import FactBase, QuoteString, StringCommand
from typing_extensions import override


class AptProblem(FactBase):
    """
    Waits (bounded) until apt can take the dpkg lock, then reports whether apt is usable.

    Returns ``None`` when ``apt-get check`` succeeds within ``lock_timeout`` seconds, else
    apt's own error lines (e.g. the lock still held by unattended-upgrades, or broken
    dependencies). Fresh Ubuntu images hold the lock for minutes at first boot.
    """

    @override
    def command(self, lock_timeout: int) -> StringCommand:
        # `; echo` keeps the fact's exit status 0 so the failure reaches process().
        return StringCommand(
            f"apt-get -qq -o DPkg::Lock::Timeout={int(lock_timeout)} check 2>&1;",
            'echo "roslab-apt-exit=$?"',
        )

    @override
    def process(self, output):
        lines = list(output)
        status = lines.pop() if lines else ""
        if status == "roslab-apt-exit=0":
            return None
        # apt prints "Waiting for cache lock" lines while it waits: keep the verdict only.
        errors = [line for line in lines if not line.startswith("Waiting for cache lock")]
        return "\n".join(errors) or status


class FileAge(FactBase):
    """
    Returns how many seconds ago a file was last modified, by the host's clock, or ``None``
    when the file does not exist.
    """

    @override
    def command(self, path: str) -> StringCommand:
        return StringCommand(
            "if [ -e",
            QuoteString(path),
            "]; then echo $(( $(date +%s) - $(stat -c %Y",
            QuoteString(path),
            ") )); fi",
        )

    @override
    def process(self, output):
        for line in output:
            line = line.strip()
            if line.lstrip("-").isdigit():
                return int(line)
        return None
