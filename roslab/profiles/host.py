"""Operations and facts for what a robot profile changes on a host besides packages and files.

    UserGroups / user_in_groups   the login user in the profile's groups (dialout for serial ports)
    udev_reloaded                 udev re-reads its rules and replays the add events (after a change)
"""

from __future__ import annotations

import os
import posixpath
import secrets
from typing import Any

from pyinfra import host
from pyinfra.api import FactBase, OperationError, operation
from pyinfra.facts.files import File

from roslab.quoting import shell_word


class UserGroups(FactBase):
    """The groups `user` is in (`id -nG`), or None when the user does not exist."""

    def command(self, user: str) -> str:
        return f"id -nG {shell_word(user)} 2>/dev/null || echo '#no-such-user'"

    def process(self, output):
        text = " ".join(output).strip()
        if text == "#no-such-user":
            return None
        return text.split()


@operation()
def user_in_groups(user: str, groups: list[str]):
    """The login user is a member of each of `groups` (added, never removed from others).

    + user: the account
    + groups: the groups it must be in (they exist on Ubuntu: dialout, video, ...)

    Example: ``user_in_groups(name="...", user="ubuntu", groups=["dialout"])``
    """
    from roslab.profiles.schema import login_group_problem

    for group in groups:  # checked at load; hand-made host data gets the same allow-list
        if login_group_problem(group):
            raise OperationError(login_group_problem(group))
    current = host.get_fact(UserGroups, user=user)
    if current is None:
        raise_missing = f"user {user!r} does not exist"
        yield f"echo {shell_word(raise_missing)} >&2; exit 1"
        return
    missing = [group for group in groups if group not in current]
    if not missing:
        host.noop(f"{user} is already in {', '.join(groups)}")
        return
    yield f"usermod -a -G {shell_word(','.join(missing))} {shell_word(user)}"


def user_in_groups_reads(user: str) -> list:
    from roslab import probe

    return [probe.read(UserGroups, user=user)]


# Where udevd runs (a Pi), it re-reads its rules and replays "add" for the subsystems of the
# device kinds a profile declares (roslab/profiles/devices.py), so a board plugged in before the run gets its name and mode now. Where it does
# not run (a container), the rules apply at the next boot; the command says which.
UDEV_RELOAD = (
    "if systemctl is-active --quiet systemd-udevd; then "
    "udevadm control --reload-rules && "
    "udevadm trigger --action=add --subsystem-match=tty --subsystem-match=usb --subsystem-match=i2c-dev "
    "--subsystem-match=spidev --subsystem-match=gpio --subsystem-match=input && "
    "echo 'udev rules reloaded'; "
    "else echo 'systemd-udevd is not running here: the rules apply from the next boot'; fi"
)


@operation(is_idempotent=False)
def udev_reloaded():
    """udev has read the current rules (run it with `_if=` the rules file's change).

    Example: ``udev_reloaded(name="...", _if=rules.did_change)``
    """
    yield UDEV_RELOAD


# --- opt-in OS tweaks (profile `os_tweaks`, roster `profile_os_tweaks`) -------------------


class MemoryTotal(FactBase):
    """The host's memory in MiB (MemTotal of /proc/meminfo), or None if unreadable."""

    def command(self) -> str:
        return "awk '/^MemTotal:/ {print int($2 / 1024)}' /proc/meminfo"

    def process(self, output):
        try:
            return int(" ".join(output).strip())
        except ValueError:
            return None


class UnitsMasked(FactBase):
    """For each of `units`, whether systemd has it masked ({unit: bool})."""

    def command(self, units: list[str]) -> str:
        words = " ".join(shell_word(unit) for unit in units)
        return (f"for unit in {words}; do "
                'printf "%s %s\\n" "$unit" "$(systemctl is-enabled "$unit" 2>/dev/null || true)"; done')

    def process(self, output):
        masked = {}
        for line in output:
            unit, _, state = line.strip().partition(" ")
            if unit:
                masked[unit] = state.strip() == "masked"
        return masked


@operation()
def units_masked(units: list[str]):
    """Each of `units` is masked (linked to /dev/null): nothing starts or waits for it.

    + units: systemd unit names (``sleep.target``, ``systemd-networkd-wait-online.service``)

    A unit this host does not have is masked all the same, so a later install cannot start it.
    Example: ``units_masked(name="...", units=["sleep.target", "suspend.target"])``
    """
    from roslab.profiles.schema import maskable_unit_problem

    for unit in units:  # checked at load; hand-made host data gets the same allow-list
        if maskable_unit_problem(unit):
            raise OperationError(maskable_unit_problem(unit))
    current = host.get_fact(UnitsMasked, units=units)
    missing = [unit for unit in units if not current.get(unit)]
    if not missing:
        host.noop(f"{', '.join(units)} already masked")
        return
    yield f"systemctl mask {' '.join(shell_word(unit) for unit in missing)}"


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


# --- boot configuration and "reboot needed" (profile `boot_config`) ------------------------

# Where a Pi's boot partition is on Ubuntu (and Raspberry Pi OS since bookworm).
BOOT_DIR = "/boot/firmware"
CONFIG_TXT = f"{BOOT_DIR}/config.txt"
CMDLINE_TXT = f"{BOOT_DIR}/cmdline.txt"
# The host's record that a change waits for a reboot: `boot_id=...` (the boot it was made in)
# and `reason=...` lines. World-readable: `roslab status` reads it without sudo. Under /run (a
# tmpfs on Ubuntu): the reboot it asks for clears it, so the run after the reboot has nothing
# to clean up and changes nothing; the boot id still guards a /run that outlived a boot.
REBOOT_RECORD = "/run/roslab/reboot-needed"
# This controller run's mark on the files it writes beside a record before renaming them over it:
# two runs at once never write through the same temporary name (each run also holds the host's
# run lock: roslab/ssh/run_lock.py).
RUN_MARK = f"{os.getpid()}-{secrets.token_hex(4)}"


def run_temporary(path: str) -> str:
    """Where this run writes `path`'s new content before it is renamed over it."""
    return f"{path}.roslab-new-{RUN_MARK}"
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


def durably_renamed(new: str, path: str, *also_synced: str) -> str:
    """Shell: `new` (and `also_synced`, a backup) reach the disk, `new` is renamed over `path`
    and the rename reaches the disk too (the directory synced): a power cut at any moment
    leaves the old file or the new one, never half of one, on a Pi's FAT partition as anywhere."""
    directory = posixpath.dirname(path) or "/"
    synced = " ".join(shell_word(each) for each in (new, *also_synced))
    # The folder's sync is best effort (a filesystem that cannot sync a folder has nothing more
    # to give); the rename has happened by then, so it does not fail the step.
    return (f"sync -- {synced} && mv -f -- {shell_word(new)} {shell_word(path)} && "
            f"{{ sync -- {shell_word(directory)} 2>/dev/null || true; }}")


@operation()
def config_txt_block(path: str, lines: list[str], label: str, backup_suffix: str):
    """A Pi's config.txt holds `lines` in a roslab-marked block (roslab.operations.managed_block),
    or, where the file does not exist (a PC, a container), nothing is created: no firmware here
    reads it. The file is copied to `<path><backup_suffix>` before it changes (the upload that
    follows syncs the file and its directory: roslab.remote_files).

    + path: the file (/boot/firmware/config.txt)
    + lines: its lines (the block starts with [all], so no conditional section above swallows them)
    + label: names the block in its markers
    + backup_suffix: the backup's suffix (``.roslab-<date>-<time>``)
    """
    from roslab.operations import managed_block

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


@operation()
def service_installed_not_running(service: str, because: str):
    """A unit is stopped and not enabled, for `because` (a setting says it must not run yet:
    the rover before calibration, a board not yet present); it stays installed.

    + service: the unit (``osr_startup.service``)
    + because: why, for the no-op line and the operation's name
    """
    from pyinfra.facts.systemd import SystemdEnabled, SystemdStatus

    running = (host.get_fact(SystemdStatus, services=[service]) or {}).get(service)
    enabled = (host.get_fact(SystemdEnabled, services=[service]) or {}).get(service)
    if not running and not enabled:
        host.noop(f"{service} is installed but not enabled because {because}")
        return
    if running:
        yield f"systemctl stop {shell_word(service)}"
    if enabled:
        yield f"systemctl disable {shell_word(service)}"
