"""`roslab trust` and `roslab forget`: the classroom's known_hosts for Pis flashed without a seed.

    roslab trust [ROSTER] [--limit NAME ...]   record the key each Pi shows now (prints fingerprints)
    roslab forget [ROSTER] --limit NAME ...    remove a Pi's recorded key (re-flashed without a seed)

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
from roslab.reach import (
    RosterProblem, add_roster_argument, add_stale_host_form, limited_hosts, load_classroom, stale_host_form,
)
from roslab.roster import display_path
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


def limited_classroom(args: argparse.Namespace, command: str) -> tuple[Path, list, dict] | int:
    """(the roster's path, the hosts --limit selects, where the last run moved hosts), or the
    exit status after saying on stderr what is wrong (1: the roster or its state; 2: --limit)."""
    try:
        classroom = load_classroom(args.roster, command)
    except RosterProblem as error:
        print(error, file=sys.stderr)
        return 1
    hosts, problem = limited_hosts(classroom, args.limit, f"roslab {command}")
    if problem:
        print(problem, file=sys.stderr)
        return 2
    try:
        moved = last_known_addresses(classroom.path)
    except (OSError, ValueError, yaml.YAMLError) as error:
        print(f"roslab {command}: cannot read where moved hosts are: {getattr(error, 'strerror', None) or error}",
              file=sys.stderr)
        return 1
    return classroom.path, hosts, moved


def run_trust(args: argparse.Namespace) -> int:
    loaded = limited_classroom(args, "trust")
    if isinstance(loaded, int):
        return loaded
    path, hosts, moved = loaded
    failed = 0
    for host in hosts:
        # The file the run checks this host against (the roster's ssh_known_hosts_file, or the
        # classroom's own): recording the key anywhere else would say "recorded" and fail the run.
        known_hosts_file = identity.known_hosts_of(path, host.settings.ssh_known_hosts_file)
        known_hosts = display_path(known_hosts_file)
        if str(known_hosts_file) == os.devnull:
            print(f"{host.name}: its ssh_known_hosts_file is /dev/null, where no key can be recorded: "
                  "set it to a known_hosts file (or leave it unset for the classroom's own)", file=sys.stderr)
            failed += 1
            continue
        port = host.settings.ssh_port or 22
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
                  f"`roslab forget {display_path(path)} --limit {host.name}` first", file=sys.stderr)
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


def run_forget(args: argparse.Namespace) -> int:
    stale = stale_host_form(args, "forget")
    if stale or not args.limit:
        print(stale or "roslab forget: name the hosts whose keys to forget with --limit (a team, role, "
              "distro or host name): roslab forget [ROSTER] --limit HOST", file=sys.stderr)
        return 2
    loaded = limited_classroom(args, "forget")
    if isinstance(loaded, int):
        return loaded
    path, hosts, moved = loaded
    removed_any = False
    for host in hosts:
        # The file the run checks this host against; under the host's name and under every
        # address it is reached at, so no other line (the teacher's own) still vouches for it.
        known_hosts_file = identity.known_hosts_of(path, host.settings.ssh_known_hosts_file)
        known_hosts = display_path(known_hosts_file)
        if str(known_hosts_file) == os.devnull:
            print(f"{host.name}: its ssh_known_hosts_file is /dev/null: no key is recorded for it")
            continue
        names = identity.host_names(host.name, known_addresses(host, moved.get(host.name)),
                                    host.settings.ssh_port or 22)
        try:
            removed = identity.forget(path, *names, known_hosts=known_hosts_file)
        except (OSError, UnicodeDecodeError, identity.IdentityError) as error:
            print(f"roslab forget: cannot edit {known_hosts}: {getattr(error, 'strerror', None) or error}",
                  file=sys.stderr)
            return 1
        removed_any = removed_any or bool(removed)
        print(f"{host.name}: " + (f"removed from {known_hosts}: {', '.join(removed)}" if removed
                                  else f"no key recorded in {known_hosts}"))
    if removed_any:
        limits = " ".join(f"--limit {pattern}" for pattern in args.limit)
        print(f"next: `roslab trust {display_path(path)} {limits}` records the key each Pi shows now")
    return 0


def register(commands) -> None:
    trust = commands.add_parser(
        "trust",
        help="record the SSH host key of Pis flashed without a seed",
        description="Ask each Pi for its SSH host key (no login), print its fingerprint and record it "
        "in the classroom's known_hosts beside the roster, under every address it is reached at. "
        "A Pi whose recorded key differs is refused: run `roslab forget --limit HOST` first.",
    )
    add_roster_argument(trust)
    trust.set_defaults(run=run_trust)

    forget = commands.add_parser(
        "forget",
        help="remove a Pi's recorded SSH host key (e.g. re-flashed without a seed)",
        description="Remove the keys recorded for the hosts --limit selects (under their names and "
        "every address they are reached at) from the known_hosts the run checks them against.",
    )
    add_roster_argument(forget)
    add_stale_host_form(forget)
    forget.set_defaults(run=run_forget)
