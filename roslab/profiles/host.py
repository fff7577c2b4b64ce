"""Operations and facts for what a robot profile changes on a host besides packages and files.

    UserGroups / user_in_groups   the login user in the profile's groups (dialout for serial ports)
    udev_reloaded                 udev re-reads its rules and replays the add events (after a change)
"""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import FactBase, operation

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


# Where udevd runs (a Pi), it re-reads its rules and replays "add" for the serial and USB
# devices, so a board plugged in before the run gets its name and mode now. Where it does
# not run (a container), the rules apply at the next boot; the command says which.
UDEV_RELOAD = (
    "if systemctl is-active --quiet systemd-udevd; then "
    "udevadm control --reload-rules && "
    "udevadm trigger --action=add --subsystem-match=tty --subsystem-match=usb && "
    "echo 'udev rules reloaded'; "
    "else echo 'systemd-udevd is not running here: the rules apply from the next boot'; fi"
)


@operation(is_idempotent=False)
def udev_reloaded():
    """udev has read the current rules (run it with `_if=` the rules file's change).

    Example: ``udev_reloaded(name="...", _if=rules.did_change)``
    """
    yield UDEV_RELOAD
