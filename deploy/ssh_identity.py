"""SSH and identity: sshd running, the teacher's keys authorised, hostname and /etc/hosts set."""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path

from pyinfra import host
from pyinfra.api import DeployError, deploy
from pyinfra.facts.systemd import SystemdEnabled
from pyinfra.operations import apt, server, systemd

from deploy.common import controller_path, login_user, setting, should_run, where
from roslab.operations import managed_block

DEFAULTS = {
    # Install and run sshd, authorise the teacher's keys, set hostname and /etc/hosts.
    "ssh_identity_enabled": True,
    # The teacher's public keys for the login user's authorized_keys: key lines
    # ("ssh-ed25519 AAAA... teacher") or paths to .pub files on the machine running pyinfra.
    "teacher_ssh_keys": [],
    # Set the hostname to the host's name in the roster.
    "manage_hostname": True,
    # List every classroom host in /etc/hosts (a marked block) so names resolve without DNS.
    "manage_etc_hosts": True,
}

PUBLIC_KEY = re.compile(r"^(ssh-[a-z0-9-]+|ecdsa-sha2-\S+|sk-\S+)\s+[A-Za-z0-9+/=]+(\s.*)?$")
ETC_HOSTS_LABEL = "classroom hosts"


def public_keys(entries, resolve_path=Path) -> list[str]:
    """Key lines from `teacher_ssh_keys`: key text as is, .pub paths read on this machine.

    `resolve_path` turns an entry into a local path (the deploy resolves relative paths
    against the roster's directory).
    """
    if isinstance(entries, str):
        entries = [entries]
    keys: list[str] = []
    for entry in entries or []:
        entry = str(entry).strip()
        if PUBLIC_KEY.match(entry):
            keys.append(entry)
            continue
        path = resolve_path(entry)
        if not path.is_file():
            raise DeployError(
                f"{where()}: teacher_ssh_keys entry {entry!r} is neither a public key line "
                "nor a readable .pub file"
            )
        lines = [line.strip() for line in path.read_text().splitlines()]
        for line in lines:
            if line and not line.startswith("#"):
                if not PUBLIC_KEY.match(line):
                    raise DeployError(
                        f"{where()}: teacher_ssh_keys file {path} holds a line that is not a public key"
                    )
                keys.append(line)
    return keys


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


@deploy(
    "SSH is on, the teacher's keys are authorised and the host knows its classroom's names",
    data_defaults=DEFAULTS,
)
def ssh_identity():
    """Install and run sshd, authorise the teacher's keys, set hostname and /etc/hosts.

    Reads host.data: ssh_identity_enabled, teacher_ssh_keys, manage_hostname,
    manage_etc_hosts, login_user, roslab_hostname, roslab_classroom_hosts, apt_lock_timeout.
    """
    if not should_run("ssh_identity_enabled"):
        return
    apt.packages(
        name="Ensure openssh-server is installed",
        packages=["openssh-server"],
        extra_install_args=f"-o DPkg::Lock::Timeout={setting('apt_lock_timeout')}",
    )
    # Ubuntu 24.04 starts sshd through ssh.socket; forcing ssh.service there would fight it.
    unit = "ssh.socket" if host.get_fact(SystemdEnabled).get("ssh.socket") else "ssh.service"
    systemd.service(
        name=f"Ensure sshd ({unit}) is enabled and running",
        service=unit,
        running=True,
        enabled=True,
    )

    keys = public_keys(host.data.teacher_ssh_keys, resolve_path=controller_path)
    if keys:
        user = login_user()
        server.user_authorized_keys(
            name=f"Ensure the teacher's SSH keys are authorised for {user}",
            user=user,
            public_keys=keys,
        )

    hostname = host.data.get("roslab_hostname") or host.name
    if host.data.manage_hostname:
        server.hostname(name=f"Ensure the hostname is {hostname}", hostname=hostname)

    if host.data.manage_etc_hosts:
        lines = etc_hosts_lines(host.data.get("roslab_classroom_hosts"))
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
