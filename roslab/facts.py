"""pyinfra facts roslab's deploys need beyond pyinfra's own.

Each fact is one remote command; none of them changes the host.
"""

from __future__ import annotations

from pyinfra.api import FactBase, QuoteString, StringCommand
from typing_extensions import override


# apt's words for a dpkg lock another process holds (apt-get check waited for it).
_LOCK_HELD = ("Could not get lock", "Unable to acquire the dpkg frontend lock", "Unable to lock")
_UPDATE_PREFIX = "roslab-dpkg-update: "
_AUDIT_PREFIX = "roslab-dpkg-audit: "
_EXIT_PREFIX = "roslab-apt-exit="
_CLOUD_INIT_PREFIX = "roslab-cloud-init="
# cloud-init's systemd generator decided it runs this boot (else it is disabled, and
# `cloud-init status --wait` could wait for a stage that never starts) ...
CLOUD_INIT_RUNS = "/run/cloud-init/enabled"
# ... and its final stage has not written its result yet.
CLOUD_INIT_DONE = "/run/cloud-init/result.json"



def apt_lock_options(lock_timeout: int) -> str:
    """apt-get options that wait (bounded) for the dpkg lock instead of failing at once.

    The one place roslab spells the lock wait: every apt-get command line (roslab.operations
    imports it from here), the AptProblem fact and
    `apt.packages(extra_install_args=apt_install_options(...))` use it.
    """
    return f"-o DPkg::Lock::Timeout={int(lock_timeout)}"

class AptProblem(FactBase):
    """
    Waits (bounded) until apt can take the dpkg lock, then reports whether apt is usable.

    Returns ``None`` when ``apt-get check`` succeeds within ``lock_timeout`` seconds and
    dpkg has nothing half-done (``{"interrupted": False, "message": None, "waited": line}``
    when it had to wait for the lock first: apt's line naming who held it), else
    ``{"interrupted": bool, "message": str}``:

    - ``interrupted``: dpkg was stopped in the middle of an install (a Pi unplugged,
      dpkg killed): its journal ``/var/lib/dpkg/updates/`` is not empty, ``dpkg --audit``
      lists half-installed or unconfigured packages, or apt says "dpkg was interrupted".
      ``dpkg --configure -a`` and ``apt-get -f install`` heal it
      (``roslab.operations.dpkg_interrupted_install_finished``).
    - otherwise apt's own error lines, e.g. the lock still held by unattended-upgrades
      after the wait, or broken dependencies. Fresh Ubuntu images hold the lock for
      minutes at first boot.

    While another process holds the lock its half-done work is normal, not interrupted.

    First, on a freshly seeded Pi, it waits (bounded by ``lock_timeout`` too) for cloud-init
    to finish its first boot (``cloud-init status --wait``): cloud-init's own package step
    fails when a deploy takes the dpkg lock from under it. Only where cloud-init exists and
    has not finished this boot: on a settled host the wait costs a few ``test -e``. Then
    the result has ``"cloud_init": {"status": exit status (124: still running at the
    timeout), "seconds": waited, "output": its last words}`` (else no such key).
    """

    @override
    def command(self, lock_timeout: int) -> StringCommand:
        wait_for_cloud_init = (
            f"if [ -e {CLOUD_INIT_RUNS} ] && [ ! -e {CLOUD_INIT_DONE} ] && command -v cloud-init >/dev/null 2>&1; then "
            "started=$(date +%s); "
            f"said=$(timeout {int(lock_timeout) or 1} cloud-init status --wait 2>&1 </dev/null); rc=$?; "
            f'echo "{_CLOUD_INIT_PREFIX}$rc $(( $(date +%s) - started )) '
            '$(printf %s "$said" | tr -s \'.\\n\' \' \' | tail -c 200)"; '
            "fi;"
        )
        # `; echo` keeps the fact's exit status 0 so the failure reaches process().
        return StringCommand(
            wait_for_cloud_init,
            f"apt-get -qq {apt_lock_options(lock_timeout)} check 2>&1;",
            f'echo "{_EXIT_PREFIX}$?";',
            f"ls -A /var/lib/dpkg/updates 2>/dev/null | sed 's/^/{_UPDATE_PREFIX}/';",
            f"dpkg --audit 2>&1 | sed 's/^/{_AUDIT_PREFIX}/'",
        )

    @override
    def process(self, output):
        cloud_init = None
        for line in output:
            if line.startswith(_CLOUD_INIT_PREFIX):
                status, seconds, *said = line[len(_CLOUD_INIT_PREFIX):].split(" ", 2)
                cloud_init = {"status": int(status) if status.isdigit() else -1,
                              "seconds": int(seconds) if seconds.isdigit() else 0,
                              "output": (said[0] if said else "").strip()}
        apt = self._apt(line for line in output if not line.startswith(_CLOUD_INIT_PREFIX))
        if cloud_init is None:
            return apt
        return {**(apt or {"interrupted": False, "message": None}), "cloud_init": cloud_init}

    @staticmethod
    def _apt(output):
        check, updates, audit, status, waited = [], [], [], "", ""
        for line in output:
            if line.startswith(_EXIT_PREFIX):
                status = line
            elif line.startswith(_UPDATE_PREFIX):
                updates.append(line[len(_UPDATE_PREFIX):])
            elif line.startswith(_AUDIT_PREFIX):
                if line[len(_AUDIT_PREFIX):].strip():
                    audit.append(line[len(_AUDIT_PREFIX):].strip())
            # apt prints "Waiting for cache lock" lines while it waits: keep the verdict,
            # and the first of them to say who held the lock.
            elif line.startswith("Waiting for cache lock"):
                waited = waited or line
            else:
                check.append(line)
        text = "\n".join(check)
        ok = status == f"{_EXIT_PREFIX}0"
        lock_held = not ok and any(words in text for words in _LOCK_HELD)
        interrupted = not lock_held and bool(updates or audit or "dpkg was interrupted" in text)
        if ok and not interrupted:
            # A wait that ended well is no problem, but the teacher should know it happened.
            return {"interrupted": False, "message": None, "waited": waited} if waited else None
        if interrupted:
            found = []
            if updates:
                found.append(f"{len(updates)} pending entries in /var/lib/dpkg/updates/")
            if audit:
                found.append("dpkg --audit: " + " ".join(audit)[:300])
            message = "dpkg was interrupted" + (f" ({'; '.join(found)})" if found else "")
        else:
            message = text or status or "apt-get check printed nothing"
        return {"interrupted": interrupted, "message": message}


class FileAge(FactBase):
    """
    Returns how many seconds ago a file was last modified, by the host's clock, or ``None``
    when the file does not exist.
    """

    @override
    def command(self, path: str) -> StringCommand:
        return StringCommand(
            "if [ -e",
            QuoteString(path),
            "]; then echo $(( $(date +%s) - $(stat -c %Y",
            QuoteString(path),
            ") )); fi",
        )

    @override
    def process(self, output):
        for line in output:
            line = line.strip()
            if line.lstrip("-").isdigit():
                return int(line)
        return None


_BOOT_PREFIX = "roslab-boot="
# How long a run waits for a host that is still booting (s): Ubuntu's wait for the network
# (systemd-networkd-wait-online) gives up after 120 s, so a boot is over well within this.
BOOT_WAIT = 300


class BootFinished(FactBase):
    """
    Waits (bounded by ``timeout`` seconds) until systemd has finished starting the host, and
    says whether it had to.

    A run right after a reboot meets units whose start is queued behind the network (a robot's
    service waits for network-online.target): read then, they look stopped, and starting them
    would be a change the boot was about to make itself. On a booted host this costs one
    ``systemctl is-system-running``.

    Returns ``None`` where systemd does not run the host, else ``{"waited": bool, "seconds":
    int, "state": systemd's word after the wait ("running", "degraded"; "" when still starting
    at the timeout), "timed_out": bool}``.
    """

    @override
    def command(self, timeout: int) -> str:
        return (
            "if command -v systemctl >/dev/null 2>&1; then "
            "state=$(systemctl is-system-running 2>/dev/null); "
            'case "$state" in initializing|starting) started=$(date +%s); '
            f"state=$(timeout {int(timeout) or 1} systemctl is-system-running --wait 2>/dev/null); rc=$?; "
            f'echo "{_BOOT_PREFIX}waited $rc $(( $(date +%s) - started )) $state";; '
            f'*) echo "{_BOOT_PREFIX}settled 0 0 $state";; esac; fi'
        )

    @override
    def process(self, output):
        for line in output:
            if line.startswith(_BOOT_PREFIX):
                how, status, seconds, *state = line[len(_BOOT_PREFIX):].split(" ", 3)
                return {"waited": how == "waited", "seconds": int(seconds) if seconds.isdigit() else 0,
                        "state": (state[0] if state else "").strip(), "timed_out": status == "124"}
        return None
