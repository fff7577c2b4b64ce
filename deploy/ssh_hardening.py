"""SSH hardened without lockout: key-only login and no root login, once a key login is proven."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import deploy
from pyinfra.operations import server

from deploy.common import should_run, stop_host, where
from roslab import probe, settings
from roslab.ssh.sshd import DROPIN, KeyLogin, SshdLoginSettings, sshd_key_only
from roslab.host_settings import host_settings

DEFAULTS = settings.defaults("ssh_hardening")


@deploy("SSH accepts keys only and no root login, and the teacher's key still gets in", data_defaults=DEFAULTS)
def ssh_hardening():
    """Write sshd's drop-in (roslab.ssh.sshd.DROPIN) and reload sshd, never locking roslab out.

    Runs after ssh_identity (which authorised the teacher's keys): the drop-in changes only
    after a key-only login from this machine worked in this run and sshd accepts the new
    configuration; see roslab.ssh.sshd.sshd_key_only.

    Reads host_settings(host): ssh_hardening_enabled, ssh_password_login, ssh_permit_root_login,
    ssh_user, ssh_hostname, ssh_port, ssh_key, ssh_known_hosts_file, ssh_strict_host_key_checking.
    """
    typed = host_settings(host)
    if not should_run("ssh_hardening_enabled"):
        return
    login = KeyLogin.of(typed, host.name)
    permit_root_login = typed.ssh_permit_root_login
    if login.user == "root" and permit_root_login == "no":
        stop_host(
            f"{where()}: field 'ssh_permit_root_login': roslab logs in as root (ssh_user), and "
            "PermitRootLogin no would lock it out; log in as the lab user, or set "
            "ssh_permit_root_login: prohibit-password; sshd was not changed"
        )
        return
    password_login = typed.ssh_password_login
    hardened = sshd_key_only(
        name=(f"Ensure sshd allows {'passwords and keys' if password_login else 'keys only'} "
              f"and root login {permit_root_login} ({DROPIN.rsplit('/', 2)[-2]}/...)"),
        login=login,
        password_login=password_login,
        permit_root_login=permit_root_login,
    )
    # Reloading keeps open sessions (this one included); an sshd that is not running
    # (socket activation before its first login) reads the new file when it starts.
    server.shell(
        name="Reload sshd so that it uses its new configuration",
        commands=["systemctl try-reload-or-restart ssh.service"],
        _if=hardened.did_change,
    )


@probe.reader
def ssh_hardening_reads() -> list:
    """What ssh_hardening's operation reads on a host that needs no change (roslab.probe)."""
    return [probe.read(SshdLoginSettings)] if should_run("ssh_hardening_enabled") else []
