"""What roslab wrote on a host for its robot profile, and what goes when the profile changes.

The host keeps a record (`/var/lib/roslab/profile.json`, written by the last run): the profile,
the groups roslab added the login user to (not those it was in before), the boot config lines,
the venv, whether it had sources and the units its OS tweaks masked. Groups added before a
host had the record are not known as roslab's, so they stay. A team switching profile (osr -> demo) then loses what no
profile of it names any more: the profile's units (each found by the mark on its first line, so
a host converged before the record existed is cleaned too) are stopped, disabled and removed,
and the login user leaves the groups roslab added for the old profile. What stays is said per
host in one line, with why (deploy/profile_switch.py). The udev rules file is
deploy/robot_profile.py's (removed when the profile has none), the underlay's repositories
deploy/sources.py's.
"""

from __future__ import annotations

import json

from pyinfra import host
from pyinfra.api import FactBase, operation

from roslab.ops.files import durably_renamed, run_temporary
from roslab.quoting import shell_word

PROFILE_RECORD = "/var/lib/roslab/profile.json"
UNIT_DIR = "/etc/systemd/system"
_UNITS_MARK = "#units"


class ProfileRecord(FactBase):
    """The host's record of what roslab wrote for its profile (None: none, or not readable as
    roslab writes it), and the profile units in /etc/systemd/system whose first line starts with
    `mark`: ``{"record": dict | None, "units": ["osr_startup", ...]}``."""

    def command(self, mark: str) -> str:
        return (f"cat {PROFILE_RECORD} 2>/dev/null; echo; echo '{_UNITS_MARK}'; "
                f"for unit in {UNIT_DIR}/*.service; do [ -f \"$unit\" ] && [ ! -L \"$unit\" ] || continue; "
                f"case \"$(head -n 1 \"$unit\")\" in {shell_word(mark)}*) echo \"$unit\";; esac; done; true")

    def process(self, output):
        text, units, in_units = [], [], False
        for line in output:
            if line.strip() == _UNITS_MARK:
                in_units = True
            elif in_units:
                name = line.strip().rsplit("/", 1)[-1]
                if name.endswith(".service"):
                    units.append(name.removesuffix(".service"))
            else:
                text.append(line)
        try:
            record = json.loads("\n".join(text)) if "".join(text).strip() else None
        except ValueError:
            record = None
        return {"record": record if isinstance(record, dict) else None, "units": sorted(units)}


@operation()
def profile_units_gone(units: list[str]):
    """Units an earlier robot profile installed and no profile names any more are stopped,
    disabled and removed (the rover's `osr_startup` must not keep driving it).

    + units: unit names without `.service`, each one roslab wrote (its mark found by the caller)
    """
    if not units:
        host.noop("no unit of an earlier robot profile is left")
        return
    for unit in units:
        word = shell_word(f"{unit}.service")
        yield (f"systemctl disable --now {word} >/dev/null 2>&1; systemctl reset-failed {word} >/dev/null 2>&1; "
               f"rm -f -- {shell_word(f'{UNIT_DIR}/{unit}.service')}")
    yield "systemctl daemon-reload"


@operation()
def user_left_groups(user: str, groups: list[str]):
    """The login user leaves `groups` (ones roslab added for an earlier profile, named by no
    profile now); the user's other groups stay.

    + user: the account
    + groups: groups to leave
    """
    if not groups:
        host.noop(f"{user} is in no group an earlier robot profile added")
        return
    for group in groups:
        yield f"gpasswd -d {shell_word(user)} {shell_word(group)} >/dev/null"


@operation()
def profile_recorded(record: dict, mark: str):
    """The host's record of what roslab wrote for its profile is `record` (world-readable:
    no secret in it; written whole, synced, renamed).

    + record: {"profile", "groups_added", "boot_config", "venv", "sources", "masked_units"}
    + mark: the profile units' first line (ProfileRecord's argument, read once for both)
    """
    current = host.get_fact(ProfileRecord, mark=mark)["record"]
    if current == record:
        host.noop(f"{PROFILE_RECORD} already records robot profile {record.get('profile')}")
        return
    new = run_temporary(PROFILE_RECORD)
    text = json.dumps(record, sort_keys=True)
    yield (f"mkdir -p {shell_word(PROFILE_RECORD.rsplit('/', 1)[0])} && printf '%s\\n' {shell_word(text)} > "
           f"{shell_word(new)} && chmod 644 {shell_word(new)} && {durably_renamed(new, PROFILE_RECORD)}")
