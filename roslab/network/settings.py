"""Network settings: parsed, checked, and checked across the classroom.

Used twice, like the distro mapping: the roster loader runs `validate_roster`
before any host is touched (address inside its subnet, gateway inside it, no
address used twice, a WiFi password from the secrets file), and the network
deploy parses each host's typed settings (roslab.host_settings.HostSettings) again
with `network_settings` so a host's data can never reach a template unchecked.

Every value is hostile until checked here. What the network files cannot hold is
refused, naming the field: control characters and line breaks in the SSID, the
password or the interface name, an interface name that could pass for an option,
a nameserver with a scope suffix. What they can hold (an SSID with quotes, `#`,
`;`, `$(...)` or unicode) is accepted here and escaped for each file format by
roslab.network.render.
"""

from __future__ import annotations

import re
import unicodedata
from dataclasses import dataclass, field
from ipaddress import IPv4Address, IPv4Interface, ip_address
from collections.abc import Mapping
from typing import Any, Iterable

from roslab.host_settings import HostSettings
from roslab.network.apply import INTERFACE_NAME

KINDS = ("ethernet", "wifi")
METHODS = ("static", "dhcp")
BACKENDS = ("auto", "netplan", "networkmanager")
IPV6_MODES = ("auto", "disabled", "ignore")
DEFAULT_INTERFACES = {"ethernet": "eth0", "wifi": "wlan0"}

# WPA-PSK: a passphrase of 8 to 63 printable ASCII characters, or 64 hex digits.
# (fullmatch: with `match`, `$` would also accept a trailing newline.)
WPA_PASSPHRASE = re.compile(r"[\x20-\x7e]{8,63}", re.ASCII)
WPA_HEX_KEY = re.compile(r"[0-9A-Fa-f]{64}", re.ASCII)
SSID_MAX_BYTES = 32
# Unicode categories an SSID may not contain: control characters (C0, DEL, C1),
# surrogates (not UTF-8), and the line and paragraph separators (YAML line breaks).
REFUSED_CATEGORIES = {"Cc", "Cs", "Zl", "Zp"}


class NetworkSettingError(ValueError):
    """One bad network setting; `field` names the roster key."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


@dataclass(frozen=True)
class NetworkSettings:
    """One host's network configuration, checked."""

    kind: str
    method: str
    interface: str
    backend: str
    ipv6: str
    address: IPv4Interface | None = None
    gateway: IPv4Address | None = None
    nameservers: tuple[str, ...] = ()
    wifi_ssid: str | None = None
    # The secret itself (a HiddenValue-style object with .unmask()), never printed.
    wifi_password: Any = field(default=None, repr=False)
    confirm_timeout: int = 60
    disable_cloud_init: bool = True
    backups_keep: int = 5

    @property
    def password(self) -> str | None:
        """The WiFi password in clear, for the 0600 file only."""
        if self.wifi_password is None:
            return None
        return _unmask(self.wifi_password)


def _unmask(secret: Any) -> Any:
    unmask = getattr(secret, "unmask", None)
    return unmask() if callable(unmask) else secret


def _choice(key: str, value: object, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise NetworkSettingError(key, f"{value!r} is not one of {', '.join(choices)}")
    return value


def _address(settings: HostSettings) -> IPv4Interface:
    raw = str(settings.network_address).strip()
    prefix: object = settings.network_prefix
    if isinstance(prefix, bool) or not isinstance(prefix, (int, str, type(None))):
        raise NetworkSettingError("network_prefix", f"{prefix!r} is not a prefix length")
    try:
        if "/" in raw:
            address = IPv4Interface(raw)
            if prefix is not None and address.network.prefixlen != int(prefix):
                raise NetworkSettingError(
                    "network_address",
                    f"{raw} has prefix /{address.network.prefixlen} "
                    f"but network_prefix is {prefix}; give one of them",
                )
        else:
            if prefix is None:
                raise NetworkSettingError(
                    "network_address",
                    f"{raw!r} has no prefix length: write e.g. {raw}/24 or set network_prefix",
                )
            address = IPv4Interface(f"{raw}/{int(prefix)}")
    except NetworkSettingError:
        raise
    except ValueError as exc:
        field_name = "network_prefix" if "/" not in raw and prefix is not None else "network_address"
        raise NetworkSettingError(field_name, f"{raw!r} is not an IPv4 address with prefix ({exc})") from None

    network = address.network
    special = _not_a_unicast_address(address.ip)
    if special:
        raise NetworkSettingError("network_address", f"{address.ip} is {special}, not a host address")
    if network.prefixlen < 8:
        raise NetworkSettingError("network_address", f"prefix /{network.prefixlen} is too short")
    if network.prefixlen <= 30 and address.ip in (network.network_address, network.broadcast_address):
        which = "network" if address.ip == network.network_address else "broadcast"
        raise NetworkSettingError(
            "network_address", f"{address} is the {which} address of {network}, not a host address"
        )
    return address


def _not_a_unicast_address(ip) -> str | None:
    """What an address is when no host or router can have it (loopback, multicast...), or None."""
    for test, what in (("is_unspecified", "the unspecified address"), ("is_loopback", "a loopback address"),
                       ("is_multicast", "a multicast address"), ("is_reserved", "a reserved address"),
                       ("is_link_local", "a link-local address")):
        if getattr(ip, test, False):
            return what
    if ip == IPv4Address("255.255.255.255"):
        return "the limited broadcast address"
    return None


def _gateway(raw: object, address: IPv4Interface | None) -> IPv4Address | None:
    if raw in (None, ""):
        return None
    try:
        gateway = IPv4Address(str(raw).strip())
    except ValueError:
        raise NetworkSettingError("network_gateway", f"{raw!r} is not an IPv4 address") from None
    special = _not_a_unicast_address(gateway)
    if special:
        raise NetworkSettingError("network_gateway", f"{gateway} is {special}, not a router's address")
    if address is not None:
        network = address.network
        if network.prefixlen <= 30 and gateway in (network.network_address, network.broadcast_address):
            which = "network" if gateway == network.network_address else "broadcast"
            raise NetworkSettingError(
                "network_gateway",
                f"{gateway} is the {which} address of {network}, not a router's address",
            )
        if gateway not in address.network:
            raise NetworkSettingError(
                "network_gateway", f"{gateway} is outside the subnet {address.network} of {address}"
            )
        if gateway == address.ip:
            raise NetworkSettingError("network_gateway", f"{gateway} is the host's own address")
    return gateway


def _nameservers(raw: object) -> tuple[str, ...]:
    if raw is None:
        raw = []
    elif isinstance(raw, str):
        raw = [raw]
    elif not isinstance(raw, (list, tuple)):
        raise NetworkSettingError("network_nameservers", f"{raw!r} is not a list of IP addresses")
    servers = []
    for server in raw:
        text = str(server).strip() if isinstance(server, str) else None
        try:
            # No scope suffix (fe80::1%eth0): it could hold anything, and no file here needs it.
            if text is None or "%" in text:
                raise ValueError(text)
            server_ip = ip_address(text)
            if server_ip.is_unspecified or server_ip.is_multicast or (
                    server_ip.version == 4 and server_ip == IPv4Address("255.255.255.255")):
                raise ValueError(text)
            servers.append(str(server_ip))
        except ValueError:
            raise NetworkSettingError(
                "network_nameservers", f"{server!r} is not an IP address"
            ) from None
    return tuple(servers)


def _interface(interface: object, kind: str) -> str:
    if interface is None:
        return DEFAULT_INTERFACES[kind]
    if not isinstance(interface, str) or not INTERFACE_NAME.fullmatch(interface):
        raise NetworkSettingError(
            "network_interface",
            f"{interface!r} is not an interface name (1 to 15 letters, digits, '_', '.' "
            "or '-', not starting with '-' or '.')",
        )
    return interface


def _ssid(ssid: object) -> str:
    if ssid is None or ssid == "":
        raise NetworkSettingError("wifi_ssid", "a wifi host needs wifi_ssid")
    if not isinstance(ssid, str):
        raise NetworkSettingError("wifi_ssid", f"{ssid!r} is not text: quote it in the roster")
    refused = sorted({f"U+{ord(c):04X}" for c in ssid if unicodedata.category(c) in REFUSED_CATEGORIES})
    if refused:
        raise NetworkSettingError(
            "wifi_ssid",
            f"{ssid!r} is not a valid SSID: no control characters or line breaks ({', '.join(refused)})",
        )
    if len(ssid.encode()) > SSID_MAX_BYTES:
        raise NetworkSettingError(
            "wifi_ssid", f"{ssid!r} is not a valid SSID: at most {SSID_MAX_BYTES} bytes of UTF-8"
        )
    return ssid


def _wifi_password(settings: HostSettings) -> Any:
    name = settings.wifi_password_secret
    if not name:
        raise NetworkSettingError(
            "wifi_password_secret",
            "a wifi host needs wifi_password_secret naming the WiFi password in the secrets file",
        )
    password = settings.wifi_password
    if password is None:
        raise NetworkSettingError(
            "wifi_password_secret", f"secret {name!r} was not found in the secrets file"
        )
    clear = _unmask(password)
    # Never quote the password itself, not even a part of it.
    if not isinstance(clear, str):
        raise NetworkSettingError(
            "wifi_password_secret", f"secret {name!r} is not text: quote it in the secrets file"
        )
    if not (WPA_PASSPHRASE.fullmatch(clear) or WPA_HEX_KEY.fullmatch(clear)):
        raise NetworkSettingError(
            "wifi_password_secret",
            f"secret {name!r} is not a WPA password (8 to 63 printable ASCII characters, "
            f"no line breaks or control characters, or 64 hex digits; it has {len(clear)} characters)",
        )
    return password


def manages_network(settings: HostSettings) -> bool:
    """Whether the network deploy touches this host at all."""
    if not settings.network_enabled:
        return False
    return bool(settings.network_address) or settings.network_method == "dhcp"


def network_settings(settings: HostSettings) -> NetworkSettings | None:
    """Parse and check one host's network settings; None if the host's network is left alone.

    Raises NetworkSettingError naming the field for any bad value (and nothing else,
    whatever the types in `settings`: HostSettings checked them, and this does again).
    """
    if not manages_network(settings):
        return None
    kind = _choice("network_kind", settings.network_kind, KINDS)
    method = _choice("network_method", settings.network_method, METHODS)
    backend = _choice("network_backend", settings.network_backend, BACKENDS)
    ipv6 = _choice("network_ipv6", settings.network_ipv6, IPV6_MODES)
    interface = _interface(settings.network_interface, kind)

    address = _address(settings) if method == "static" else None
    gateway = _gateway(settings.network_gateway, address)
    nameservers = _nameservers(settings.network_nameservers)

    ssid, password = (_ssid(settings.wifi_ssid), _wifi_password(settings)) if kind == "wifi" else (None, None)

    timeout: object = settings.network_confirm_timeout
    if isinstance(timeout, bool) or not isinstance(timeout, int) or not 10 <= timeout <= 3600:
        raise NetworkSettingError(
            "network_confirm_timeout", f"{timeout!r} is not a number of seconds from 10 to 3600"
        )
    disable_cloud_init: object = settings.network_disable_cloud_init
    if not isinstance(disable_cloud_init, bool):
        raise NetworkSettingError(
            "network_disable_cloud_init", f"{disable_cloud_init!r} is not true or false"
        )

    backups_keep: object = settings.network_backups_keep
    if isinstance(backups_keep, bool) or not isinstance(backups_keep, int) or not 1 <= backups_keep <= 100:
        raise NetworkSettingError("network_backups_keep", f"{backups_keep!r} is not a number from 1 to 100")

    return NetworkSettings(
        kind=kind,
        method=method,
        interface=interface,
        backend=backend,
        ipv6=ipv6,
        address=address,
        gateway=gateway,
        nameservers=nameservers,
        wifi_ssid=ssid,
        wifi_password=password,
        confirm_timeout=timeout,
        disable_cloud_init=disable_cloud_init,
        backups_keep=backups_keep,
    )


@dataclass(frozen=True)
class NetworkProblem:
    """A bad network setting of one host in the roster."""

    team: str | None
    host: str
    field: str | None
    message: str


def check_classroom_network(
    hosts: Iterable[tuple[str | None, str, str | None, HostSettings | None]], check_duplicates: bool = True
) -> list[NetworkProblem]:
    """Check every host's network settings, and that no two hosts share an address.

    `hosts` yields (team, host name, the address SSH uses now, its typed settings, or None for a
    host the roster gives no network to manage). `check_duplicates=False` leaves duplicate
    network_address values to the caller.
    """
    problems: list[NetworkProblem] = []
    owners: dict[IPv4Address, str] = {}
    parsed: list[tuple[str | None, str, IPv4Address]] = []  # the hosts given an address
    ssh_addresses: dict[str, str] = {}

    for team, name, ssh_address, typed in hosts:
        if ssh_address:
            ssh_addresses[name] = str(ssh_address)
        try:
            settings = network_settings(typed) if typed is not None else None
        except NetworkSettingError as exc:
            problems.append(NetworkProblem(team, name, exc.field, exc.message))
            continue
        except Exception as exc:  # a bug here must not hide the host's problem, or stop the loader
            problems.append(NetworkProblem(team, name, None, f"network settings not checked: {exc!r}"))
            continue
        if settings is None or settings.address is None:
            continue
        ip = settings.address.ip
        parsed.append((team, name, ip))
        if ip in owners and check_duplicates:
            problems.append(
                NetworkProblem(
                    team, name, "network_address", f"{ip} is also the network_address of {owners[ip]}"
                )
            )
        else:
            owners[ip] = name

    # Moving onto an address another host answers at now would collide mid-run.
    # (Indexed by address: a classroom of thousands of static hosts stays linear.)
    reached_at: dict[str, list[str]] = {}
    for other, other_address in ssh_addresses.items():
        reached_at.setdefault(other_address, []).append(other)
    for team, name, ip in parsed:
        for other in reached_at.get(str(ip), ()):
            if other != name:
                problems.append(
                    NetworkProblem(
                        team,
                        name,
                        "network_address",
                        f"{ip} is the address {other} is reached at now",
                    )
                )
    return problems


def _given_a_network(data: Mapping[str, Any]) -> bool:
    """Whether a roster host's data asks the network deploy for anything: `manages_network`, read
    from the roster's mapping before the host's settings are built (network_enabled true and an
    address or DHCP)."""
    return bool(data.get("network_enabled", True)) and (
        bool(data.get("network_address")) or data.get("network_method") == "dhcp")


def validate_roster(classroom, report) -> None:
    """Roster validator (run by roslab.roster.load_roster): every host's network settings.

    Reports each problem with `report.error(...)` and never raises. The roster
    loader already reports two hosts with one network_address.
    """
    try:
        # Only a host the roster gives a network has its settings built (roslab.roster.Host.settings):
        # `roslab check` of 10,000 hosts without one builds none.
        hosts = [(host.team, host.name, host.address, host.settings if _given_a_network(host.data) else None)
                 for host in classroom.hosts]
        lines = {host.name: host.lines for host in classroom.hosts}
        problems = check_classroom_network(hosts, check_duplicates=False)
    except Exception as exc:  # never raise: the loader reports every problem at once
        report.error(f"the network settings could not be checked: {exc!r}")
        return
    for problem in problems:
        report.error(
            problem.message,
            team=problem.team,
            host=problem.host,
            field=problem.field,
            line=(lines.get(problem.host) or {}).get(problem.field) if problem.field else None,
        )
