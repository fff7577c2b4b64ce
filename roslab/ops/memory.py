"""Memory: the host's RAM and a swap file (facts and operations side by side, roslab.ops;
opt-in OS tweaks: profile `os_tweaks`, roster `profile_os_tweaks`)."""

from __future__ import annotations

import posixpath
from typing import Any

from pyinfra import host
from pyinfra.api import FactBase, operation

from roslab.quoting import shell_word


class MemoryTotal(FactBase):
    """The host's memory in MiB (MemTotal of /proc/meminfo), or None if unreadable."""

    def command(self) -> str:
        return "awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo"

    def process(self, output):
        try:
            return int(" ".join(output).strip())
        except ValueError:
            return None


# Room kept free beside a new swap file, so the card is never filled by it (logs, apt, the
# student's builds still need space).
SWAP_FREE_MARGIN_MB = 256


def partial_swap_path(path: str) -> str:
    """Where a swap file is made before it is complete (renamed into place only then)."""
    return path + ".roslab-new"


class SwapFile(FactBase):
    """A swap file's size in bytes, whether it is in use, and whether a partial one from an
    interrupted run is beside it: {"size": int | None, "active": bool, "partial": bool}."""

    def command(self, path: str) -> str:
        word = shell_word(path)
        return (f"if [ -f {word} ]; then stat -c 'size %s' {word}; else echo 'size none'; fi; "
                f"if awk 'NR > 1 {{print $1}}' /proc/swaps | grep -qxF -- {word}; "
                "then echo 'active yes'; else echo 'active no'; fi; "
                f"if [ -e {shell_word(partial_swap_path(path))} ]; then echo 'partial yes'; fi")

    def process(self, output):
        result: dict[str, Any] = {"size": None, "active": False, "partial": False}
        for line in output:
            key, _, value = line.strip().partition(" ")
            if key == "size" and value.isdigit():
                result["size"] = int(value)
            elif key in ("active", "partial"):
                result[key] = value == "yes"
        return result


@operation()
def swap_file_on(path: str, size_mb: int, margin_mb: int = SWAP_FREE_MARGIN_MB):
    """A swap file of `size_mb` MiB at `path` (mode 0600) is in use.

    + path: the swap file (``/swapfile``)
    + size_mb: its size in MiB; a file of another size is switched off and made anew
    + margin_mb: room that must stay free on the file's filesystem beside it

    The room is checked on the host when the file is made (free space plus the old file's):
    too little is refused in one line naming what is needed and what is free, before the old
    file is touched. The file is made under a temporary name (`fallocate`, never a `dd` that
    fills the card), made swap, and renamed into place only when complete; a partial file of
    an interrupted run is removed first.
    Only the running system: the /etc/fstab line that keeps it on after a reboot is a
    managed block of its own (deploy/robot_profile.py).
    Example: ``swap_file_on(name="...", path="/swapfile", size_mb=2048)``
    """
    current = host.get_fact(SwapFile, path=path)
    word, partial = shell_word(path), shell_word(partial_swap_path(path))
    if current["size"] == size_mb * 1024 * 1024:
        if current.get("partial"):
            yield f"rm -f -- {partial}"
        if current["active"]:
            if not current.get("partial"):
                host.noop(f"{path} ({size_mb} MiB) is already in use as swap")
            return
        yield f"swapon {word}"
        return
    directory = shell_word(posixpath.dirname(path) or "/")
    need_kib = (size_mb + margin_mb) * 1024
    # Free space plus what the old file holds (it goes first); in KiB, as df -P and du give it.
    room = (f"room=$(( $(df -Pk -- {directory} | awk 'NR == 2 {{print $4}}') + "
            f"$(if [ -f {word} ]; then du -k -- {word} | cut -f1; else echo 0; fi) ))")
    refuse = (f"echo \"roslab: not enough room for {path}: {size_mb} MiB and a margin of "
              f"{margin_mb} MiB needed, $((room / 1024)) MiB free: nothing was changed\" >&2; exit 1")
    failed = (f"{{ rm -f -- {partial}; echo \"roslab: could not make {path} ({size_mb} MiB): "
              f"$step failed; the partial file was removed\" >&2; exit 1; }}")
    yield " ".join([
        f"rm -f -- {partial};",
        f"{room};",
        f"if [ \"$room\" -lt {need_kib} ]; then {refuse}; fi;",
        *([f"swapoff {word} || exit 1;"] if current["active"] else []),
        f"rm -f -- {word} || exit 1;",
        # umask 077: the file is never readable by others, not even while it is being made.
        f"step=fallocate; (umask 077 && fallocate -l {size_mb}M {partial}) || {failed};",
        f"step=mkswap; chmod 600 {partial} && mkswap {partial} >/dev/null || {failed};",
        f"mv -f -- {partial} {word} && swapon {word}",
    ])
