"""`roslab seed`: check the whole roster and every seed, then write them and record the keys."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from roslab.ssh import identity
from roslab.network.state import last_known_addresses
from roslab.reach import (
    RosterProblem, add_roster_argument, limited_hosts, load_classroom,
)
from roslab.roster import display_path
from roslab.roster.inventory import known_addresses
from roslab.secrets import plain_text
from roslab.seed import targets, tools
from roslab.seed.documents import SeedError, authorized_keys, check_console_password, host_seed, network_config


def _secrets_of(host, roster_path) -> list[str]:
    """What a checker's message must never show: the host's private key (also as a quoted
    string would show it) and its WiFi password."""
    private = identity.host_keys(roster_path, host.name).private_text()
    found = [private, private.replace("\n", "\\n"),
             *(line for line in private.splitlines() if not line.startswith("-----"))]
    for password in (host.settings.wifi_password, host.settings.console_password):
        if password is not None:
            found.append(plain_text(password))
    return found


def console_password_problem(host) -> None:
    if host.settings.console_password_secret:
        check_console_password(host)


def grouped(problems: dict, hosts: list, path) -> list[str]:
    """One line per problem: the hosts that share it named together (all of them: "every host")."""
    lines = []
    for (field, message), names in problems.items():
        if len(names) == len(hosts) and len(hosts) > 1:
            who = f"every host ({len(names)})"
        elif len(names) == 1:
            who = f"host {names[0]!r}"
        else:
            who = f"hosts {', '.join(map(repr, names))}"
        lines.append(f"{display_path(path)}: {who}" + (f", field {field!r}" if field else "") + f": {message}")
    return lines


class _Stop(Exception):
    """`roslab seed` ends here: the lines to print on stderr and the exit status."""

    def __init__(self, status: int, *lines: str):
        super().__init__("\n".join(lines))
        self.status = status


def run_seed(args: argparse.Namespace) -> int:
    try:
        classroom, hosts = _selected_hosts(args)
        path = classroom.path
        _refuse_what_the_roster_cannot_say(hosts, path)
        seeds = _checked_seeds(hosts, path)
        recorded_in = _write_and_record(args, hosts, seeds, path)
    except _Stop as stop:
        print(stop, file=sys.stderr)
        return stop.status
    if recorded_in:
        print(f"The keys are recorded in {', '.join(sorted(recorded_in))}; "
              "pyinfra connects to these Pis with strict host key checking.")
    return 0


def _selected(args: argparse.Namespace, command: str) -> tuple:
    """The roster and the hosts `--limit` selects, in roster order."""
    try:
        classroom = load_classroom(args.roster, command)
    except RosterProblem as error:
        raise _Stop(1, str(error)) from None
    hosts, problem = limited_hosts(classroom, args.limit, f"roslab {command}")
    if problem:
        raise _Stop(2, problem)
    return classroom, hosts


def _selected_hosts(args: argparse.Namespace) -> tuple:
    """The roster and the hosts `--limit` selects; one host for a card or an image."""
    classroom, hosts = _selected(args, "seed")
    if (args.boot_partition or args.image) and (not args.limit or len(hosts) != 1):
        # A card is one Pi's identity: name it, so no card gets another Pi's key by accident.
        raise _Stop(2, "roslab seed: --boot-partition and --image take the seed of one host: give --limit HOST "
                       f"(one host; it selects {len(hosts)})")
    try:
        if args.boot_partition:
            targets.check_boot_partition(Path(args.boot_partition))
    except targets.TargetError as error:
        raise _Stop(1, f"roslab seed: {error}; nothing was written") from None
    return classroom, hosts


def _refuse_what_the_roster_cannot_say(hosts: list, path: Path) -> None:
    """Every host checked first (keys, network, console password), before any key or file; a
    WiFi host without its regulatory domain is a warning."""
    shared: dict[tuple, list[str]] = {}
    for host in hosts:
        for check in (authorized_keys, network_config, console_password_problem):
            try:
                check(host)
            except SeedError as error:
                names = shared.setdefault((error.field, error.message), [])
                if host.name not in names:
                    names.append(host.name)
    if shared:
        raise _Stop(1, *grouped(shared, hosts, path), "roslab seed: nothing was written")
    without_domain = [host.name for host in hosts
                      if host.settings.network_kind == "wifi" and not host.settings.wifi_regulatory_domain]
    if without_domain:
        print(f"warning: {display_path(path)}: {', '.join(without_domain)} on WiFi without "
              "wifi_regulatory_domain: their WiFi keeps to the channels and power allowed everywhere; "
              "set it to your country's code (like DE)", file=sys.stderr)


def _checked_seeds(hosts: list, path: Path) -> dict:
    """Each host's seed files, checked by cloud-init's and netplan's own schema before writing."""
    seeds = {host.name: host_seed(host, path) for host in hosts}
    secrets = [secret for host in hosts for secret in _secrets_of(host, path)]
    problems = []
    try:
        user_problems = tools.check_user_data(
            {name: files["user-data"].content.decode() for name, files in seeds.items()}, secrets)
        for name, files in seeds.items():
            for problem in user_problems.get(name, []):
                problems.append(f"{name}: user-data: cloud-init: {problem}")
            for problem in tools.check_network_config("network-config", files["network-config"].content.decode(),
                                                      secrets):
                problems.append(f"{name}: network-config: netplan: {problem}")
    except tools.SeedToolError as error:
        raise _Stop(1, f"roslab seed: {error}; nothing was written") from None
    if problems:
        raise _Stop(1, *problems, "roslab seed: a seed failed its check (a roslab bug: please report it); "
                                  "nothing was written")
    return seeds


def _write_and_record(args: argparse.Namespace, hosts: list, seeds: dict, path: Path) -> set[str]:
    """Write each host's seed where the command says, record its host key; the known_hosts files
    recorded in."""
    try:
        moved = last_known_addresses(path)
    except (OSError, ValueError) as error:
        raise _Stop(1, f"roslab seed: cannot read where moved hosts are: "
                       f"{getattr(error, 'strerror', None) or error}; nothing was written") from None
    recorded_in: set[str] = set()
    for host in hosts:
        where, changed = _write_seed(args, host.name, seeds[host.name])
        public = identity.host_keys(path, host.name).public_line()
        known_hosts, recorded = _record_key(host, path, moved)
        if known_hosts is not None:
            recorded_in.add(known_hosts)
        key = f"host key {identity.fingerprint(public)}"
        if changed:
            print(f"{host.name}: wrote {', '.join(changed)} in {where} ({key})")
        else:
            print(f"{host.name}: unchanged in {where} ({key})")
        if recorded is not None and recorded.public_line() != " ".join(public.split()[:2]):
            print(f"{host.name}: its recorded host key is now the seeded one: until it boots from this "
                  "seed, pyinfra refuses it")
    return recorded_in


def _record_key(host, path: Path, moved: dict | None = None) -> tuple[str | None, identity.KnownHost | None]:
    """Record the host's seeded key in the known_hosts file the run checks it against
    (ssh_known_hosts_file, or the classroom's own): (that file's name, the key recorded before),
    (None, None) where the roster checks no keys (/dev/null)."""
    public = identity.host_keys(path, host.name).public_line()
    known_hosts = identity.known_hosts_of(path, host.settings.ssh_known_hosts_file)
    if str(known_hosts) == os.devnull:
        return None, None
    if moved is None:
        moved = last_known_addresses(path)
    try:
        recorded = identity.known_key(path, host.name, known_hosts=known_hosts)
        identity.trust(path, host.name, known_addresses(host, moved.get(host.name)), public,
                       port=host.settings.ssh_port or 22, known_hosts=known_hosts)
    except (OSError, identity.IdentityError) as error:
        raise _Stop(1, f"roslab: {host.name}: its seed is written, but its key could not be "
                       f"recorded in {display_path(known_hosts)}: "
                       f"{getattr(error, 'strerror', None) or error}") from None
    return display_path(known_hosts), recorded


def _write_seed(args: argparse.Namespace, name: str, files) -> tuple[str, list[str]]:
    """(where the seed went, the files changed): an image, a boot partition or a folder per host."""
    try:
        if args.image:
            return display_path(args.image), targets.write_image(Path(args.image), files)
        if args.boot_partition:
            return display_path(args.boot_partition), targets.write_boot_partition(Path(args.boot_partition), files)
        return display_path(Path(args.out) / name), targets.write_directory(Path(args.out) / name, files)
    except (targets.TargetError, OSError) as error:
        raise _Stop(1, f"roslab seed: {name}: {error}") from None


def register(commands) -> None:
    seed = commands.add_parser(
        "seed",
        help="write first-boot seeds (cloud-init NoCloud) that boot fresh Pis into the roster",
        description="Per Pi, a NoCloud user-data, network-config and meta-data from the roster: "
        "hostname, the lab user with the teacher's keys and sudo, no password login, the Pi's own "
        "SSH host key (generated once, kept beside the roster), its network, locale, time zone and "
        "time sync. Checked with cloud-init's and netplan's own parsers before anything is written.",
    )
    add_roster_argument(seed, what=" (--boot-partition, --image: one host)")
    where = seed.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", metavar="DIR", help="write DIR/<host>/{user-data,network-config,meta-data}")
    where.add_argument("--boot-partition", metavar="PATH",
                       help="a mounted Ubuntu Pi system-boot partition (with --limit HOST)")
    where.add_argument("--image", metavar="FILE",
                       help="a raw Ubuntu Pi image: its boot partition is written with mtools, "
                       "not mounted (with --limit HOST)")
    seed.set_defaults(run=run_seed)
