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
import socket
import sys
from pathlib import Path

import paramiko

from roslab import identity
from roslab.network.state import last_known_addresses
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


def run_trust(args: argparse.Namespace) -> int:
    path = Path(args.roster) if args.roster else default_roster_path()
    classroom = _load(path)
    if classroom is None:
        return 1
    hosts = classroom.hosts
    if args.host:
        by_name = {host.name: host for host in hosts}
        unknown = [name for name in args.host if name not in by_name]
        if unknown:
            print(f"roslab trust: no host {', '.join(map(repr, unknown))} in {display_path(path)}",
                  file=sys.stderr)
            return 2
        hosts = [by_name[name] for name in dict.fromkeys(args.host)]
    moved = last_known_addresses(path)
    known_hosts = display_path(identity.known_hosts_path(path))
    failed = 0
    for host in hosts:
        address = moved.get(host.name) or host.address
        port = host.data.get("ssh_port") or 22
        try:
            public = scan_host_key(address, port)
        except (OSError, paramiko.SSHException, EOFError) as error:
            print(f"{host.name} ({address}): no host key: {error or type(error).__name__}", file=sys.stderr)
            failed += 1
            continue
        shown = f"{public.split()[0]} {identity.fingerprint(public)}"
        recorded = identity.known_key(path, host.name)
        if recorded is not None and recorded.public_line() != " ".join(public.split()[:2]):
            print(f"{host.name} ({address}): shows {shown}, but another key is recorded for it in "
                  f"{known_hosts}; if the Pi was re-flashed without its seed, run "
                  f"`roslab forget {host.name} --roster {display_path(path)}` first", file=sys.stderr)
            failed += 1
            continue
        changed = identity.trust(path, host.name, known_addresses(host, moved.get(host.name)), public,
                                 port=port)
        print(f"{host.name} ({address}): {shown} {'recorded' if changed else 'already recorded'}")
    if hosts and not failed:
        print("Compare these fingerprints with the Pis' own (`ssh-keygen -lf "
              "/etc/ssh/ssh_host_ed25519_key.pub` on each) if anyone else could be on this network.")
    return 1 if failed else 0


def run_forget(args: argparse.Namespace) -> int:
    path = Path(args.roster) if args.roster else default_roster_path()
    removed = identity.forget(path, *args.hosts)
    known_hosts = display_path(identity.known_hosts_path(path))
    if not removed:
        print(f"roslab forget: {known_hosts} has no key for {', '.join(args.hosts)}")
        return 0
    print(f"removed from {known_hosts}: {', '.join(removed)}")
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
    trust.add_argument("--host", action="append", metavar="NAME", help="only this host (repeatable)")
    trust.set_defaults(run=run_trust)

    forget = commands.add_parser(
        "forget",
        help="remove a Pi's recorded SSH host key (e.g. re-flashed without a seed)",
        description="Remove the hosts' (or addresses') keys from the classroom's known_hosts.",
    )
    forget.add_argument("hosts", nargs="+", metavar="HOST", help="host name or address")
    forget.add_argument("--roster", metavar="ROSTER", help="roster file (default: as for roslab check)")
    forget.set_defaults(run=run_forget)
