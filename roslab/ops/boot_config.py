"""A Pi's boot configuration (config.txt, cmdline.txt) and the host's "reboot needed" record
(facts and operations side by side, roslab.ops; profile `boot_config`)."""

from __future__ import annotations

from typing import Any

from pyinfra import host
from pyinfra.api import FactBase, operation
from pyinfra.facts.files import File

from roslab.ops.files import durably_renamed, managed_block, run_temporary
from roslab.quoting import shell_word


# Where a Pi's boot partition is on Ubuntu (and Raspberry Pi OS since bookworm).
BOOT_DIR = "/boot/firmware"
CONFIG_TXT = f"{BOOT_DIR}/config.txt"
CMDLINE_TXT = f"{BOOT_DIR}/cmdline.txt"
# The host's record that a change waits for a reboot: `boot_id=...` (the boot it was made in)
# and `reason=...` lines. World-readable: `roslab status` reads it without sudo. Under /run (a
# tmpfs on Ubuntu): the reboot it asks for clears it, so the run after the reboot has nothing
# to clean up and changes nothing; the boot id still guards a /run that outlived a boot.
REBOOT_RECORD = "/run/roslab/reboot-needed"


BOOT_ID = "/proc/sys/kernel/random/boot_id"


def cmdline_without(text: str, words: list[str]) -> str:
    """cmdline.txt's one line without `words` (whole words only; the others keep their order)."""
    return " ".join(word for word in text.split() if word not in words)


class CmdlineText(FactBase):
    """The text of `path` (the kernel's command line file: one line), or None when it is missing."""

    def command(self, path: str) -> str:
        quoted = shell_word(path)
        return f"if [ -f {quoted} ]; then cat {quoted}; else echo '#no-such-file'; fi"

    def process(self, output):
        text = "\n".join(output)
        return None if text.strip() == "#no-such-file" else text


@operation()
def config_txt_block(path: str, lines: list[str], label: str, backup_suffix: str):
    """A Pi's config.txt holds `lines` in a roslab-marked block (roslab.ops.files.managed_block),
    or, where the file does not exist (a PC, a container), nothing is created: no firmware here
    reads it. The file is copied to `<path><backup_suffix>` before it changes (the upload that
    follows syncs the file and its directory: roslab.remote_files).

    + path: the file (/boot/firmware/config.txt)
    + lines: its lines (the block starts with [all], so no conditional section above swallows them)
    + label: names the block in its markers
    + backup_suffix: the backup's suffix (``.roslab-<date>-<time>``)
    """
    if host.get_fact(File, path=path) is None:
        host.noop(f"{path} does not exist (not a Raspberry Pi's boot partition): the boot config "
                  f"({', '.join(lines)}) is not written")
        return
    commands = list(managed_block._inner(path=path, content="\n".join(["[all]", *lines]), label=label))
    if not commands:
        return
    backup = path + backup_suffix
    if not any(backup in str(command) for command in commands):  # a marker repair copies it already
        yield f"cp -p -- {shell_word(path)} {shell_word(backup)} && sync -- {shell_word(backup)}"
    yield from commands


def cmdline_with(text: str, add: list[str], remove: list[str]) -> str:
    """cmdline.txt's one line without `remove` and with each word of `add` it lacks appended
    (whole words; the line's other words keep their order)."""
    words = cmdline_without(text, remove).split()
    return " ".join([*words, *(word for word in dict.fromkeys(add) if word not in words)])


@operation()
def cmdline_words_absent(path: str, words: list[str], backup_suffix: str):
    """The kernel command line file holds none of `words` (cmdline_words_kept with nothing to add).

    + path: the file (/boot/firmware/cmdline.txt)
    + words: whole words to take out (``console=serial0,115200``)
    + backup_suffix: the backup's suffix (``.roslab-<date>-<time>``)
    """
    yield from cmdline_words_kept._inner(path=path, add=[], remove=words, backup_suffix=backup_suffix)


@operation()
def cmdline_words_kept(path: str, add: list[str], remove: list[str], backup_suffix: str):
    """The kernel command line file holds each word of `add` (``modules-load=dwc2,g_ether``, for
    the TurtleBot 4's usb0) and none of `remove` (the serial console, for a UART a robot talks
    on); its other words stay as they are; the file is copied to `<path><backup_suffix>` before
    it changes.

    + path: the file (/boot/firmware/cmdline.txt)
    + add: whole words it must hold (appended when missing)
    + remove: whole words to take out
    + backup_suffix: the backup's suffix (``.roslab-<date>-<time>``)
    """
    current = host.get_fact(CmdlineText, path=path)
    if current is None:
        host.noop(f"{path} does not exist (not a Raspberry Pi's boot partition): nothing to change")
        return
    wanted = cmdline_with(current, add, remove)
    if wanted == " ".join(current.split()):
        described = [*([f"holds {', '.join(add)}"] if add else []),
                     *([f"holds none of {', '.join(remove)}"] if remove else [])]
        host.noop(f"{path} {' and '.join(described)}")
        return
    quoted, new, backup = shell_word(path), run_temporary(path), path + backup_suffix
    # One line, written beside the file and renamed over it: the firmware never reads half a file.
    yield (f"cp -p -- {quoted} {shell_word(backup)} && "
           f"printf '%s\\n' {shell_word(wanted)} > {shell_word(new)} && {durably_renamed(new, path, backup)}")


class RebootRecord(FactBase):
    """The host's reboot record and its current boot:
    ``{"current_boot": id, "boot_id": id or None, "reasons": [...], "exists": bool}``."""

    def command(self) -> str:
        return (f"echo \"current_boot=$(cat {BOOT_ID} 2>/dev/null)\"; "
                f"if [ -f {REBOOT_RECORD} ]; then echo '#record'; cat {REBOOT_RECORD}; fi")

    def process(self, output):
        return parse_reboot_record(output)


def parse_reboot_record(lines) -> dict:
    """RebootRecord's output (also `roslab status`'s): the current boot and the record."""
    result: dict[str, Any] = {"current_boot": None, "boot_id": None, "reasons": [], "exists": False}
    for line in lines:
        key, sep, value = line.strip().partition("=")
        if line.strip() == "#record":
            result["exists"] = True
        elif sep and key == "current_boot":
            result["current_boot"] = value or None
        elif sep and key == "boot_id":
            result["boot_id"] = value or None
        elif sep and key == "reason" and value and value not in result["reasons"]:
            result["reasons"].append(value)
    return result


def reboot_pending(record: dict) -> bool:
    """Whether the record names a change that still waits for a reboot (made in this boot)."""
    return bool(record.get("exists") and record.get("boot_id")
                and record.get("boot_id") == record.get("current_boot"))


@operation(is_idempotent=False)
def reboot_needed_recorded(reasons: list[str]):
    """The host records that it needs a reboot for `reasons`, in this boot (run it with `_if=`
    the change that needs it). roslab never reboots: the teacher does, when the class allows.

    + reasons: one line each (``/boot/firmware/config.txt changed``); kept with the reasons of an
      earlier change in the same boot
    """
    record = host.get_fact(RebootRecord)
    kept = record["reasons"] if reboot_pending(record) else []
    lines = [*kept, *(reason for reason in reasons if reason not in kept)]
    new = run_temporary(REBOOT_RECORD)
    yield (f"mkdir -p {shell_word(REBOOT_RECORD.rsplit('/', 1)[0])} && "
           f"{{ printf 'boot_id=%s\\n' \"$(cat {BOOT_ID})\"; "
           f"printf 'reason=%s\\n' {' '.join(shell_word(line) for line in lines)}; }}"
           f" > {shell_word(new)} && chmod 644 {shell_word(new)} && {durably_renamed(new, REBOOT_RECORD)}")


@operation()
def reboot_record_current():
    """A reboot record left from an earlier boot is gone: the host has rebooted since the change."""
    record = host.get_fact(RebootRecord)
    if not record["exists"]:
        host.noop("no change waits for a reboot")
        return
    if reboot_pending(record):
        host.noop(f"a reboot is still needed ({'; '.join(record['reasons'])}): roslab never reboots a host")
        return
    yield f"rm -f -- {shell_word(REBOOT_RECORD)}"
