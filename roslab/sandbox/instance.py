"""A sandbox instance: its name, subnet, state directory and the classroom it holds.

Several instances coexist on one machine (each engineer's tests run their own);
everything an instance creates carries a short id derived from its name, so
`down` finds its leftovers even when the state directory is gone.
"""

from __future__ import annotations

import hashlib
import ipaddress
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

from .emulation import HostIdentity
from .system import SandboxError

DEFAULT_NAME = "roslab"
DEFAULT_SUBNET = "10.213.0.0/24"
STATE_ROOT = Path("/run/roslab/sandbox")
UPSTREAM_PORT = 8080
FIRST_HOST_OCTET = 11  # hosts are .11, .12, ...; .1 is the bridge (the "upstream")
MAX_HOSTS = 200

# Team n's release: odd teams on 24.04, even teams on 22.04, unless $ROSLAB_SANDBOX_RELEASES
# lists the teams' releases in turn (e.g. "24.04,22.04,26.04"; the list repeats).
RELEASES_BY_TEAM = ("24.04", "22.04")
RELEASES_ENV = "ROSLAB_SANDBOX_RELEASES"
# The board of a sandbox host whose roster says none: robots are Raspberry Pi 4s (the boot
# partition stand-in, pi_boot.py), mains are PCs.
BOARD_BY_ROLE = {"robot": "pi4", "main": "pc"}


def releases_by_team() -> tuple[str, ...]:
    """The Ubuntu release of team 1, 2, ... in turn ($ROSLAB_SANDBOX_RELEASES, else RELEASES_BY_TEAM)."""
    from roslab.ros.distro import BY_RELEASE

    text = os.environ.get(RELEASES_ENV, "").strip()
    if not text:
        return RELEASES_BY_TEAM
    releases = tuple(part.strip() for part in text.split(","))
    unknown = [release for release in releases if release not in BY_RELEASE]
    if unknown or not releases:
        raise SandboxError(f"{RELEASES_ENV}={text!r}: {', '.join(unknown) or 'empty'} is not a release the "
                           f"sandbox emulates ({', '.join(BY_RELEASE)})")
    return releases

_NAME_RE = re.compile(r"^[a-z][a-z0-9-]{0,30}$")


@dataclass(frozen=True)
class SandboxHost:
    """One host of the sandbox classroom."""

    name: str  # "team1-main"
    team: str  # "team1"
    role: str  # "main" or "robot"
    release: str  # "24.04"
    index: int  # 0-based position in the classroom
    address: str
    flavour: str = "server"  # "desktop": NetworkManager runs the network instead of networkd
    board: str | None = None  # the roster's `board`: a Pi's boots with a Pi's boot partition (pi_boot.py)

    def identity(self, prefixlen: int) -> HostIdentity:
        return HostIdentity(hostname=self.name, release=self.release, address=self.address,
                            prefixlen=prefixlen, flavour=self.flavour)


@dataclass(frozen=True)
class Instance:
    name: str
    subnet: ipaddress.IPv4Network

    @classmethod
    def from_env(cls, name: str | None = None) -> "Instance":
        """The instance named by `name`, else $ROSLAB_SANDBOX, else "roslab"."""
        name = name or os.environ.get("ROSLAB_SANDBOX") or DEFAULT_NAME
        if not _NAME_RE.match(name):
            raise SandboxError(
                f"sandbox name {name!r} is invalid: use 1-31 lowercase letters, digits and '-', starting with a letter"
            )
        subnet_text = os.environ.get("ROSLAB_SANDBOX_SUBNET") or default_subnet(name)
        try:
            subnet = ipaddress.IPv4Network(subnet_text)
        except ValueError as exc:
            raise SandboxError(f"ROSLAB_SANDBOX_SUBNET={subnet_text!r} is not an IPv4 network: {exc}") from None
        if subnet.prefixlen > 24 or not subnet.is_private:
            raise SandboxError(f"sandbox subnet {subnet} must be a private network of /24 or larger")
        return cls(name, subnet)

    # -- names of what the instance creates ---------------------------------------
    @property
    def short_id(self) -> str:
        """6 hex digits naming this instance's interfaces, netns and cgroups (names <= 15 chars)."""
        return hashlib.sha1(self.name.encode()).hexdigest()[:6]

    @property
    def bridge(self) -> str:
        return f"rlbr{self.short_id}"

    def veth(self, host: SandboxHost) -> str:
        return f"rlv{self.short_id}{host.index}"

    def netns(self, host: SandboxHost) -> str:
        return f"rl{self.short_id}-{host.name}"

    @property
    def netns_prefix(self) -> str:
        return f"rl{self.short_id}-"

    def machine_name(self, host: SandboxHost) -> str:
        return f"{self.name}-{host.name}"

    @property
    def bridge_address(self) -> str:
        return str(self.subnet.network_address + 1)

    @property
    def upstream_url(self) -> str:
        return f"http://{self.bridge_address}:{UPSTREAM_PORT}"

    # -- files ---------------------------------------------------------------------
    @property
    def state_dir(self) -> Path:
        return STATE_ROOT / self.name

    @property
    def roster_path(self) -> Path:
        return self.state_dir / "roster.yaml"

    @property
    def key_path(self) -> Path:
        return self.state_dir / "id_ed25519"

    def host_dir(self, host: SandboxHost) -> Path:
        return self.state_dir / "hosts" / host.name

    # -- the classroom ---------------------------------------------------------------
    def plan_members(self, members: list[dict], desktop: Iterable[str] = ()) -> list[SandboxHost]:
        """The hosts a class roster names (`class_roster.members`: name, team, role, release), in
        its order, on this instance's addresses."""
        if not 1 <= len(members) <= min(MAX_HOSTS, self.subnet.num_addresses - FIRST_HOST_OCTET - 1):
            raise SandboxError(f"the roster has {len(members)} hosts: a sandbox holds 1 to {MAX_HOSTS}")
        desktop = set(desktop)
        unknown = desktop - {member["name"] for member in members}
        if unknown:
            raise SandboxError(f"--desktop {', '.join(sorted(unknown))}: no such host in the roster")
        # A member keeps the index (and so the address) it was given when it joined: a host
        # added or removed by `up --roster` again moves no other host.
        indexes = [member.get("index", index) for index, member in enumerate(members)]
        if max(indexes) >= min(MAX_HOSTS, self.subnet.num_addresses - FIRST_HOST_OCTET - 1):
            raise SandboxError(f"the roster's hosts need more addresses than {self.subnet} has for a sandbox")
        return [SandboxHost(name=member["name"], team=member["team"], role=member["role"],
                            release=member["release"], index=index,
                            address=str(self.subnet.network_address + FIRST_HOST_OCTET + index),
                            flavour="desktop" if member["name"] in desktop else "server",
                            board=member.get("board") or BOARD_BY_ROLE.get(member["role"]))
                for index, member in zip(indexes, members)]

    def plan_hosts(self, count: int, desktop: Iterable[str] = (),
                   releases: Iterable[str] | None = None) -> list[SandboxHost]:
        """`count` hosts in teams of two (main, robot), teams on the releases of `releases_by_team()`.

        Hosts named in `desktop` are Ubuntu Desktop-like (NetworkManager), the rest Server-like.
        """
        if not 1 <= count <= min(MAX_HOSTS, self.subnet.num_addresses - FIRST_HOST_OCTET - 1):
            raise SandboxError(f"--hosts {count}: a sandbox holds 1 to {MAX_HOSTS} hosts")
        hosts = []
        releases = tuple(releases or ()) or releases_by_team()
        for index in range(count):
            team_number, member = divmod(index, 2)
            team = f"team{team_number + 1}"
            role = ("main", "robot")[member]
            hosts.append(SandboxHost(
                name=f"{team}-{role}", team=team, role=role,
                release=releases[team_number % len(releases)], index=index,
                address=str(self.subnet.network_address + FIRST_HOST_OCTET + index), board=BOARD_BY_ROLE[role],
            ))
        desktop = set(desktop)
        unknown = desktop - {host.name for host in hosts}
        if unknown:
            raise SandboxError(f"--desktop {', '.join(sorted(unknown))}: no such host among {hosts[0].name} .. "
                               f"{hosts[-1].name}")
        return [replace(host, flavour="desktop") if host.name in desktop else host for host in hosts]


def default_subnet(name: str) -> str:
    """10.213.0.0/24 for the default instance; a distinct 10.213.x.0/24 derived from any other name."""
    if name == DEFAULT_NAME:
        return DEFAULT_SUBNET
    third_octet = 1 + int(hashlib.sha1(name.encode()).hexdigest(), 16) % 254
    return f"10.213.{third_octet}.0/24"
