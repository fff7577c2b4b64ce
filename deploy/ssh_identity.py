"""SSH and identity: sshd running, the teacher's keys authorised, hostname and /etc/hosts set."""

from __future__ import annotations

import ipaddress

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.facts.systemd import SystemdEnabled
from pyinfra.operations import apt, server, systemd

from deploy.common import existing_login_home, login_home, login_user, should_run
from roslab import probe, settings
from roslab.ops.apt import apt_install_options
from roslab.ops.files import managed_block, managed_block_reads
from roslab.host_settings import HostSettings, host_settings

DEFAULTS = settings.defaults("ssh_identity")

ETC_HOSTS_LABEL = "classroom hosts"
# Ubuntu 24.04 starts sshd through ssh.socket; forcing ssh.service there would fight it.
SSHD_SOCKET = "ssh.socket"


def sshd_unit() -> str:
    """ssh.socket where it is enabled, else ssh.service (systemd asked about ssh.socket only)."""
    enabled = host.get_fact(SystemdEnabled, services=[SSHD_SOCKET]).get(SSHD_SOCKET)
    return SSHD_SOCKET if enabled else "ssh.service"


def etc_hosts_lines(classroom_hosts) -> list[str]:
    """`<address> <name>` for every classroom host with an IP address (DNS names are skipped)."""
    lines = []
    for entry in classroom_hosts or []:
        try:
            address = ipaddress.ip_address(str(entry["address"]))
        except ValueError:
            continue
        lines.append(f"{address} {entry['name']}")
    return lines


@probe.installs
def ssh_identity_packages(settings: HostSettings, codename: str | None, python_sdist: bool = False) -> list[str]:
    """What this step installs (roslab.probe.installs): openssh-server."""
    return ["openssh-server"] if settings.ssh_identity_enabled else []


@deploy(
    "SSH is on, the teacher's keys are authorised and the host knows its classroom's names",
    data_defaults=DEFAULTS,
)
def ssh_identity():
    """Install and run sshd, authorise the teacher's keys, set hostname and /etc/hosts.

    Reads host_settings(host): ssh_identity_enabled, teacher_ssh_keys (key lines: the roster loader
    read the .pub files), manage_hostname, manage_etc_hosts, login_user, roslab_hostname,
    roslab_classroom_hosts, apt_lock_timeout.
    """
    typed = host_settings(host)
    if not should_run("ssh_identity_enabled"):
        return
    apt.packages(
        name="Ensure openssh-server is installed",
        packages=ssh_identity_packages(typed, None),
        extra_install_args=apt_install_options(typed.apt_lock_timeout),
    )
    unit = sshd_unit()
    systemd.service(
        name=f"Ensure sshd ({unit}) is enabled and running",
        service=unit,
        running=True,
        enabled=True,
    )

    keys = list(typed.teacher_ssh_keys)
    if keys:
        user = login_user()
        if login_home() is None:  # no such user on the host: it is stopped
            return
        server.user_authorized_keys(
            name=f"Ensure the teacher's SSH keys are authorised for {user}",
            user=user,
            public_keys=keys,
        )

    hostname = typed.roslab_hostname or host.name
    if typed.manage_hostname:
        server.hostname(name=f"Ensure the hostname is {hostname}", hostname=hostname)

    if typed.manage_etc_hosts:
        lines = etc_hosts_lines(typed.roslab_classroom_hosts)
        if lines:
            managed_block(
                name="Ensure /etc/hosts lists every classroom host",
                path="/etc/hosts",
                content="\n".join(lines),
                label=ETC_HOSTS_LABEL,
                user="root",
                group="root",
                mode="644",
            )


@probe.reader
def ssh_identity_reads() -> list:
    """What ssh_identity's operations read on a host that needs no change."""
    typed = host_settings(host)
    if not should_run("ssh_identity_enabled"):
        return []
    # Both units: which one sshd_unit() picks is part of this very read.
    reads = [*probe.packages_reads(), *probe.service_reads(SSHD_SOCKET), *probe.service_reads("ssh.service")]
    home = existing_login_home()
    if typed.teacher_ssh_keys and home:
        reads += probe.authorized_keys_reads(login_user(), home)
    if typed.manage_hostname:
        reads += probe.hostname_reads()
    if typed.manage_etc_hosts:
        reads += managed_block_reads("/etc/hosts")
    return reads
