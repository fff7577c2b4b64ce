"""`roslab init DIR`: a classroom folder to run a class from, without a clone of roslab.

    roslab init DIR
    cd DIR && roslab check && pyinfra -y inventory.py deploy.py

Writes, refusing to overwrite anything that is there:
- `classroom.yaml`: a commented roster to fill in (the teacher's public key filled in when
  this machine has one in ~/.ssh);
- `secrets.yaml`: the secrets file the roster names, mode 0600 from its first byte;
- `inventory.py` and `deploy.py`: what pyinfra needs in the folder, two lines each, running
  the installed roslab's inventory and deploy (`roslab.packaged`); the demo nodes come from
  the installed package too. Upgrading roslab upgrades the class's deploy; the folder
  keeps only the teacher's files.
- `.gitignore`: secrets.yaml and `.roslab-state/` (host keys, known_hosts, runs) stay out of git.

Works the same from a checkout (the checkout's deploy.py and nodes/ are the package's).
Exit status: 0 written, 1 when a file is already there or the folder cannot be written.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

INVENTORY = '''\
"""pyinfra inventory of this classroom folder, written by `roslab init`: classroom.yaml beside it
(or $ROSLAB_ROSTER). Groups: main, robot, one per team, one per distro."""

from roslab.packaged import classroom_inventory as _classroom_inventory

globals().update(_classroom_inventory(__file__))
'''

DEPLOY = '''\
"""pyinfra deploy of this classroom folder, written by `roslab init`: the installed roslab's
classroom deploy (every step, in order; see roslab's docs/deploys.md)."""

from roslab.packaged import run_deploy as _run_deploy

_run_deploy()
'''

SECRETS = '''\
# Secrets of the classroom in classroom.yaml (written by `roslab init`; mode 0600: keep it so,
# roslab refuses a secrets file other users can read). Never commit it.
# name: value, named from the roster by its `*_secret` keys, e.g.:
# classroom_wifi: "the WiFi password"          (wifi_password_secret: classroom_wifi)
# pi_sudo: "the Pis' sudo password"            (sudo_password_secret: pi_sudo; only if sudo asks)
{}
'''

GITIGNORE = '''\
# written by `roslab init`: secrets and each Pi's host keys stay on this machine
secrets.yaml
.roslab-state/
'''

ROSTER = '''\
# The classroom roster (written by `roslab init`). Check it with `roslab check`, preview
# with `pyinfra inventory.py deploy.py --dry`, provision with `pyinfra -y inventory.py deploy.py`.
#
# Any setting (`roslab check` names unknown ones; roslab's docs/roster-and-settings.md lists
# them all with their defaults) may be set at three levels, later wins: under `classroom:`
# (every host), on a team (its hosts), or on a host.

classroom:
  name: {name}
  # The user roslab logs in as over SSH (the Ubuntu image's default user); it provisions
  # through sudo.
  ssh_user: ubuntu
  # Ubuntu release the Pis run; it picks the ROS 2 distro (24.04 -> jazzy, 22.04 -> humble).
  # Quote it: YAML reads 24.04 as a number.
  ubuntu_release: "24.04"
  # The teacher's public keys (key lines or .pub files on this machine): every Pi authorises
  # them, and `roslab seed` writes them into each Pi's first-boot seed.
{keys}
  # How each team's hosts find each other: multicast (DDS's own), or on a WiFi that drops
  # multicast static (each host's peers are its team's) or discovery_server (a server on each
  # team's main). A team may set its own.
  # ros_discovery_mode: static
  # Passwords live in secrets.yaml beside this file (mode 0600), named here, e.g.:
  # wifi_password_secret: classroom_wifi
  # sudo_password_secret: pi_sudo

teams:
  # Each team: its own settings, then its hosts. A team has at most one main host (the
  # students' workstation) and any number of robots. Team names are pyinfra groups
  # (`pyinfra -y inventory.py deploy.py --limit team1`).
  team1:
    # ROS_DOMAIN_ID (0 to 101): every team has its own; without one, roslab picks a free one
    # from the team's name (`roslab check` shows it).
    ros_domain_id: 11
    hosts:
      team1-main:
        role: main
        # Where SSH reaches the Pi now (an address or a DNS name; default: the host name).
        address: 192.168.50.11
      team1-robot:
        role: robot
        address: 192.168.50.12
'''

KEY_FILES = ("id_ed25519.pub", "id_ecdsa.pub", "id_rsa.pub")


def teacher_keys_lines(home: Path) -> str:
    found = [home / ".ssh" / name for name in KEY_FILES if (home / ".ssh" / name).is_file()]
    if found:
        return f"  teacher_ssh_keys:\n    - {found[0]}"
    return ("  # No public key was found in ~/.ssh: make one (ssh-keygen -t ed25519) and name it here.\n"
            "  # teacher_ssh_keys:\n  #   - ~/.ssh/id_ed25519.pub")


def files(folder: Path, home: Path) -> dict[str, tuple[str, int]]:
    """name -> (text, mode) of the folder's files."""
    name = "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "-" for c in folder.resolve().name)
    return {
        "classroom.yaml": (ROSTER.format(name=name.strip("-") or "classroom", keys=teacher_keys_lines(home)), 0o644),
        "secrets.yaml": (SECRETS, 0o600),
        "inventory.py": (INVENTORY, 0o644),
        "deploy.py": (DEPLOY, 0o644),
        ".gitignore": (GITIGNORE, 0o644),
    }


def write_new(path: Path, text: str, mode: int) -> None:
    """Create `path` with `mode` from its first byte (O_EXCL: never over an existing file)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), mode)
    try:
        os.fchmod(fd, mode)  # whatever the umask
        os.write(fd, text.encode("utf-8"))
    finally:
        os.close(fd)


def run(args: argparse.Namespace) -> int:
    folder = Path(args.folder)
    planned = files(folder, Path.home())
    there = [name for name in planned if os.path.lexists(folder / name)]
    if there:
        print(f"roslab init: {folder} already has {', '.join(there)}; nothing was written "
              "(roslab init never overwrites a file)", file=sys.stderr)
        return 1
    try:
        folder.mkdir(parents=True, exist_ok=True)
        for name, (text, mode) in planned.items():
            write_new(folder / name, text, mode)
    except OSError as error:
        print(f"roslab init: cannot write in {folder}: {error.strerror or error}", file=sys.stderr)
        return 1
    print(f"A classroom folder in {folder}:")
    for name in planned:
        print(f"  {name}")
    print(f"\nNext: cd {folder}, fill in classroom.yaml (and secrets.yaml), then\n"
          "  roslab check                             # the roster, without touching any host\n"
          "  pyinfra inventory.py deploy.py --dry     # what would change\n"
          "  pyinfra -y inventory.py deploy.py        # provision (-y: without asking)\n"
          "  roslab status                            # the class at a glance")
    return 0


def register(commands) -> None:
    init = commands.add_parser(
        "init", help="make a classroom folder (roster, secrets file, pyinfra entry files)",
        description=__doc__.splitlines()[0])
    init.add_argument("folder", metavar="DIR", help="the folder (created if missing)")
    init.set_defaults(run=run)
