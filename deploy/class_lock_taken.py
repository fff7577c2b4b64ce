"""The class lock taken by the run itself (`class_lock_auto: true`; roslab.class_lock_auto).

The last step of a host whose (distro, architecture) group classroom.lock lacks: it reads the
host's installed packages once every other step of the host has run (`dpkg-query`, as
`roslab lock` reads them) and notes them for the controller, which writes the lock once at the
end of the run. A host whose group is locked gets no step and no read; --dry executes nothing.
"""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.api.facts import get_fact
from pyinfra.facts.server import Arch
from pyinfra.operations import python

from deploy.common import host_distro, host_is_active
from roslab import class_lock, class_lock_auto, probe, settings
from roslab.ops import class_lock as lock_ops
from roslab.host_settings import host_settings

DEFAULTS = settings.defaults("ros_install")


def group_locked(roster_path: str, distro: str) -> bool:
    """Whether the lock beside the roster holds this host's group (no lock file: no read)."""
    lock = class_lock.lock_beside(roster_path)
    if lock is None or not lock.groups:
        return False
    return class_lock.host_group(roster_path, distro, host.get_fact(Arch)) is not None


def installed_noted(state, host, roster_path: str, distro: str) -> None:
    """Run time, after the host's other steps: its installed packages, noted for the lock.
    (pyinfra's python.call passes `state` and `host` to a function that names them.)"""
    reading = get_fact(state, host, lock_ops.InstalledVersions)
    key = class_lock.group_key(distro, reading["architecture"])
    class_lock_auto.note_installed(roster_path, host.name, key, reading["packages"])


@deploy("The class lock holds the host's group (class_lock_auto)", data_defaults=DEFAULTS)
def class_lock_taken():
    """Read the host's installed versions for classroom.lock, if its group is not locked yet.

    Reads host_settings(host): class_lock_auto, roslab_roster_path, ros_distro.
    """
    typed = host_settings(host)
    roster_path = typed.roslab_roster_path
    if not host_is_active() or not typed.class_lock_auto or not roster_path:
        return  # off (the default): only `roslab lock` takes the lock; or a hand-made inventory
    distro = host_distro()
    if group_locked(roster_path, distro):
        return  # a run never rewrites a locked group: `roslab lock --update` moves it
    python.call(
        name=f"Read the installed versions for {class_lock.LOCK_FILE} (its group is not locked yet)",
        function=installed_noted, roster_path=roster_path, distro=distro,
    )


@probe.reader
def class_lock_taken_reads() -> list:
    """What class_lock_taken reads while planning: the architecture, where a lock has groups."""
    typed = host_settings(host)
    if not typed.class_lock_auto or not typed.roslab_roster_path:
        return []
    lock = class_lock.lock_beside(typed.roslab_roster_path)
    return [probe.read(Arch)] if lock is not None and lock.groups else []
