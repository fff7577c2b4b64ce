"""udev: it re-reads its rules after a change (roslab.ops)."""

from __future__ import annotations

from pyinfra.api import operation


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
