"""`roslab trust` and `roslab forget`: the classroom's known_hosts for Pis flashed without a seed.

    roslab trust [ROSTER] [--host NAME ...]   record the key each Pi shows now (prints fingerprints)
    roslab forget HOST [--roster ROSTER]      remove a Pi's recorded key (re-flashed without a seed)

`trust` asks each host for its host key over its SSH port (as ssh-keyscan does; no login),
preferring ed25519, and records it under every address the host is reached at. A host
whose recorded key differs is left alone and reported: a changed key is accepted only
after `roslab forget`, never silently.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
from pathlib import Path

import paramiko
import yaml

from roslab.ssh import identity
from roslab.network.state import last_known_addresses
from roslab.reach import add_limit_argument, select_roster_hosts
from roslab.roster import RosterError, default_roster_path, display_path, load_roster
from roslab.roster.inventory import known_addresses

PREFERRED_KEY_TYPES = ["ssh-ed25519", "ecdsa-sha2-nistp256", "rsa-sha2-512", "rsa-sha2-256", "ssh-rsa"]
SCAN_TIMEOUT = 10


def scan_host_key(address: str, port: int, timeout: float = SCAN_TIMEOUT) -> str:
    """The host key `address:port` shows, as an `ssh-ed25519 AAAA...` line (no login)."""
    sock = socket.create_connection((address, port), timeout=timeout)
    transport = paramiko.Transport(sock)
    try:
        options = transport.get_security_options()
        options.key_types = [kind for kind in PREFERRED_KEY_TYPES if kind in options.key_types]
        transport.start_client(timeout=timeout)
        key = transport.get_remote_server_key()
        return f"{key.get_name()} {key.get_base64()}"
    finally:
        transport.close()


def _load(path: Path):
    try:
        return load_roster(path)
    except RosterError as error:
        print(error, file=sys.stderr)
        return None


def addresses_to_try(host, moved_to: str | None) -> list[str]:
    """Where to ask a host for its key, in order: its last confirmed address, the roster's,
    and the static address the network deploy moves it to. A Pi the last run moved may be
    back on its roster address (re-flashed, its network reset), and the other way round."""
    return [address for address in dict.fromkeys([moved_to, *known_addresses(host, moved_to)]) if address]


def scan_first(addresses: list[str], port: int) -> tuple[str, str]:
    """(address, key line) of the first address that shows a host key; OSError naming each failure."""
    failures = []
    for address in addresses:
        try:
            return address, scan_host_key(address, port)
        except (OSError, paramiko.SSHException, EOFError) as error:
            failures.append(f"{address}: {error or type(error).__name__}")
    raise OSError("; ".join(failures))


def run_trust(args: argparse.Namespace) -> int:
    path = Path(args.roster) if args.roster else default_roster_path()
    classroom = _load(path)
    if classroom is None:
        return 1
    hosts, unknown = select_roster_hosts(classroom, args.limit)
    if unknown:
        print(f"roslab trust: --limit {', '.join(map(repr, unknown))} selects no host of {display_path(path)}",
              file=sys.stderr)
        return 2
    try:
        moved = last_known_addresses(path)
    except (OSError, ValueError, yaml.YAMLError) as error:
        print(f"roslab trust: cannot read where moved hosts are: {getattr(error, 'strerror', None) or error}",
              file=sys.stderr)
        return 1
    failed = 0
    for host in hosts:
        # The file the run checks this host against (the roster's ssh_known_hosts_file, or the
        # classroom's own): recording the key anywhere else would say "recorded" and fail the run.
        known_hosts_file = identity.known_hosts_of(path, host.data)
        known_hosts = display_path(known_hosts_file)
        if str(known_hosts_file) == os.devnull:
            print(f"{host.name}: its ssh_known_hosts_file is /dev/null, where no key can be recorded: "
                  "set it to a known_hosts file (or leave it unset for the classroom's own)", file=sys.stderr)
            failed += 1
            continue
        port = host.data.get("ssh_port") or 22
        try:
            address, public = scan_first(addresses_to_try(host, moved.get(host.name)), port)
        except OSError as error:
            print(f"{host.name}: no host key: {error}", file=sys.stderr)
            failed += 1
            continue
        shown = f"{public.split()[0]} {identity.fingerprint(public)}"
        addresses = known_addresses(host, moved.get(host.name))
        names = identity.host_names(host.name, addresses, port)
        try:
            entries = identity.read_known_hosts(path, known_hosts_file)
        except (OSError, UnicodeDecodeError, identity.IdentityError) as error:
            print(f"{host.name}: cannot read {known_hosts}: {getattr(error, 'strerror', None) or error}",
                  file=sys.stderr)
            failed += 1
            continue
        if identity.other_keys(entries, names, public):
            print(f"{host.name} ({address}): shows {shown}, but another key is recorded for it in "
                  f"{known_hosts}; if the Pi was re-flashed without its seed, run "
                  f"`roslab forget {host.name} --roster {display_path(path)}` first", file=sys.stderr)
            failed += 1
            continue
        try:
            changed = identity.trust(path, host.name, addresses, public, port=port,
                                     known_hosts=known_hosts_file)
        except (OSError, identity.IdentityError) as error:
            print(f"{host.name}: cannot record its key in {known_hosts}: "
                  f"{getattr(error, 'strerror', None) or error}", file=sys.stderr)
            failed += 1
            continue
        print(f"{host.name} ({address}): {shown} {'recorded' if changed else 'already recorded'} "
              f"in {known_hosts}")
    if hosts and not failed:
        print("Compare these fingerprints with the Pis' own (`ssh-keygen -lf "
              "/etc/ssh/ssh_host_ed25519_key.pub` on each) if anyone else could be on this network.")
    return 1 if failed else 0


def known_hosts_files(path: Path, hosts_or_addresses: list[str]) -> list[Path]:
    """The known_hosts files `roslab forget` edits: those the run uses for the named hosts
    (every file the roster uses for an address or a name it does not know), never /dev/null.
    An unusable roster leaves the classroom's own file."""
    try:
        classroom = load_roster(path)
    except RosterError as error:
        print(f"roslab forget: the roster has errors, so only the classroom's own known_hosts is "
              f"edited:\n{error}", file=sys.stderr)
        return [identity.known_hosts_path(path)]
    by_name = {host.name: host for host in classroom.hosts}
    named = [by_name[name] for name in hosts_or_addresses if name in by_name]
    every = len(named) < len(hosts_or_addresses)
    files = [identity.known_hosts_of(path, host.data) for host in (classroom.hosts if every else named)]
    return [file for file in dict.fromkeys(files) if str(file) != os.devnull]


def run_forget(args: argparse.Namespace) -> int:
    path = Path(args.roster) if args.roster else default_roster_path()
    files = known_hosts_files(path, args.hosts)
    removed_any = False
    for known_hosts_file in files:
        known_hosts = display_path(known_hosts_file)
        try:
            removed = identity.forget(path, *args.hosts, known_hosts=known_hosts_file)
        except (OSError, UnicodeDecodeError, identity.IdentityError) as error:
            print(f"roslab forget: cannot edit {known_hosts}: {getattr(error, 'strerror', None) or error}",
                  file=sys.stderr)
            return 1
        if removed:
            removed_any = True
            print(f"removed from {known_hosts}: {', '.join(removed)}")
    if not removed_any:
        shown = ", ".join(display_path(file) for file in files) or "no known_hosts file"
        print(f"roslab forget: {shown} has no key for {', '.join(args.hosts)}")
        return 0
    print(f"next: `roslab trust {display_path(path)} --host {args.hosts[0]}` records the key it shows now")
    return 0


def register(commands) -> None:
    trust = commands.add_parser(
        "trust",
        help="record the SSH host key of Pis flashed without a seed",
        description="Ask each Pi for its SSH host key (no login), print its fingerprint and record it "
        "in the classroom's known_hosts beside the roster, under every address it is reached at. "
        "A Pi whose recorded key differs is refused: run `roslab forget HOST` first.",
    )
    trust.add_argument("roster", nargs="?", metavar="ROSTER", help="roster file (default: as for roslab check)")
    add_limit_argument(trust)
    trust.set_defaults(run=run_trust)

    forget = commands.add_parser(
        "forget",
        help="remove a Pi's recorded SSH host key (e.g. re-flashed without a seed)",
        description="Remove the hosts' (or addresses') keys from the classroom's known_hosts.",
    )
    forget.add_argument("hosts", nargs="+", metavar="HOST", help="host name or address")
    forget.add_argument("--roster", metavar="ROSTER", help="roster file (default: as for roslab check)")
    forget.set_defaults(run=run_forget)
