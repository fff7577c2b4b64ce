"""systemd: a boot that has finished, masked units, a service installed but not running (facts
and operations side by side, roslab.ops)."""

from __future__ import annotations

from pyinfra import host
from pyinfra.api import FactBase, OperationError, operation
from typing_extensions import override

from roslab.quoting import shell_word


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


class UnitsMasked(FactBase):
    """For each of `units`, whether systemd has it masked ({unit: bool})."""

    def command(self, units: list[str]) -> str:
        words = " ".join(shell_word(unit) for unit in units)
        return (f"for unit in {words}; do "
                'printf "%s %s\\n" "$unit" "$(systemctl is-enabled "$unit" 2>/dev/null || true)"; done')

    def process(self, output):
        masked = {}
        for line in output:
            unit, _, state = line.strip().partition(" ")
            if unit:
                masked[unit] = state.strip() == "masked"
        return masked


@operation()
def units_masked(units: list[str]):
    """Each of `units` is masked (linked to /dev/null): nothing starts or waits for it.

    + units: systemd unit names (``sleep.target``, ``systemd-networkd-wait-online.service``)

    A unit this host does not have is masked all the same, so a later install cannot start it.
    Example: ``units_masked(name="...", units=["sleep.target", "suspend.target"])``
    """
    from roslab.profiles.schema import maskable_unit_problem

    for unit in units:  # checked at load; hand-made host data gets the same allow-list
        if maskable_unit_problem(unit):
            raise OperationError(maskable_unit_problem(unit))
    current = host.get_fact(UnitsMasked, units=units)
    missing = [unit for unit in units if not current.get(unit)]
    if not missing:
        host.noop(f"{', '.join(units)} already masked")
        return
    yield f"systemctl mask {' '.join(shell_word(unit) for unit in missing)}"


@operation()
def service_installed_not_running(service: str, because: str):
    """A unit is stopped and not enabled, for `because` (a setting says it must not run yet:
    the rover before calibration, a board not yet present); it stays installed.

    + service: the unit (``osr_startup.service``)
    + because: why, for the no-op line and the operation's name
    """
    from pyinfra.facts.systemd import SystemdEnabled, SystemdStatus

    running = (host.get_fact(SystemdStatus, services=[service]) or {}).get(service)
    enabled = (host.get_fact(SystemdEnabled, services=[service]) or {}).get(service)
    if not running and not enabled:
        host.noop(f"{service} is installed but not enabled because {because}")
        return
    if running:
        yield f"systemctl stop {shell_word(service)}"
    if enabled:
        yield f"systemctl disable {shell_word(service)}"
