"""One host's NoCloud seed: `user-data`, `network-config` and `meta-data`.

Every document is built as Python data from checked roster values and dumped with
`yaml.safe_dump` (the netplan document with the network deploy's own renderer, whose
every value is a YAML double-quoted string), so no roster value is ever spliced into
YAML text. Which file holds which secret:

- user-data: the host's SSH private key (mode 0600), no WiFi password;
- network-config: the WiFi password when the host is on WiFi (mode 0600 then);
- meta-data: the instance id (a hash of the other two: a changed seed is a new
  instance, so cloud-init applies it again) and the hostname.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import yaml

from roslab import formats, settings
from roslab.ssh import identity
from roslab.controller_files import UnreadableFile, read_regular_file
from roslab.secrets import plain_text
from roslab.network.render import render_netplan
from roslab.network.settings import NetworkSettingError, network_settings
from roslab.roster.model import Host

SEED_FILES = ("user-data", "network-config", "meta-data")
# The groups Ubuntu gives its default user that a robotics class needs (serial ports,
# cameras, sound, USB devices); cloud-init creates any a release lacks.
LAB_USER_GROUPS = ["adm", "audio", "dialout", "plugdev", "sudo", "video"]
HEADER = "# managed by roslab: first-boot configuration of {host} from the classroom roster ({what}).\n"


class SeedError(ValueError):
    """Why a host cannot be seeded; names the host and the roster field."""

    def __init__(self, host: str, field: str | None, message: str):
        where = f"host {host!r}" + (f", field {field!r}" if field else "")
        super().__init__(f"{where}: {message}")
        self.host, self.field, self.message = host, field, message


@dataclass(frozen=True)
class SeedFile:
    name: str
    content: bytes
    secret: bool  # holds a private key or a password: written 0600, never printed

    @property
    def mode(self) -> int:
        return 0o600 if self.secret else 0o644


class _Dumper(yaml.SafeDumper):
    """safe_dump, with multi-line strings (the private key) as literal blocks where YAML allows."""


def _represent_str(dumper: yaml.SafeDumper, value: str):
    style = "|" if "\n" in value else None
    return dumper.represent_scalar("tag:yaml.org,2002:str", value, style=style)


_Dumper.add_representer(str, _represent_str)


def dump(document) -> str:
    return yaml.dump(document, Dumper=_Dumper, sort_keys=False, default_flow_style=False,
                     allow_unicode=True, width=4096)


def login_public_key(host: Host) -> list[str]:
    """The controller's login key (`ssh_key`) as a public key line, from its .pub file."""
    private = host.settings.ssh_key
    if not private:
        return []
    public = Path(f"{private}.pub")
    try:
        lines = formats.public_key_lines(read_regular_file(public).decode("utf-8"))
    except (UnreadableFile, UnicodeDecodeError):
        lines = None
    if not lines:
        raise SeedError(host.name, "ssh_key",
                        f"{public} is missing or not a public key; the seed authorises it for the lab "
                        f"user: run `ssh-keygen -y -f {private} > {public}`")
    return lines


def authorized_keys(host: Host) -> list[str]:
    keys = list(dict.fromkeys([*host.settings.teacher_ssh_keys, *login_public_key(host)]))
    if not keys:
        raise SeedError(host.name, "teacher_ssh_keys",
                        "a seeded Pi allows no password login, so it needs an SSH key to let you in: "
                        "set teacher_ssh_keys (or ssh_key, with its .pub beside it)")
    return keys


def user_data(host: Host, keys: identity.HostKeys) -> dict:
    """The cloud-config of one host (see cloud-init's cc_* modules of the same names)."""
    typed = host.settings
    ssh_user = typed.ssh_user or settings.SETTINGS["ssh_user"].default
    keys_text = authorized_keys(host)
    user = {
        "name": ssh_user,
        "gecos": "roslab lab user",
        "groups": LAB_USER_GROUPS,
        "shell": "/bin/bash",
        # No password at all (password login is off): sudo without one.
        "lock_passwd": True,
        "sudo": "ALL=(ALL) NOPASSWD:ALL",
        "ssh_authorized_keys": keys_text,
    }
    if typed.console_password is not None:
        # A way in at the Pi's own keyboard when its network is wrong. Hashed here, never the
        # plain text; SSH still takes keys only (ssh_pwauth: false).
        user["lock_passwd"] = False
        user["hashed_passwd"] = console_password_hash(host, keys)
    users = [user]
    login = typed.login_user
    if login and login != ssh_user:  # the student account that owns the ROS environment
        users.append({"name": login, "groups": [g for g in LAB_USER_GROUPS if g != "sudo"],
                      "shell": "/bin/bash", "lock_passwd": True, "ssh_authorized_keys": keys_text})
    return {
        "hostname": host.name,
        "preserve_hostname": False,
        "locale": typed.locale,
        "timezone": typed.timezone,
        "users": users,
        "ssh_pwauth": False,
        "disable_root": True,
        # The host key generated once on the controller: a re-flashed Pi keeps its identity.
        "ssh_deletekeys": True,
        "ssh_genkeytypes": ["ed25519"],
        "ssh_keys": {"ed25519_private": keys.private_text(), "ed25519_public": keys.public_line()},
        # Nothing from the internet at first boot (a classroom network may have none): Ubuntu
        # Server's image has openssh-server, and the deploy installs everything else.
        "package_update": False,
        "package_upgrade": False,
        # Pis have no clock battery: time must sync before apt trusts signatures.
        "ntp": {"enabled": True, "ntp_client": "systemd-timesyncd"},
    }


CRYPT_SALT_CHARS = "./0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"


def check_console_password(host: Host) -> tuple[str, str]:
    """(the console password, openssl's path); SeedError when it cannot be hashed."""
    import shutil

    secret = host.settings.console_password
    password = plain_text(secret)
    if secret is None or not password or any(char in password for char in "\n\r\0"):
        raise SeedError(host.name, "console_password_secret", "the console password must be one non-empty line")
    openssl = shutil.which("openssl")
    if openssl is None:
        raise SeedError(host.name, "console_password_secret",
                        "hashing the console password needs openssl on this machine (apt install openssl)")
    return password, openssl


def console_password_hash(host: Host, keys: identity.HostKeys) -> str:
    """The console password as a SHA-512 crypt hash (`$6$salt$...`, what /etc/shadow holds),
    made by `openssl passwd -6` with the password on its stdin (never on a command line).
    The salt is derived from the host's own key, so the same roster gives the same seed
    (and the same cloud-init instance) on every `roslab seed`, and each Pi its own salt."""
    import subprocess

    password, openssl = check_console_password(host)
    digest = hashlib.sha256(f"roslab console salt\0{host.name}\0{keys.private_text()}".encode()).digest()
    salt = "".join(CRYPT_SALT_CHARS[byte % len(CRYPT_SALT_CHARS)] for byte in digest[:16])
    done = subprocess.run([openssl, "passwd", "-6", "-salt", salt, "-stdin"], input=password + "\n",
                          capture_output=True, text=True, timeout=30)
    hashed = done.stdout.strip()
    if done.returncode != 0 or not hashed.startswith(f"$6${salt}$"):
        raise SeedError(host.name, "console_password_secret",
                        f"openssl could not hash the console password ({' '.join(done.stderr.split())[:200]})")
    return hashed


def network_config(host: Host) -> tuple[str, bool]:
    """(netplan v2 document, holds a password). Without network settings: DHCP on eth0,
    as Ubuntu's own image does. `renderer: networkd` always: without it a static address
    on a Pi image silently falls back to DHCP."""
    try:
        settings = network_settings(host.settings)
    except NetworkSettingError as error:
        raise SeedError(host.name, error.field, error.message) from None
    if settings is None:
        return HEADER.format(host=host.name, what="DHCP on eth0") + dump({"network": {
            "version": 2, "renderer": "networkd",
            "ethernets": {"eth0": {"dhcp4": True, "optional": True}}}}), False
    return (render_netplan(settings, "networkd", host.settings.wifi_regulatory_domain),
            settings.password is not None)


def host_seed(host: Host, roster_path) -> dict[str, SeedFile]:
    """The three seed files of `host` (its host key is generated on first use)."""
    keys = identity.host_keys(roster_path, host.name)
    user_text = "#cloud-config\n" + HEADER.format(host=host.name, what="user-data") + dump(user_data(host, keys))
    network_text, network_secret = network_config(host)
    digest = hashlib.sha256((user_text + "\0" + network_text).encode()).hexdigest()[:16]
    meta_text = HEADER.format(host=host.name, what="meta-data") + dump({
        "instance-id": f"roslab-{host.name}-{digest}",
        "local-hostname": host.name,
    })
    return {
        "user-data": SeedFile("user-data", user_text.encode(), secret=True),
        "network-config": SeedFile("network-config", network_text.encode(), secret=network_secret),
        "meta-data": SeedFile("meta-data", meta_text.encode(), secret=False),
    }
