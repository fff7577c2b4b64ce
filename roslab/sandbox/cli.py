"""`roslab sandbox ...`: the sandbox classroom's command line."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import tempfile
from pathlib import Path

from . import card, card_image, lifecycle, pi_boot, publish, seeding
from .system import SandboxError


def register(subparsers) -> argparse.ArgumentParser:
    """Add `sandbox` and its subcommands to the `roslab` command's subparsers."""
    parser = subparsers.add_parser(
        "sandbox", help="boot, list and stop test hosts on this machine",
        description="Test hosts on this machine that look like a classroom of Pis. "
                    "The instance is named by $ROSLAB_SANDBOX (default: roslab).",
    )
    commands = parser.add_subparsers(dest="sandbox_command", required=True, metavar="COMMAND")
    up = commands.add_parser("up", help="boot the sandbox classroom (does nothing if it runs, but follows an edited --roster)")
    up.add_argument("--hosts", type=int, default=None, metavar="N",
                    help=f"number of hosts, in teams of two (default {lifecycle.DEFAULT_HOSTS})")
    up.add_argument("--desktop", action="append", default=[], metavar="HOST",
                    help="make HOST an Ubuntu Desktop-like host (NetworkManager instead of networkd); repeatable")
    up.add_argument("--roster", type=Path, metavar="FILE",
                    help="your class's roster: its hosts (names, teams, roles, releases) and its settings where "
                         "the sandbox can serve them (a note names each it cannot); status and ssh then use "
                         "its host names. Run again after editing the roster: the sandbox follows it (new "
                         "settings, hosts added or removed, the others kept) and says what changed")
    commands.add_parser("status", help="list the hosts and whether they answer")
    commands.add_parser("down", help="stop the hosts and remove everything the sandbox made")
    _register_reset(commands)
    _register_saved_states(commands)
    reboot = commands.add_parser("reboot", help="reboot a host")
    reboot.add_argument("host")
    ssh = commands.add_parser("ssh", help="log in to a host as the login user (or run CMD there)")
    ssh.add_argument("host")
    ssh.add_argument("cmd", nargs=argparse.REMAINDER, metavar="CMD")
    board = commands.add_parser(
        "board", help="start, stop or show a team's emulated board (an ESP32, an OSR's RoboClaws)",
        description="The emulated board of a team, by its robot profile. esp32_microros (esp32_transport: "
                    "udp): a program on this machine that publishes what firmware/esp32_microros publishes, "
                    "with the team's domain and node name (the values `roslab esp32-firmware` prints), "
                    "through the real micro-ROS agent on the team's host, and reconnects when the agent "
                    "restarts; needs ROSLAB_SANDBOX_SOURCES (it is built from the Micro-XRCE-DDS-Client "
                    "bundle). osr: stand-in RoboClaw motor controllers (addresses 128, 129, 130) on "
                    "/dev/serial1 inside the team's robot, answering the rover's real roboclaw_wrapper, which "
                    "then publishes /drive_state and /status.")
    board.add_argument("team")
    board.add_argument("action", choices=("start", "stop", "status"))
    board.add_argument("--roster", type=Path, metavar="FILE",
                       help="the roster the class was deployed with (default: the sandbox's own roster)")
    create3 = commands.add_parser(
        "create3", help="plug a stand-in Create 3 into a host (a TurtleBot 4's base), unplug it, or show it",
        description="A stand-in for a TurtleBot 4's Create 3 (an emulation of its web server, not the robot): "
                    "usb0 appears in HOST, the base answers at 192.168.186.2 on its other end and records "
                    "what roslab posts to it (domain, namespace, middleware, NTP server). Only HOST reaches it.")
    create3.add_argument("host")
    create3.add_argument("action", choices=("start", "stop", "status"))
    create3.add_argument("--firmware", default=None, metavar="VERSION",
                         help="the firmware it reports (default I.0.0.FastDDS, a Jazzy generation; H.x for Humble)")
    _register_publish(commands)
    _register_card_image(commands)
    parser.set_defaults(run=run)  # the `roslab` command calls args.run(args)
    return parser


def _register_card_image(commands) -> None:
    """`sandbox card-image FILE [--release R] [--board B]`."""
    card_image = commands.add_parser(
        "card-image", help="write the sandbox's own Pi-like card image (a stand-in for Ubuntu's), for `roslab flash`",
        description="Write an image of the sandbox's host image laid out as Ubuntu's Raspberry Pi preinstalled "
                    "image (FAT system-boot with config.txt, cmdline.txt and cloud-init's NoCloud files; ext4 "
                    "writable, as before its first boot). A STAND-IN for Ubuntu's arm64 download, which cannot "
                    "boot here: it is amd64, as the sandbox's hosts are. Flash it with `roslab flash ... "
                    "--architecture amd64`, then boot a host from the card: `roslab sandbox reset HOST --card DEV`.")
    card_image.add_argument("out", type=Path, metavar="FILE")
    card_image.add_argument("--release", default="24.04", choices=sorted(pi_boot.CONFIG_TXT),
                            help="the Ubuntu release it is (default %(default)s)")
    card_image.add_argument("--board", default="pi4", choices=pi_boot.PI_BOARDS,
                            help="whose config.txt and cmdline.txt it holds (default %(default)s)")


def _register_publish(commands) -> None:
    """`sandbox publish PACKAGE --bump` and `sandbox publish --revert`."""
    published = commands.add_parser(
        "publish", help="serve a newer version of a package, as the archive would after a sync (or --revert)",
        description="Move the sandbox's upstream on purpose (to rehearse `roslab lock --update`): PACKAGE's "
                    "newest .deb is served again as <version>+roslab<N>. A ROS package's index then lists only "
                    "the newer version, as packages.ros.org does; a Debian package's goes to every release's "
                    "-updates suite, the release keeping the older. Only this sandbox's archives change.")
    published.add_argument("package", nargs="?", metavar="PACKAGE")
    what = published.add_mutually_exclusive_group(required=True)
    what.add_argument("--bump", action="store_true", help="publish PACKAGE under a higher version")
    what.add_argument("--revert", action="store_true", help="serve the archives as `up` served them again")


def _register_reset(commands) -> None:
    """`sandbox reset HOST... [--unseeded | --seed DIR | --card IMG]`."""
    reset = commands.add_parser(
        "reset", help="re-flash hosts: a fresh image, booted (a seeded host keeps its SSH host key)",
        description="Give hosts a fresh image and boot them, as re-flashing a Pi's card would. A host made "
                    "by `up` or re-flashed with --seed counts as seeded and keeps its SSH host key; any "
                    "other host makes a new random one.")
    reset.add_argument("hosts", nargs="+", metavar="HOST")
    flash = reset.add_mutually_exclusive_group()
    flash.add_argument("--unseeded", action="store_true",
                       help="re-flash without a seed: a new random host key roslab does not know "
                            "(the host no longer counts as seeded)")
    flash.add_argument("--seed", type=Path, metavar="DIR",
                       help="re-flash one HOST with a NoCloud seed (user-data, meta-data, network-config, "
                            "as `roslab seed` writes): it boots through cloud-init, as a flashed Pi does")
    flash.add_argument("--card", type=Path, metavar="DEV",
                       help="boot one HOST from a card `roslab flash` or `roslab seed --image` wrote (the card's "
                            "device or an image file), through cloud-init with the seed on the card's "
                            "system-boot, which must be this HOST's. A card of the sandbox's own image "
                            "(`sandbox card-image`) is the host's disk: its writable partition is the root; "
                            "the system on a Pi's card (arm64) cannot run here, so the host boots the "
                            "sandbox's image with the card's seed")
    reset.add_argument("--apt-lock-seconds", type=float, default=None, metavar="S",
                       help="on a boot from a seed, how long the stand-in for first-boot "
                            f"unattended-upgrades holds the dpkg lock (default {seeding.FIRST_BOOT_APT_LOCK_SECONDS}; "
                            "0: not at all)")


def _register_saved_states(commands) -> None:
    """`sandbox save NAME` and `sandbox restore NAME`."""
    save = commands.add_parser(
        "save", help="save every host's disk (and roslab's run records) under NAME, to restore later",
        description="Save the classroom as it is now: each host's disk (stopped for the copy, booted again) "
                    "and roslab's run records beside the sandbox roster, under NAME in the sandbox's folder "
                    "(`down` removes it). A name is saved once.")
    save.add_argument("name", metavar="NAME")
    restore = commands.add_parser(
        "restore", help="bring every host back to the state saved under NAME (seconds, not a converge)",
        description="Give every host the disk saved under NAME (what changed since is lost) and boot it; "
                    "same hosts, addresses and keys. The saved state stays as it is for the next restore.")
    restore.add_argument("name", metavar="NAME")


def print_status(report: dict) -> None:
    print(f"sandbox {report['name']}: subnet {report['subnet']}, upstream {report['upstream']}")
    print(f"roster: {report['roster']}")
    print(f"deploy it: ROSLAB_SANDBOX={report['name']} pyinfra -y inventories/sandbox.py deploy.py   (in roslab's checkout)")
    print(f"       or: ROSLAB_ROSTER={report['roster']} pyinfra -y inventory.py deploy.py   (in a `roslab init` folder)")
    # roslab verify/status in a classroom folder would read its classroom.yaml: its real addresses
    print(f"check it: roslab verify {report['roster']}   (and roslab status, roslab check: the same roster)")
    for distro, what in sorted(report.get("ros", {}).items()):
        print(f"ROS 2 {distro}: {what}")
    for host in report["hosts"]:
        state = "ssh ok" if host["ssh"] else ("booting" if host["running"] else "STOPPED")
        kind = "Desktop" if host["flavour"] == "desktop" else "Server"
        print(f"  {host['name']:<16} {host['address']:<15} Ubuntu {host['release']} {kind} (emulated)  {state}")


def board_line(values) -> str:
    """What the team's board is and where it talks, in one line."""
    return (f"{values.team}: board {values.node_name} (domain {values.domain_id}) publishes /esp32/potentiometer "
            f"(std_msgs/msg/Int32) through the micro-ROS agent on {values.agent_host} at "
            f"{values.agent_address}:{values.agent_port}/udp")


def reset_hosts(args: argparse.Namespace) -> float:
    """`sandbox reset`: with --card, the seed read off the card (checked to be the one HOST's)."""
    if args.card is None:
        return lifecycle.reset(args.hosts, unseeded=args.unseeded, seed=args.seed,
                               apt_lock_seconds=args.apt_lock_seconds)
    if len(args.hosts) != 1:
        raise SandboxError("reset --card: a card is one host's: name exactly one HOST")
    with tempfile.TemporaryDirectory(prefix="roslab-card-seed-") as scratch:
        seed = seeding.seed_from_card(args.card, args.hosts[0], Path(scratch) / args.hosts[0])
        own = card.bootable_here(args.card)
        return lifecycle.reset(args.hosts, seed=seed, apt_lock_seconds=args.apt_lock_seconds,
                               card=args.card if own else None)


def run_board(args: argparse.Namespace) -> int:
    """`roslab sandbox board TEAM start|stop|status`: the team's emulated board, by its robot profile
    (esp32_microros: the ESP32 stand-in; osr: the stand-in RoboClaws in the rover)."""
    from roslab.robot_tools.esp32_firmware import board_values
    from roslab.reach import RosterProblem, load_classroom

    from . import rover_board
    from .instance import Instance

    instance = Instance.from_env()
    roster = args.roster or instance.roster_path
    try:
        classroom = load_classroom(str(roster), "sandbox board")
    except RosterProblem as problem:
        raise SandboxError(str(problem)) from None
    values = board_values(classroom, args.team)
    if values is not None:
        return esp32_board_action(args, values, instance, roster)
    rover = rover_board.robot_host(classroom, args.team)
    if rover is not None:
        return rover_board_action(args, instance, rover.name)
    teams = sorted({host.team for host in classroom.hosts
                    if board_values(classroom, host.team) or rover_board.robot_host(classroom, host.team)})
    raise SandboxError(f"{roster}: team {args.team!r} has no board the sandbox emulates (an ESP32 of robot_profile "
                       f"esp32_microros, the RoboClaws of robot_profile osr); teams with one: "
                       f"{', '.join(teams) or 'none'}")


def esp32_board_action(args: argparse.Namespace, values, instance, roster: Path) -> int:
    """start/stop/status of an esp32_microros team's ESP32 stand-in (on this machine)."""
    from . import esp32_board
    from .real_sources import Bundles

    if values.transport != "udp":
        raise SandboxError(f"{roster}: team {args.team!r} has esp32_transport {values.transport}: the sandbox "
                           "emulates a board on WiFi only (no USB link reaches a sandbox host); set it to udp")
    if args.action == "stop":
        stopped = esp32_board.stop(instance.state_dir, args.team)
        print(f"{args.team}: board {values.node_name} {'stopped' if stopped else 'was not running'}")
    elif args.action == "status":
        print(f"{board_line(values)}: {esp32_board.state(instance.state_dir, args.team)}")
    else:
        publishing = esp32_board.start(esp32_board.binary(Bundles.from_env()), values, instance.state_dir)
        log_file = esp32_board.board_files(instance.state_dir, args.team)[1]
        print(f"{board_line(values)}: " + ("publishing" if publishing else
              f"started, still waiting for the agent (is micro_ros_agent running there?); log: {log_file}"))
    return 0


def rover_board_action(args: argparse.Namespace, instance, host_name: str) -> int:
    """start/stop/status of an osr team's stand-in RoboClaws (inside its robot host)."""
    from . import rover_board

    line = rover_board.describe(args.team, host_name)
    if args.action == "stop":
        stopped = rover_board.stop(instance, host_name)
        print(f"{line}: {'stopped' if stopped else 'was not running'}")
    elif args.action == "status":
        print(f"{line}: {rover_board.state(instance, host_name)}")
    else:
        pid = rover_board.start(instance, host_name)
        print(f"{line}: answering (pid {pid} in {host_name}); the rover's service (osr_startup, when "
              "osr_calibrated) respawns roboclaw_wrapper, which now finds them")
    return 0


def run_create3(args: argparse.Namespace) -> int:
    """`roslab sandbox create3 HOST start|stop|status`."""
    from . import create3_link

    classroom = lifecycle.load()
    host = classroom.host(args.host)
    if args.action == "start":
        pid = create3_link.plug(classroom.instance, host, args.firmware or create3_link.DEFAULT_FIRMWARE)
        print(f"{host.name}: a stand-in Create 3 is plugged in (usb0; it answers at 192.168.186.2, pid {pid}): "
              "roslab's next run gives usb0 its address and configures it")
    elif args.action == "stop":
        unplugged = create3_link.unplug(classroom.instance, host)
        print(f"{host.name}: Create 3 {'unplugged' if unplugged else 'was not plugged in'}")
    else:
        print(f"{host.name}: Create 3 {create3_link.state(classroom.instance, host)}")
    return 0


def run_publish(args: argparse.Namespace) -> int:
    served = lifecycle.load().instance.state_dir / "upstream"
    if args.revert:
        if args.package:
            raise SandboxError("publish --revert takes no PACKAGE: it serves every archive as `up` did")
        reverted = publish.revert(served)
        print("served as `up` served them: " + (", ".join(reverted) if reverted else "nothing was published"))
        return 0
    if not args.package:
        raise SandboxError("publish --bump needs the PACKAGE to publish under a higher version")
    for done in publish.bump(served, args.package):
        print(f"published {done.line()}")
    return 0


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def run(args: argparse.Namespace) -> int:
    if os.geteuid() != 0:  # status too: it looks into the hosts' namespaces and the sandbox's state
        print(f"roslab sandbox {args.sandbox_command}: needs root (the sandbox is network namespaces, "
              "mounts and containers); run it with sudo", file=sys.stderr)
        return 1
    if not logging.getLogger().handlers:  # `roslab sandbox ...`: say what it is doing, on stderr
        logging.basicConfig(level=logging.INFO, format="roslab sandbox: %(message)s")
    # A SIGTERM (a CI timeout, `kill`) unwinds like Ctrl-C, so a half-done `up`
    # takes down what it started.
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        if args.sandbox_command == "up":
            lifecycle.up(args.hosts, desktop=args.desktop, class_roster=args.roster)
            print_status(lifecycle.status())
        elif args.sandbox_command == "status":
            print_status(lifecycle.status())
        elif args.sandbox_command == "down":
            lifecycle.down()
        elif args.sandbox_command == "reset":
            seconds = reset_hosts(args)
            on_card = args.card and lifecycle.boots_from_card(args.hosts[0])
            how = ("booted from the card itself (its writable the root), its seed read by cloud-init" if on_card else
                   "booted from the card's seed with cloud-init (the card's own system cannot run here)"
                   if args.card else
                   "booted from the seed with cloud-init" if args.seed else
                   "new random SSH host key, unknown to roslab" if args.unseeded else "fresh image")
            print(f"{', '.join(args.hosts)}: {how}, ssh ready after {seconds:.1f} s")
        elif args.sandbox_command == "card-image":
            written = card_image.write_image(args.out, args.release, args.board)
            print(f"{written}: Ubuntu {args.release} for a {args.board}, the sandbox's stand-in "
                  f"({written.stat().st_size / 1e6:,.0f} MB)")
        elif args.sandbox_command == "save":
            print(f"saved as {args.name!r} in {lifecycle.save(args.name):.1f} s")
        elif args.sandbox_command == "restore":
            print(f"restored {args.name!r}, ssh ready after {lifecycle.restore(args.name):.1f} s")
        elif args.sandbox_command == "reboot":
            print(f"{args.host}: rebooted, ssh ready after {lifecycle.reboot(args.host):.1f} s")
        elif args.sandbox_command == "ssh":
            lifecycle.ssh(args.host, args.cmd)
        elif args.sandbox_command == "board":
            return run_board(args)
        elif args.sandbox_command == "create3":
            return run_create3(args)
        elif args.sandbox_command == "publish":
            return run_publish(args)
    except SandboxError as exc:
        print(f"roslab sandbox: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"roslab sandbox: {args.sandbox_command} interrupted", file=sys.stderr)
        return 130
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roslab")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return args.run(args)
