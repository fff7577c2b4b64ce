"""A team that switches robot profile (osr -> demo) keeps nothing of the old one that could act.

Runs last: the new profile's units, groups and sources are in place. From the host's record of
what roslab wrote for its profile (roslab/ops/profile_record.py), the units of an earlier profile
are stopped, disabled and removed, and the login user leaves the groups roslab added for it;
what stays (a boot config block, whose removal needs a reboot; the login user's venv; the
underlay's last build) is said in one warning line per host, in the run that switches. The
record is then rewritten, so the next run is a no-op.
"""

from __future__ import annotations

from pyinfra import host, logger
from pyinfra.api import deploy

from deploy.common import existing_login_home, login_user, should_run, where
from deploy.profile_services import MANAGED_MARK
from roslab import probe, settings
from roslab.ops.boot_config import CONFIG_TXT
from roslab.ops.users import UserGroups
from roslab.ops.profile_record import ProfileRecord, profile_recorded, profile_units_gone, user_left_groups
from roslab.host_settings import host_settings
from roslab.profiles.resolve import ResolvedProfile

DEFAULTS = settings.defaults("robot_profile")


def profile() -> ResolvedProfile | None:
    return host_settings(host).roslab_profile


def underlay_sourced(typed) -> bool:
    """Whether ~/.bashrc and the nodes source the underlay: while the host has any repositories,
    its profile's or the class's (the roster's workspace_sources), as deploy/sources.py and
    deploy/shell_env.py decide it, not only while its profile names some."""
    return bool(typed.sources_enabled and typed.roslab_sources)


def wanted_record(previous: dict, current_groups: list[str] | None) -> dict:
    """What roslab wrote for the host's profile as of this run: the groups it added are those of
    the profile the user was not in before roslab (kept from the record while still named)."""
    resolved, typed = profile(), host_settings(host)
    groups = set(resolved.groups if resolved else [])
    added = set(previous.get("groups_added") or []) & groups
    if current_groups is not None:
        added |= {group for group in groups if group not in current_groups}
    tweaks = resolved.os_tweaks if resolved and typed.profile_os_tweaks else {}
    return {
        "profile": resolved.name if resolved else "demo",
        "groups_added": sorted(added),
        "boot_config": list(resolved.boot_config.get("config_txt") or []) if resolved else [],
        "venv": resolved.python.venv if resolved and typed.python_env_enabled else None,
        "sources": underlay_sourced(typed),
        "masked_units": sorted(tweaks.get("mask_units") or []),
    }


def kept_after_switch(previous: dict, record: dict) -> list[str]:
    """What an earlier profile left that roslab does not remove, each with why."""
    kept = []
    if previous.get("boot_config") and not record["boot_config"]:
        kept.append(f"its boot config block in {CONFIG_TXT} ({', '.join(previous['boot_config'])}): taking it "
                    "out needs a reboot, which roslab never does; delete the block by hand when the Pi may reboot")
    if previous.get("venv") and previous["venv"] != record["venv"]:
        kept.append(f"its venv ~/{previous['venv']}: the login user's files; delete it by hand if unused")
    if previous.get("sources") and not record["sources"]:
        kept.append("its underlay's last build in sources_underlay_dir (the host has no repositories now: they "
                    "are removed, and ~/.bashrc and the nodes no longer source the build): delete it by hand")
    unmasked = sorted(set(previous.get("masked_units") or []) - set(record["masked_units"]))
    if unmasked:
        kept.append(f"the units its OS tweaks masked ({', '.join(unmasked)}) and any swap file: an OS "
                    "setting roslab never undoes (systemctl unmask, swapoff by hand)")
    return kept


@deploy("Nothing of an earlier robot profile is left that no profile names", data_defaults=DEFAULTS)
def profile_switch_cleaned():
    """Remove the units and groups an earlier robot profile left, say what stays, and record
    what this profile wrote.

    Reads host_settings(host): robot_profile_enabled, profile_services_enabled, python_env_enabled,
    roslab_profile (name, groups, services, boot_config, python, sources), login_user, ssh_user.
    """
    if not should_run("robot_profile_enabled"):
        return
    seen = host.get_fact(ProfileRecord, mark=MANAGED_MARK)
    previous = seen["record"] or {}
    home = existing_login_home()
    user = login_user()
    current_groups = host.get_fact(UserGroups, user=user) if home is not None else None
    record = wanted_record(previous, current_groups)
    removed = []
    current_profile = profile()
    if should_run("profile_services_enabled"):
        named = {service.name for service in (current_profile.services if current_profile else [])}
        stale = [unit for unit in seen["units"] if unit not in named]
        if stale:
            profile_units_gone(name=f"Ensure {', '.join(f'{unit}.service' for unit in stale)} of an earlier robot "
                                    "profile is stopped, disabled and removed", units=stale)
            removed += [f"{unit}.service" for unit in stale]
    leave = sorted(group for group in set(previous.get("groups_added") or []) - set(current_profile.groups if current_profile else [])
                   if current_groups is not None and group in current_groups)
    if leave:
        user_left_groups(name=f"Ensure {user} is no longer in {', '.join(leave)} (added for robot profile "
                              f"{previous.get('profile')})", user=user, groups=leave)
        removed.append(f"{user} from groups {', '.join(leave)}")
    old = previous.get("profile")
    if old and old != record["profile"] and (removed or kept_after_switch(previous, record)):
        kept = kept_after_switch(previous, record)  # (a host the switch left untouched gets no line)
        said = [f"removed {'; '.join(removed)}" if removed else "nothing of it to remove",
                *(["kept " + "; ".join(kept)] if kept else [])]
        logger.warning(f"{host.print_prefix}roslab: {where()}: robot profile {old} -> {record['profile']}: "
                       + "; ".join(said))
    wrote = any(value for key, value in record.items() if key != "profile")
    if wrote or seen["record"] is not None:  # a profile that writes none of it needs no record
        profile_recorded(name=f"Ensure the host records what robot profile {record['profile']} wrote",
                         record=record, mark=MANAGED_MARK)


@probe.reader
def profile_switch_reads() -> list:
    """What profile_switch_cleaned reads on a host that needs no change."""
    if not should_run("robot_profile_enabled"):
        return []
    reads = [probe.read(ProfileRecord, mark=MANAGED_MARK)]
    if existing_login_home() is not None:
        reads.append(probe.read(UserGroups, user=login_user()))
    return reads
