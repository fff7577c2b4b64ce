"""The robot profile's host changes: its udev rules, the login user's groups, apt packages it
removes (brltty, which grabs USB-serial adapters), its boot configuration (a Pi's config.txt
block and cmdline.txt words, recorded as "reboot needed": roslab never reboots), and (opt-in,
`profile_os_tweaks`) the OS changes its maker recommends: masked units, a swap file.

The profile's packages are ros_install's (deploy/ros_install.py `ros_packages`), its variables
are in the shell block and the service's unit (roslab.ros.environment.host_environment), its launch
is the workspace's service (deploy/workspace.py): this step adds what belongs to none of them.
Everything comes resolved from the roster (`host_settings(host).roslab_profile`, see roslab/profiles).
"""

from __future__ import annotations

import posixpath
from io import StringIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.facts.files import File
from pyinfra.operations import apt, files

from deploy.common import existing_login_home, login_user, should_run
from roslab import probe, settings
from roslab.reporting import summary
from roslab.ops.files import BACKUP_SUFFIX, managed_block, managed_block_reads
from roslab.ops.boot_config import (
    CMDLINE_TXT,
    CONFIG_TXT,
    CmdlineText,
    RebootRecord,
    cmdline_words_kept,
    config_txt_block,
    reboot_needed_recorded,
    reboot_pending,
    reboot_record_current,
)
from roslab.ops.memory import MemoryTotal, SwapFile, swap_file_on
from roslab.ops.systemd import UnitsMasked, units_masked
from roslab.ops.udev import udev_reloaded
from roslab.ops.users import user_in_groups, user_in_groups_reads
from roslab.profiles.resolve import UDEV_RULES_PATH
from roslab.host_settings import host_settings
from roslab.profiles.resolve import ResolvedProfile

DEFAULTS = settings.defaults("robot_profile")
SWAP_FILE = "/swapfile"
FSTAB = "/etc/fstab"
FSTAB_LABEL = "robot profile swap file"
BOOT_CONFIG_LABEL = "robot profile boot config"


def profile() -> ResolvedProfile | None:
    return host_settings(host).roslab_profile


@deploy("The robot profile's udev rules, groups, removed packages, boot config and opted-in OS tweaks "
        "are in place", data_defaults=DEFAULTS)
def robot_profile():
    """Write the profile's udev rules (and reload udev), put the login user in its groups,
    remove the apt packages it removes, keep its boot config (a reboot it needs is recorded and
    reported, never done) and, where the roster opts in, apply the profile's OS tweaks.

    Reads host_settings(host): robot_profile_enabled, roslab_profile (udev_rules, groups, name, os_tweaks,
    remove_apt_packages, boot_config), profile_os_tweaks, login_user, ssh_user.
    """
    if not should_run("robot_profile_enabled"):
        return
    resolved = profile()
    name = resolved.name if resolved else "demo"
    removed = resolved.remove_apt_packages if resolved else []
    if removed:
        # Before the udev rules: brltty's own rules claim CP210x and CH340 adapters.
        apt.packages(name=f"Ensure {', '.join(removed)} is not installed (robot profile {name})",
                     packages=removed, present=False)
    rules = resolved.udev_rules if resolved else ""
    if rules:
        written = files.put(
            name=f"Ensure {posixpath.basename(UDEV_RULES_PATH)} holds robot profile {name}'s udev rules",
            src=StringIO(rules), dest=UDEV_RULES_PATH, user="root", group="root", mode="644",
        )
    elif host.get_fact(File, path=UDEV_RULES_PATH):
        written = files.file(
            name=f"Ensure {UDEV_RULES_PATH} is gone (robot profile {name} has no udev rules here)",
            path=UDEV_RULES_PATH, present=False,
        )
    else:
        written = None
    if written is not None:
        udev_reloaded(name="Ensure udev has read the robot profile's rules", _if=written.did_change)
    groups = resolved.groups if resolved else []
    if groups and existing_login_home() is not None:
        user = login_user()
        user_in_groups(name=f"Ensure {user} is in {', '.join(groups)} (robot profile {name})",
                       user=user, groups=groups)
    boot_config_kept(name, resolved.boot_config if resolved else {})
    tweaks = os_tweaks()
    if tweaks:
        os_tweaks_applied(name, tweaks)


def boot_config_kept(name: str, boot: dict) -> None:
    """The profile's boot config on a Pi's boot partition; a change is recorded as "reboot
    needed" (the run summary and `roslab status` say so until the host has rebooted)."""
    lines, added, words = (boot.get(key) or [] for key in ("config_txt", "cmdline_add", "cmdline_remove"))
    if not lines and not added and not words:
        return
    record = host.get_fact(RebootRecord)
    if record["exists"] and not reboot_pending(record):
        reboot_record_current(name="Ensure a reboot record from before the last reboot is gone")
    changes, reasons = [], []
    if lines:
        changes.append(config_txt_block(
            name=f"Ensure {CONFIG_TXT} holds robot profile {name}'s boot config ({', '.join(lines)})",
            path=CONFIG_TXT, lines=lines, label=BOOT_CONFIG_LABEL, backup_suffix=BACKUP_SUFFIX))
        reasons.append(f"{CONFIG_TXT} ({', '.join(lines)})")
    if added or words:
        parts = [*([f"with {', '.join(added)}"] if added else []), *([f"without {', '.join(words)}"] if words else [])]
        changes.append(cmdline_words_kept(
            name=f"Ensure {CMDLINE_TXT} is {' and '.join(parts)} (robot profile {name})",
            path=CMDLINE_TXT, add=added, remove=words, backup_suffix=BACKUP_SUFFIX))
        reasons.append(f"{CMDLINE_TXT} ({'; '.join(parts)})")
    reasons = [f"boot config changed: {reason}" for reason in reasons]
    reboot_needed_recorded(
        name="Ensure the host records that the boot config waits for a reboot",
        reasons=reasons, _if=lambda: any(change.did_change() for change in changes),
    )
    summary.record_reboot(reasons, record["reasons"] if reboot_pending(record) else [], changes)


def os_tweaks() -> dict:
    """The profile's OS tweaks for this host, or {} when the roster has not opted in."""
    resolved = profile()
    return resolved.os_tweaks if resolved and host_settings(host).profile_os_tweaks else {}


def swap_wanted(tweaks: dict, memory_mb: int | None) -> bool:
    """A swap file is made where the profile asks for one and the host's memory is at most its
    limit (no limit: always); a host whose memory cannot be read gets none."""
    if not tweaks.get("swap_mb"):
        return False
    limit = tweaks.get("swap_if_memory_mb_at_most")
    return limit is None or (memory_mb is not None and memory_mb <= limit)


def os_tweaks_applied(name: str, tweaks: dict) -> None:
    units = tweaks.get("mask_units") or []
    if units:
        units_masked(name=f"Ensure {', '.join(units)} are masked (robot profile {name}, profile_os_tweaks)",
                     units=units)
    if swap_wanted(tweaks, host.get_fact(MemoryTotal)):
        size = tweaks["swap_mb"]
        swap_file_on(name=f"Ensure {SWAP_FILE} ({size} MiB) is in use as swap (robot profile {name})",
                     path=SWAP_FILE, size_mb=size)
        managed_block(name=f"Ensure {FSTAB} turns {SWAP_FILE} on at boot", path=FSTAB,
                      content=f"{SWAP_FILE} none swap sw 0 0", label=FSTAB_LABEL)


@probe.reader
def robot_profile_reads() -> list:
    """What robot_profile's operations read on a host that needs no change."""
    if not should_run("robot_profile_enabled"):
        return []
    resolved = profile()
    reads = probe.put_reads(UDEV_RULES_PATH) if resolved and resolved.udev_rules else \
        [probe.read(File, path=UDEV_RULES_PATH)]
    if resolved and resolved.groups and existing_login_home() is not None:
        reads += user_in_groups_reads(login_user())
    if resolved and resolved.remove_apt_packages:
        reads += probe.packages_reads()
    boot = resolved.boot_config if resolved else {}
    if boot:
        reads += [probe.read(RebootRecord), probe.read(File, path=CONFIG_TXT)]
        if boot.get("config_txt"):
            reads += managed_block_reads(CONFIG_TXT)
        if boot.get("cmdline_remove") or boot.get("cmdline_add"):
            reads.append(probe.read(CmdlineText, path=CMDLINE_TXT))
    tweaks = os_tweaks()
    if tweaks.get("mask_units"):
        reads.append(probe.read(UnitsMasked, units=tweaks["mask_units"]))
    if tweaks.get("swap_mb"):
        reads.append(probe.read(MemoryTotal))
        reads += [probe.read(SwapFile, path=SWAP_FILE), *managed_block_reads(FSTAB)]
    return reads
