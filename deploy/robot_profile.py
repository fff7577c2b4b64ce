"""The robot profile's host changes: its udev rules, the login user's groups.

The profile's packages are ros_install's (deploy/ros_install.py `ros_packages`), its variables
are in the shell block and the service's unit (roslab.ros_env.host_environment), its launch
is the workspace's service (deploy/workspace.py): this step adds what belongs to none of them.
Everything comes resolved from the roster (`host.data.roslab_profile`, see roslab/profiles).
"""

from __future__ import annotations

from io import StringIO

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.facts.files import File
from pyinfra.operations import files

from deploy.common import existing_login_home, login_user, should_run
from roslab import probe, settings
from roslab.profiles.host import udev_reloaded, user_in_groups, user_in_groups_reads
from roslab.profiles.resolve import UDEV_RULES_PATH

DEFAULTS = settings.defaults("robot_profile")


def profile() -> dict:
    return host.data.get("roslab_profile") or {}


@deploy("The robot profile's udev rules and groups are in place", data_defaults=DEFAULTS)
def robot_profile():
    """Write the profile's udev rules (and reload udev), put the login user in its groups.

    Reads host.data: robot_profile_enabled, roslab_profile (udev_rules, groups, name),
    login_user, ssh_user.
    """
    if not should_run("robot_profile_enabled"):
        return
    name = profile().get("name") or "demo"
    rules = profile().get("udev_rules") or ""
    if rules:
        written = files.put(
            name=f"Ensure {UDEV_RULES_PATH} holds robot profile {name}'s udev rules",
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
    groups = profile().get("groups") or []
    if groups and existing_login_home() is not None:
        user = login_user()
        user_in_groups(name=f"Ensure {user} is in {', '.join(groups)} (robot profile {name})",
                       user=user, groups=groups)


@probe.reader
def robot_profile_reads() -> list:
    """What robot_profile's operations read on a host that needs no change."""
    if not should_run("robot_profile_enabled"):
        return []
    reads = probe.put_reads(UDEV_RULES_PATH) if profile().get("udev_rules") else \
        [probe.read(File, path=UDEV_RULES_PATH)]
    if profile().get("groups") and existing_login_home() is not None:
        reads += user_in_groups_reads(login_user())
    return reads
