"""The `roslab` command.

    roslab init DIR           make a classroom folder: roster, secrets file, pyinfra entry files
    roslab check [ROSTER]     validate a roster and print the classroom as a table
    roslab verify [ROSTER]    check that each team's main host hears its robot (roslab.cli.verify)
    roslab seed [ROSTER] --out DIR | --boot-partition PATH | --image FILE
                              first-boot seeds for freshly flashed Pis (roslab.seed)
    roslab flash [ROSTER] --image IMG --device DEV ...
                              write a tray of SD cards at once, each seeded and verified (roslab.seed.flash)
    roslab trust [ROSTER]     record the host key of Pis flashed without a seed (roslab.cli.trust)
    roslab forget [ROSTER] --limit NAME
                              remove a Pi's recorded host key (roslab.cli.trust)
    roslab opencr-update [ROSTER] --limit NAME
                              flash a TurtleBot3's OpenCR firmware (roslab.robot_tools.opencr_update)
    roslab esp32-firmware [ROSTER] [--limit NAME]
                              print each ESP32 team's flash command (roslab.robot_tools.esp32_firmware)
    roslab status [ROSTER]    every host's state, as a table and an HTML page (roslab.cli.status)

Every command takes the roster and its hosts one way (roslab.reach): ROSTER first, then
`--limit NAME` (repeatable: a team, role or distro group, or host names with wildcards)
where it reaches hosts.
`roslab sandbox ...` comes from `roslab.sandbox.cli` when that module is present.
Exit status: 0 when the roster is valid, 1 when it has errors, 2 on bad usage.
"""

from __future__ import annotations

import argparse
import sys

from roslab import __version__
from roslab.reach import RosterProblem, add_roster_argument, load_classroom
from roslab.host_settings import HostSettings
from roslab.roster import Classroom, display_path

TABLE_COLUMNS = ("TEAM", "HOST", "ROLE", "ADDRESS", "UBUNTU", "DISTRO", "VARIANT", "DOMAIN", "DISCOVERY", "PROFILE")


def profile_cell(typed: HostSettings) -> str:
    """The host's robot profile and its settings, as a teacher checks them before deploying:
    `turtlebot3 (burger, LDS-03)`. A setting whose values are words of its own (allowed) shows
    its value; a yes/no, a number or free text (a serial number) shows `name=value`."""
    from roslab.profiles.library import builtin_profiles

    profile = typed.roslab_profile
    if profile is None:
        return typed.robot_profile or "-"
    builtin = builtin_profiles().get(profile.name)  # a roster's own profile: every setting as name=value
    declared = builtin.settings if builtin is not None else {}
    words = []
    for name, value in profile.settings.items():
        setting = declared.get(name)
        bare = setting is not None and setting.allowed and str(value) not in ("true", "false")
        words.append(str(value) if bare else f"{name}={value}")
    return profile.name + (f" ({', '.join(words)})" if words else "")


def classroom_table(classroom: Classroom) -> str:
    """The classroom as aligned columns, one host per line."""
    rows = [TABLE_COLUMNS]
    for host in classroom.hosts:
        rows.append((
            host.team,
            host.name,
            host.role,
            host.address,
            host.ubuntu_release or "-",
            host.distro or "-",
            host.variant or "-",
            "-" if host.ros_domain_id is None else
            str(host.ros_domain_id) + (" (auto)" if host.domain_assigned else ""),
            host.settings.ros_discovery_mode or "-",
            profile_cell(host.settings),
        ))
    widths = [max(len(row[column]) for row in rows) for column in range(len(TABLE_COLUMNS))]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows
    )


def run_check(args: argparse.Namespace) -> int:
    try:
        classroom = load_classroom(args.roster, "check")
    except RosterProblem as problem:
        print(problem, file=sys.stderr)
        return 1
    path = classroom.path
    for warning in classroom.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    title = f"Classroom {classroom.name!r}" if classroom.name else "Classroom"
    middleware = classroom.hosts[0].settings.ros_middleware if classroom.hosts else None
    print(f"{title} ({display_path(path)}): {len(classroom.teams)} teams, {len(classroom.hosts)} hosts"
          + (f", middleware {middleware}" if middleware else ""))
    print(classroom_table(classroom))
    return 0


def run_verify(args: argparse.Namespace) -> int:
    from roslab.cli.verify import run  # connects to hosts: imported only when asked

    return run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="roslab", description="Provision ROS 2 onto a classroom of Raspberry Pis."
    )
    parser.add_argument("--version", action="version", version=f"roslab {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    check = commands.add_parser(
        "check",
        help="validate a roster without deploying and print the classroom",
        description="Validate a roster without touching any host; print the classroom as a "
        "table. Exits 1 if the roster has errors.",
    )
    add_roster_argument(check, limit=False)
    check.set_defaults(run=run_check)

    verify = commands.add_parser(
        "verify",
        help="check that each team's main host hears its robot",
        description="Read-only: on each team's main host, listen for the robot's messages with "
        "the team's domain ID and print a table per team. Exits 1 unless every team is heard.",
    )
    add_roster_argument(verify)
    verify.set_defaults(run=run_verify)

    from roslab.cli import init, lock, trust
    from roslab.seed import command as seed_command, flash

    # roslab init, seed, flash, trust and forget, lock
    for register_command in (init.register, seed_command.register, flash.register, trust.register, lock.register):
        register_command(commands)

    from roslab.robot_tools import register_profile_tools

    register_profile_tools(commands)  # what the robot profiles bring: roslab opencr-update

    status = commands.add_parser(
        "status",
        help="show every host's state as a table and an HTML page",
        description="Read-only: reach every host (in parallel, bounded) and show whether it answers, "
        "its Ubuntu release, ROS 2 distro, domain ID, address, nodes service and last deploy run; "
        "as a table and as one self-contained HTML page with a picture of each team. "
        "Exits 1 if a host is unreachable.",
    )
    from roslab.cli.status import build_parser as status_arguments, run as run_status

    status_arguments(status)
    status.set_defaults(run=run_status)

    try:
        from roslab.sandbox.cli import register
    except ModuleNotFoundError as exc:
        if exc.name not in ("roslab.sandbox", "roslab.sandbox.cli"):
            raise  # the sandbox exists but is broken: say so
    else:
        register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.run(args)


if __name__ == "__main__":
    sys.exit(main())
