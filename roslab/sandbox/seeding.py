"""Booting a sandbox host "as flashed": cloud-init from a NoCloud seed, as a Pi does.

A real Pi reads its seed (`user-data`, `network-config`, `meta-data`, written by
`roslab seed`) from the FAT boot partition, mounted at `/boot/firmware`, where
Ubuntu's Pi images point cloud-init's NoCloud datasource (filesystem label
`system-boot`). A sandbox host booted with a seed gets the seed directory bound
read-only at `/boot/firmware` and runs Debian's real cloud-init (22.4) on it:
cloud-init creates the user, installs the SSH host keys, sets the hostname and
writes `/etc/netplan/50-cloud-init.yaml` from the seed's `network-config`.

Hosts not booted from a seed keep cloud-init disabled (`/etc/cloud/cloud-init.disabled`
in the base image), so their boots stay fast.

Two pieces here are stand-ins for what a container cannot have (each says so in
the files it writes):

- the label lookup: a container sees no block devices, so cloud-init's search for
  the `system-boot` label finds nothing; `/var/lib/cloud/seed/nocloud` (one of
  NoCloud's seed directories, read with `network-config` in 22.4, unlike
  `seedfrom`) is a link to `/boot/firmware`;
- Ubuntu's first-boot unattended-upgrades: a service that holds the dpkg locks
  (`fcntl` on `/var/lib/dpkg/lock-frontend` and `/var/lib/dpkg/lock`, as apt does)
  for a while on the first boot, so the deploy's wait for the lock is exercised.
"""

from __future__ import annotations

import ipaddress
import json
import os
import re
from pathlib import Path

import yaml

from .system import SandboxError

SEED_FILES = ("user-data", "meta-data", "network-config")
REQUIRED_SEED_FILES = ("user-data", "meta-data")  # what NoCloud insists on
BOOT_PARTITION = "/boot/firmware"  # where Ubuntu for Pi mounts the boot partition
NOCLOUD_SEED_DIR = "/var/lib/cloud/seed/nocloud"

CLOUD_INIT_DISABLED = "/etc/cloud/cloud-init.disabled"
CLOUD_INIT_DISABLED_TEXT = (
    "roslab sandbox: cloud-init is installed but disabled on hosts not booted from a seed\n"
    "(a Pi after its first boot); `roslab sandbox reset HOST --seed DIR` removes this file.\n"
)

# Ubuntu for Pi's datasource configuration (livecd-rootfs writes it as 99-fake_cloud.cfg).
UBUNTU_PI_DATASOURCE = (
    "# roslab sandbox emulation of Ubuntu for Raspberry Pi's cloud-init datasource\n"
    "# configuration: the seed is on the boot partition, labelled system-boot.\n"
    "datasource_list: [ NoCloud, None ]\n"
    "datasource:\n"
    "  NoCloud:\n"
    "    fs_label: system-boot\n"
)

# Ubuntu's cloud.cfg renders the network with netplan; Debian's would try ifupdown first.
UBUNTU_NETWORK_RENDERER = (
    "# roslab sandbox emulation of Ubuntu's cloud.cfg: cloud-init writes the network\n"
    "# configuration as netplan (/etc/netplan/50-cloud-init.yaml), as on Ubuntu Server.\n"
    "system_info:\n"
    "  network:\n"
    "    renderers: [netplan]\n"
)


def cloud_init_image_files() -> dict[str, str]:
    """cloud-init configuration baked into the base image (inert while cloud-init is disabled)."""
    return {
        "/etc/cloud/cloud.cfg.d/99-fake_cloud.cfg": UBUNTU_PI_DATASOURCE,
        "/etc/cloud/cloud.cfg.d/90-roslab-sandbox-ubuntu.cfg": UBUNTU_NETWORK_RENDERER,
    }


def seed_address(seed: Path, subnet: ipaddress.IPv4Network) -> str:
    """The address a seed gives its host on the sandbox network; SandboxError if it is no
    NoCloud seed or gives none there (checked before any host is touched).

    The sandbox network has no DHCP server: a seed must set a static address (the roster's
    `network_address`) inside the sandbox's subnet, or the host would never be reachable.
    """
    if not seed.is_dir():
        raise SandboxError(f"--seed {seed}: not a directory (give the folder `roslab seed` wrote for the host)")
    missing = [name for name in REQUIRED_SEED_FILES if not (seed / name).is_file()]
    if missing:
        raise SandboxError(f"--seed {seed}: no {' or '.join(missing)} in it: not a cloud-init NoCloud seed "
                           "(`roslab seed ROSTER --out DIR` writes DIR/<host>/)")
    try:
        network = yaml.safe_load((seed / "network-config").read_text()) if (seed / "network-config").is_file() else {}
    except yaml.YAMLError as error:
        raise SandboxError(f"--seed {seed}: network-config is not YAML: {error}") from None
    network = (network or {}).get("network", network) if isinstance(network, dict) else {}
    addresses = []
    for kind in ("ethernets", "wifis"):
        for interface in ((network or {}).get(kind) or {}).values():
            for address in (interface or {}).get("addresses") or []:
                try:
                    addresses.append(ipaddress.ip_interface(str(address)).ip)
                except ValueError:
                    pass  # cloud-init and netplan report it
    inside = [str(address) for address in addresses if address in subnet]
    if not inside:
        raise SandboxError(
            f"--seed {seed}: its network-config gives no static address in the sandbox's subnet {subnet} "
            f"(it has {', '.join(map(str, addresses)) or 'DHCP only'}); the sandbox network has no DHCP "
            "server: give the host a network_address in the roster and run `roslab seed` again")
    return inside[0]


# -- the first-boot unattended-upgrades stand-in ---------------------------------------------

FIRST_BOOT_APT_LOCK_SECONDS = 20  # Ubuntu's real one holds the lock for minutes; tests need seconds
FIRST_BOOT_UNIT = "roslab-sandbox-first-boot-upgrades.service"
FIRST_BOOT_SCRIPT = "/usr/local/sbin/roslab-sandbox-first-boot-upgrades"
FIRST_BOOT_CONFIG = "/etc/default/roslab-sandbox-first-boot-upgrades"
FIRST_BOOT_DONE = "/var/lib/roslab-sandbox/first-boot-upgrades.done"

FIRST_BOOT_SCRIPT_TEXT = f'''\
#!/usr/bin/python3
"""roslab sandbox STAND-IN for Ubuntu's first-boot unattended-upgrades.

A freshly flashed Ubuntu Pi runs unattended-upgrades soon after its first boot and
holds the dpkg lock meanwhile, so a deploy's first apt command meets a held lock.
This stand-in upgrades nothing: it takes the locks apt takes (fcntl write locks on
/var/lib/dpkg/lock-frontend, then /var/lib/dpkg/lock), tells systemd it holds them,
holds them for HOLD_SECONDS (from {FIRST_BOOT_CONFIG}) and marks the first boot done.
"""
import fcntl
import os
import socket
import time
from pathlib import Path

seconds = float(os.environ.get("HOLD_SECONDS", "{FIRST_BOOT_APT_LOCK_SECONDS}"))
handles = []
for name in ("/var/lib/dpkg/lock-frontend", "/var/lib/dpkg/lock"):
    handle = open(name, "a")
    fcntl.lockf(handle, fcntl.LOCK_EX)  # waits for any apt already running, as apt would
    handles.append(handle)
address = os.environ.get("NOTIFY_SOCKET", "")
if address:  # Type=notify: the host's sshd starts only once the locks are held
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.sendto(b"READY=1", "\\0" + address[1:] if address.startswith("@") else address)
print(f"roslab sandbox stand-in for first-boot unattended-upgrades: holding the dpkg lock for {{seconds:g}} s",
      flush=True)
time.sleep(seconds)
done = Path("{FIRST_BOOT_DONE}")
done.parent.mkdir(parents=True, exist_ok=True)
done.write_text("roslab sandbox stand-in for first-boot unattended-upgrades: done\\n")
'''

FIRST_BOOT_UNIT_TEXT = f"""\
# roslab sandbox STAND-IN for Ubuntu's first-boot unattended-upgrades: holds the dpkg
# lock for a while on a host's first boot from a seed (see {FIRST_BOOT_SCRIPT}).
[Unit]
Description=roslab sandbox stand-in for first-boot unattended-upgrades (holds the dpkg lock)
ConditionPathExists=!{FIRST_BOOT_DONE}
After=cloud-init.service
Before=ssh.service

[Service]
Type=notify
NotifyAccess=main
EnvironmentFile=-{FIRST_BOOT_CONFIG}
ExecStart={FIRST_BOOT_SCRIPT}

[Install]
WantedBy=multi-user.target
"""


# The sandbox network has no IPv6 router and no DHCP server. networkd calls a link with a
# static address online only once one of its dynamic protocols succeeded (a seed's eth0
# has router advertisements and DHCPv6 on, from network_ipv6: auto), and cloud-init's
# network stage waits for systemd-networkd-wait-online: 2 minutes. In a classroom the
# router answers at once. Here eth0 keeps only the seed's static configuration.
NO_ROUTER_DROP_IN = "/etc/systemd/network/10-netplan-eth0.network.d/50-roslab-sandbox-no-router.conf"
NO_ROUTER_DROP_IN_TEXT = (
    "# roslab sandbox: the sandbox network has no IPv6 router and no DHCP server, so eth0\n"
    "# asks for neither (booting would wait 2 minutes for them); its static address stays.\n"
    "[Network]\n"
    "DHCP=no\n"
    "IPv6AcceptRA=no\n"
)


# A Pi's ethernet keeps its MAC address. In a sandbox host, /sys/class/net lists the
# machine's interfaces (sysfs is not the host's network namespace), and cloud-init's
# netplan renderer runs `udevadm test-builtin net_setup_link` on each of them: udev's
# default MACAddressPolicy=persistent then lands, by interface index, on the host's own
# eth0 and gives it a new MAC address, leaving the machine's ARP entry stale for half a
# minute. Links keep their addresses here (inside the host's namespace only).
KEEP_MAC_LINK = "/etc/systemd/network/10-roslab-sandbox-keep-mac.link"
KEEP_MAC_LINK_TEXT = (
    "# roslab sandbox: interfaces keep their MAC address, as a Pi's ethernet does (udev's\n"
    "# default MACAddressPolicy=persistent would replace the sandbox veth's random one).\n"
    "[Match]\n"
    "OriginalName=*\n"
    "\n"
    "[Link]\n"
    "MACAddressPolicy=none\n"
)


def seed_locale_enabled(locale_gen: str, user_data: str) -> str:
    """/etc/locale.gen with the seed's `locale` enabled: emulating Ubuntu's locale-gen.

    cloud-init sets a seed's locale with `locale-gen <locale>`; Ubuntu's generates the
    locale it is given, Debian's ignores its arguments and reads /etc/locale.gen, so on
    these Debian hosts the line is enabled before the first boot instead.
    """
    try:
        config = yaml.safe_load(user_data)
    except yaml.YAMLError:
        return locale_gen  # cloud-init reports the broken seed itself
    locale = config.get("locale") if isinstance(config, dict) else None
    if not isinstance(locale, str) or not re.fullmatch(r"[A-Za-z0-9_.@-]+", locale):
        return locale_gen
    lines = locale_gen.splitlines(keepends=True)
    for index, line in enumerate(lines):
        words = line.lstrip("# ").split()
        if words and words[0] == locale:
            lines[index] = line.lstrip("# ")
            return "".join(lines)
    return locale_gen


def check_apt_lock_seconds(seconds: float) -> None:
    if not 0 <= seconds <= 3600:
        raise SandboxError(f"--apt-lock-seconds {seconds:g}: use 0 to 3600")


def seeded_boot_files(apt_lock_seconds: float) -> dict[str, tuple[str, int]]:
    """Files a host booted from a seed gets besides the seed: path -> (content, mode)."""
    check_apt_lock_seconds(apt_lock_seconds)
    files = {
        "/etc/cloud/cloud.cfg.d/README.roslab-sandbox": (
            "roslab sandbox: this host booted from a seed: Debian's cloud-init ran on the\n"
            f"NoCloud seed bound at {BOOT_PARTITION} (the Pi's boot partition).\n", 0o644),
        NO_ROUTER_DROP_IN: (NO_ROUTER_DROP_IN_TEXT, 0o644),
        KEEP_MAC_LINK: (KEEP_MAC_LINK_TEXT, 0o644),
    }
    if apt_lock_seconds:
        files.update({
            FIRST_BOOT_SCRIPT: (FIRST_BOOT_SCRIPT_TEXT, 0o755),
            f"/etc/systemd/system/{FIRST_BOOT_UNIT}": (FIRST_BOOT_UNIT_TEXT, 0o644),
            FIRST_BOOT_CONFIG: ("# roslab sandbox stand-in for first-boot unattended-upgrades\n"
                                f"HOLD_SECONDS={apt_lock_seconds:g}\n", 0o644),
        })
    return files


def seed_from_card(card: Path, host_name: str, into: Path) -> Path:
    """The NoCloud seed on a flashed card (an image file or a block device), copied into
    `into`, as a Pi's cloud-init finds it: the files `roslab seed --image` or `roslab flash`
    wrote into the card's FAT `system-boot`. SandboxError, before any host is touched, when
    the card has no such partition or seed, or was seeded (or flashed) for another host.
    """
    from roslab.seed import documents, flash, targets

    if not (card.is_file() or card.is_block_device()):
        raise SandboxError(f"--card {card}: not an image file or a block device")
    try:
        fat = targets.ImageFat(card, targets.boot_partition(card))
        files = {name: fat.read(name) for name in (*documents.SEED_FILES, flash.MARKER)}
    except (targets.TargetError, OSError) as error:
        raise SandboxError(f"--card {card}: {error}") from None
    seed = {name: files[name] for name in documents.SEED_FILES}
    missing = [name for name, content in seed.items() if content is None]
    if missing:
        raise SandboxError(f"--card {card}: its system-boot holds no {' or '.join(missing)}: not seeded "
                           "(`roslab flash` or `roslab seed ROSTER --image FILE` seeds a card)")
    marker = files[flash.MARKER]
    try:
        meta = yaml.safe_load(seed["meta-data"] or b"") or {}
        record = json.loads(marker) if marker else {}
    except (yaml.YAMLError, ValueError) as error:
        raise SandboxError(f"--card {card}: its meta-data or flash record does not parse: {error}") from None
    hostname = meta.get("local-hostname") if isinstance(meta, dict) else None
    flashed_for = record.get("host") if isinstance(record, dict) else None
    meant = {str(value) for value in (hostname, flashed_for) if value is not None}
    if meant != {host_name}:
        raise SandboxError(f"--card {card}: it was seeded for {' and '.join(sorted(meant)) or 'no host'}, "
                           f"not {host_name}")
    into.mkdir(parents=True, exist_ok=True)
    for name, content in seed.items():
        descriptor = os.open(into / name, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)  # user-data: secrets
        with os.fdopen(descriptor, "wb") as out:
            out.write(content or b"")
    return into
