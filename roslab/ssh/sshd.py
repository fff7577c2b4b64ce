"""sshd made key-only without locking anyone out: the operation, its fact, and the key login check.

`sshd_key_only` compares roslab's drop-in and sshd's effective settings with what the
roster asks for. When they differ it, in this order:

1. logs in from the controller over a *new* SSH connection with the roster's key only
   (publickey, BatchMode: no password could help it), as roslab's SSH user, at the
   address the host is reached at (`confirm_key_login`, run on the controller). If that
   fails, the operation fails there and nothing on the host has changed;
2. uploads the new drop-in beside the live one under a name sshd does not read;
3. checks it on the host (`INSTALL_SCRIPT`): a copy of sshd's configuration with the
   new drop-in in it must pass `sshd -t`, and `sshd -T` must show the wanted values
   (sshd keeps the *first* value it reads, so a file read earlier could overrule ours);
   only then is it moved into place (one rename). Otherwise it is removed, and sshd's
   files and running configuration stay as they were.

The caller reloads sshd with `_if=<this operation>.did_change` (deploy/ssh_hardening.py).
"""

from __future__ import annotations

import hashlib
import shlex
import subprocess
from dataclasses import dataclass
from io import StringIO

from pyinfra import host, logger, state
from pyinfra.api import FactBase, FunctionCommand, QuoteString, StringCommand, operation
from pyinfra.api.command import FileUploadCommand
from pyinfra.facts.files import FileContents
from pyinfra.operations.util.files import generate_color_diff

from roslab.host_fields import HostSettings
from roslab.templating import render

# Its name sorts before Ubuntu's drop-ins (50-cloud-init.conf, 60-cloudimg-settings.conf):
# sshd_config includes sshd_config.d/*.conf at its top, in name order, and the first value wins.
DROPIN = "/etc/ssh/sshd_config.d/01-roslab.conf"
# The new drop-in waits here until it is checked: sshd only reads `*.conf`.
STAGED = DROPIN + ".roslab-new"
SSHD = "/usr/sbin/sshd"
TEMPLATE = "sshd-roslab.conf.j2"
OWNER = {"user": "root", "group": "root", "mode": "644"}
# Seconds the controller gives the key login (connect, authenticate, run `true`).
KEY_LOGIN_TIMEOUT = 30

SSHD_CONFIG = "/etc/ssh/sshd_config"
# Checked on the host, as root: $1 sshd, $2 its main configuration file, $3 the drop-in,
# $4 the staged new one, then one `<keyword> (<value>|...)` per setting `sshd -T` must show.
INSTALL_SCRIPT = r"""
sshd=$1 config=$2 target=$3 staged=$4
shift 4
dir=${target%/*}
shadow=$(mktemp -d "${TMPDIR:-/run}/roslab-sshd-check.XXXXXX") || exit 1
trap 'rm -rf "$shadow" "$staged"' EXIT
# sshd's configuration as it will be: the main file, its drop-ins, ours replaced by the new one.
cp -a "$dir" "$shadow/d" && cp "$staged" "$shadow/d/${target##*/}" &&
    sed "s#$dir/#$shadow/d/#g" "$config" > "$shadow/sshd_config" || exit 1
if ! errors=$("$sshd" -t -f "$shadow/sshd_config" 2>&1); then
    errors=$(printf '%s' "$errors" | sed "s#$shadow/d/#$dir/#g" | tr '\n' ' ')
    echo "roslab: sshd -t rejects the configuration, so ssh hardening changed nothing" \
        "and sshd keeps its current one: $errors" >&2
    exit 1
fi
effective=$("$sshd" -T -f "$shadow/sshd_config" 2>/dev/null)
for wanted in "$@"; do
    keyword=${wanted%% *}
    if ! printf '%s\n' "$effective" | grep -qiE "^$wanted\$"; then
        found=$(printf '%s\n' "$effective" | grep -i "^$keyword " | head -n 1)
        echo "roslab: sshd would still use '${found:-no $keyword}' although $target sets it:" \
            "a file sshd reads first sets its own (see: sudo sshd -T); ssh hardening changed nothing" >&2
        exit 1
    fi
done
chown root:root "$staged" && chmod 644 "$staged" && mv -f "$staged" "$target"
"""


def wanted_settings(password_login: bool, permit_root_login: str) -> dict[str, tuple[str, ...]]:
    """sshd -T keyword -> the values that mean what the roster asks for."""
    password = "yes" if password_login else "no"
    # sshd -T prints prohibit-password under its old name on some releases.
    root = ("prohibit-password", "without-password") if permit_root_login == "prohibit-password" else ("no",)
    return {
        "pubkeyauthentication": ("yes",),
        "passwordauthentication": (password,),
        "kbdinteractiveauthentication": (password,),
        "permitrootlogin": root,
    }


def dropin_text(password_login: bool, permit_root_login: str) -> str:
    if permit_root_login not in ("no", "prohibit-password"):
        raise ValueError(f"PermitRootLogin {permit_root_login!r} is not no or prohibit-password")
    return render(TEMPLATE, password_authentication="yes" if password_login else "no",
                  permit_root_login=permit_root_login)


class SshdLoginSettings(FactBase):
    """roslab's sshd drop-in and the login settings sshd would use, in one command.

    Returns ``{"dropin": {"user", "group", "mode", "sha256"} or None, "effective": {keyword: value}}``;
    ``effective`` holds `sshd -T`'s lower-case keywords (empty if sshd's files do not load).
    """

    @staticmethod
    def default():
        return {"dropin": None, "effective": {}}

    def command(self) -> str:
        path = shlex.quote(DROPIN)
        keywords = "|".join(wanted_settings(False, "no"))
        return (
            f"if [ -f {path} ]; then "
            f"echo \"dropin $(stat -c '%U %G %a' {path}) $(sha256sum < {path} | cut -d' ' -f1)\"; fi; "
            f"{SSHD} -T 2>/dev/null | grep -iE '^({keywords}) ' || true"
        )

    def process(self, output):
        dropin, effective = None, {}
        for line in output:
            words = line.split()
            if words[:1] == ["dropin"] and len(words) == 5:
                dropin = dict(zip(("user", "group", "mode", "sha256"), words[1:]))
            elif len(words) == 2:
                effective[words[0].lower()] = words[1].lower()
        return {"dropin": dropin, "effective": effective}


@dataclass(frozen=True)
class KeyLogin:
    """How the controller logs in to check that key login works: as roslab connects."""

    user: str | None  # None: the controller's own user, as pyinfra connects without ssh_user
    address: str
    port: int = 22
    key: str | None = None  # private key file; None: the agent and ~/.ssh's default keys
    known_hosts: str | None = None
    strict_host_key_checking: str | None = None

    @classmethod
    def of(cls, settings: HostSettings, host_name: str) -> KeyLogin:
        """How roslab connects to the host of these typed settings (pyinfra's name `host_name`)."""
        return cls(
            user=settings.ssh_user,
            address=str(settings.ssh_hostname or host_name),
            port=int(settings.ssh_port or 22),
            key=settings.ssh_key,
            known_hosts=settings.ssh_known_hosts_file,
            strict_host_key_checking=settings.ssh_strict_host_key_checking,
        )

    def argv(self) -> list[str]:
        """`ssh` logging in with a key only, on a new connection, and running `true`."""
        options = {
            "BatchMode": "yes",  # never a prompt: no password, no passphrase, no host key question
            "PreferredAuthentications": "publickey",
            "PasswordAuthentication": "no",
            "KbdInteractiveAuthentication": "no",
            "ControlMaster": "no",  # a shared connection from ~/.ssh/config would prove nothing
            "ControlPath": "none",
            "ConnectTimeout": "10",
            "LogLevel": "ERROR",
        }
        if self.key:
            options["IdentitiesOnly"] = "yes"
        if self.known_hosts:
            options["UserKnownHostsFile"] = self.known_hosts
        if self.strict_host_key_checking:
            options["StrictHostKeyChecking"] = self.strict_host_key_checking
        argv = ["ssh"]
        for option, value in options.items():
            argv += ["-o", f"{option}={value}"]
        if self.key:
            argv += ["-i", self.key]
        return [*argv, "-p", str(self.port), *(["-l", self.user] if self.user else []), "--", self.address, "true"]


def confirm_key_login(state, host, login: KeyLogin) -> bool:
    """On the controller: True once a key-only login to the host worked; else log why (one line)."""
    try:
        result = subprocess.run(login.argv(), stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                timeout=KEY_LOGIN_TIMEOUT)
        reason = None if result.returncode == 0 else (
            " ".join(result.stderr.split()) or f"ssh exited with {result.returncode}")
    except FileNotFoundError:
        reason = "the ssh client is not installed on this machine"
    except subprocess.TimeoutExpired:
        reason = f"no answer within {KEY_LOGIN_TIMEOUT} s"
    if reason is None:
        host.log(f"Key login as {login.user} to {login.address} confirmed", logger.info)
        return True
    host.log_styled(
        f"roslab: a key-only SSH login as {login.user} to {login.address}:{login.port} failed ({reason}), "
        "so ssh hardening changed nothing: sshd keeps its current configuration",
        fg="red",
        log_func=logger.error,
    )
    return False


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


@operation()
def sshd_key_only(login: KeyLogin, password_login: bool = False, permit_root_login: str = "no"):
    """
    Make sshd accept keys only (unless ``password_login``) and root as ``permit_root_login`` says.

    + login: how the controller checks that a key login works before anything changes
    + password_login: keep password and keyboard-interactive login
    + permit_root_login: ``no`` or ``prohibit-password``

    The drop-in ``/etc/ssh/sshd_config.d/01-roslab.conf`` changes only after a key-only
    login from the controller worked in this run, and only if sshd accepts the whole new
    configuration (``sshd -t``) and would use its values (``sshd -T``). sshd is not
    reloaded here: reload it with ``_if=<this operation>.did_change``.

    **Example:**

    .. code:: python

        hardened = sshd_key_only(
            name="Ensure sshd allows key login only",
            login=KeyLogin.of(host_settings(host), host.name),
        )
        server.shell(name="Reload sshd", commands=["systemctl reload ssh"], _if=hardened.did_change)
    """
    content = dropin_text(password_login, permit_root_login)
    wanted = wanted_settings(password_login, permit_root_login)
    found = host.get_fact(SshdLoginSettings)
    in_place = found["dropin"] == {**OWNER, "sha256": sha256(content)}
    effective = all(found["effective"].get(keyword) in values for keyword, values in wanted.items())
    if in_place and effective:
        host.noop(f"sshd already allows {'passwords and keys' if password_login else 'keys only'}, "
                  f"root login: {permit_root_login}")
        return

    if state.config.DIFF and not in_place:
        old = host.get_fact(FileContents, path=DROPIN)
        host.log(f"Will {'modify' if old is not None else 'create'} {DROPIN}", logger.info)
        old_lines = [line + "\n" for line in old or []]
        for line in generate_color_diff(old_lines, content.splitlines(keepends=True)):
            logger.info("  %s", line)
        logger.info("")

    yield FunctionCommand(confirm_key_login, (), {"login": login})
    yield FileUploadCommand(StringIO(content), STAGED)
    patterns = [f"{keyword} ({'|'.join(values)})" for keyword, values in wanted.items()]
    yield StringCommand("sh", "-c", QuoteString(INSTALL_SCRIPT), "roslab-sshd-install", SSHD, SSHD_CONFIG,
                        DROPIN, STAGED, *(QuoteString(pattern) for pattern in patterns))
