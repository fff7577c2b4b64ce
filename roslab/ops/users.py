"""Users: the login user's groups, and running an operation or fact as a user (facts and
operations side by side, roslab.ops)."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import FactBase, OperationError, operation

from roslab.quoting import shell_word


def as_user(user: str) -> dict:
    """pyinfra arguments that run an operation or fact as `user` (rosdep and colcon refuse root)."""
    return {"_sudo": True, "_sudo_user": user}


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
