"""The pyinfra operation that moves a host's network without locking anyone out, and its facts.

`network_in_effect` compares the files a host should have with what it has. If
they differ it sends the new files on the stdin of one command, `network_apply.py start`
(roslab.network.apply), which stages them (root's, 0600 from their first byte, in a 0700
directory; never in a file of the login user's, never on a command line), validates
them, and starts `network_apply.py apply` with systemd-run, detached from the SSH
session; whatever fails, the staged files are removed. Finally (on the controller, at
execution time) `roslab.network.confirm.confirm_network_change` connects to the
host's new address, confirms, and moves pyinfra's connection there so the rest
of the deploy runs at the new address. Without a confirmation the host restores
its old files itself; the controller reports that and fails the host.
"""

from __future__ import annotations

import hashlib
import json
import shlex
from io import StringIO
from pathlib import Path
from uuid import uuid4

from pyinfra import host, logger, state
from pyinfra.api import FactBase, FunctionCommand, OperationError, StringCommand, operation
from pyinfra.api.command import FileUploadCommand
from pyinfra.facts.files import File, Sha256File
from pyinfra.operations.util.files import generate_color_diff

from roslab.network import apply
from roslab.network.apply import (
    BACKUP_ROOT,
    NETPLAN_DIR,
    RECOVERED_FILE,
    RUN_DIR,
    SCRIPT_INSTALL_PATH,
    STATE_DIR,
    STATUS_FILE,
    Plan,
    Status,
)
from roslab.network import state as network_state
from roslab.network.confirm import change_ended, change_started, confirm_network_change, confirm_pending_change
from roslab.network.render import (
    CLOUD_INIT_DISABLE_FILE,
    CLOUD_INIT_FILE,
    NETPLAN_FILE,
    SED_MASK_SECRETS,
    RendererFacts,
    choose_layout,
    desired_files,
    keyfile_path,
    mask_secrets,
)
from roslab.network.settings import NetworkSettings
from roslab.probe import read

APPLY_SCRIPT = Path(apply.__file__)
# Where the script and the plan go on the host (the script where the boot unit finds it).
SCRIPT_PATH = SCRIPT_INSTALL_PATH
PLAN_PATH = f"{RUN_DIR}/plan.json"
RECOVERED_PATH = f"{STATE_DIR}/{RECOVERED_FILE}"
STATUS_PATH = f"{RUN_DIR}/{STATUS_FILE}"


class SecretStdin:
    """A command's stdin that holds a secret: pyinfra reads it with readlines(); shown, it is masked."""

    def __init__(self, text: str):
        self._text = text

    def readlines(self) -> list[str]:
        return [self._text]

    def __repr__(self) -> str:
        return "SecretStdin(***)"

    __str__ = __repr__


class NetworkRenderer(FactBase):
    """Who manages the host's network, and whether cloud-init writes it.

    Returns ``{"renderer": RendererFacts(...), "cloud_init": bool, "recovered": dict | None,
    "last_change": Status | None}``: what the boot unit restored (until reported), and how the
    last change since boot ended as the host's status file says (/run: gone at a restart).
    """

    def command(self) -> str:
        return (
            "echo networkmanager=$(systemctl is-active NetworkManager 2>/dev/null); "
            "echo networkd=$(systemctl is-active systemd-networkd 2>/dev/null); "
            "if command -v netplan >/dev/null 2>&1; then echo netplan=yes; fi; "
            f"if grep -qsiE '^[[:space:]]*renderer:[[:space:]]*\"?NetworkManager' {NETPLAN_DIR}/*.yaml; "
            "then echo nm_renderer=yes; fi; "
            f"if ls {NETPLAN_DIR}/90-NM-*.yaml >/dev/null 2>&1; then echo nm_profiles=yes; fi; "
            f"if [ -d /etc/cloud ] || [ -e {NETPLAN_DIR}/50-cloud-init.yaml ]; then echo cloud_init=yes; fi; "
            f"if [ -f {RECOVERED_PATH} ]; then echo recovered=$(head -c 2000 {RECOVERED_PATH} | tr -d '\\n'); fi; "
            f"if [ -f {STATUS_PATH} ]; then echo last_change=$(head -c 2000 {STATUS_PATH} | tr -d '\\n'); fi; "
            "(. /etc/os-release && echo version=$VERSION_ID)"
        )

    def process(self, output):
        values = dict(line.split("=", 1) for line in output if "=" in line)
        renderer = RendererFacts(
            networkmanager_active=values.get("networkmanager") == "active",
            networkd_active=values.get("networkd") == "active",
            netplan_installed=values.get("netplan") == "yes",
            netplan_nm_renderer=values.get("nm_renderer") == "yes",
            netplan_nm_profiles=values.get("nm_profiles") == "yes",
            ubuntu_version=values.get("version") or None,
        )
        try:
            recovered = json.loads(values["recovered"]) if values.get("recovered") else None
        except ValueError:
            recovered = {"reason": "its network configuration was restored at boot (record unreadable)"}
        try:
            last = json.loads(values["last_change"]) if values.get("last_change") else None
            last_change = Status(**last) if isinstance(last, dict) else None
        except (ValueError, TypeError):
            last_change = None
        return {"renderer": renderer, "cloud_init": values.get("cloud_init") == "yes",
                "recovered": recovered if isinstance(recovered, dict) else None,
                "last_change": last_change}


class NetplanFilesConfiguring(FactBase):
    """The netplan files in /etc/netplan that configure this interface, as paths.

    netplan merges every file, so another file that sets addresses for the same
    interface (a Desktop's NetworkManager profile, an old hand-written file) would keep
    its address beside ours. Parsed on the host: the files may hold WiFi passwords,
    and only their names leave it.
    """

    default = list

    def command(self, interface: str) -> str:
        script = (
            "import glob, sys, yaml\n"
            f"for path in sorted(glob.glob({NETPLAN_DIR + '/*.yaml'!r})):\n"
            "    try:\n"
            "        network = (yaml.safe_load(open(path)) or {}).get('network') or {}\n"
            "    except Exception:\n"
            "        continue\n"
            "    if any(sys.argv[1] in (network.get(kind) or {}) for kind in ('ethernets', 'wifis')):\n"
            "        print(path)\n"
        )
        return f"python3 -c {shlex.quote(script)} {shlex.quote(interface)} 2>/dev/null || true"

    def process(self, output):
        return [line.strip() for line in output if line.strip()]


class MaskedFileContents(FactBase):
    """A file's content with WiFi passwords masked on the host, for diffs; None if absent.

    Masking happens before the content leaves the host, so not even pyinfra's
    debug output can show the old password.
    """

    def command(self, path: str) -> str:
        quoted = shlex.quote(path)
        return f"if [ -f {quoted} ]; then sed -e {shlex.quote(SED_MASK_SECRETS)} {quoted}; fi"

    def process(self, output):
        return "".join(line + "\n" for line in output)


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _is_private(file_fact) -> bool:
    return bool(file_fact) and file_fact.get("user") == "root" and file_fact.get("mode") == 600


def _print_masked_diff(path: str, new_content: str) -> None:
    old = host.get_fact(MaskedFileContents, path=path)
    new = mask_secrets(new_content)
    host.log(f"Will {'modify' if old else 'create'} {path}", logger.info)
    if old == new:
        logger.info("  (only the WiFi password changes)")
    for line in generate_color_diff((old or "").splitlines(keepends=True), new.splitlines(keepends=True)):
        logger.info("  %s", line)
    logger.info("")


@operation()
def network_in_effect(
    settings: NetworkSettings,
    current_address: str,
    roster_path: str | None = None,
):
    """
    Make the host's network configuration the one from the roster, safely.

    + settings: the host's checked network settings (``roslab.network.settings.network_settings``)
    + current_address: the address pyinfra reaches the host at now
    + roster_path: the roster file; the confirmed address is recorded beside it

    The host keeps the new configuration only if the controller reaches it at its
    new address within ``settings.confirm_timeout`` seconds; otherwise it restores
    the previous files by itself, and this operation fails the host saying so.

    **Example:**

    .. code:: python

        network_in_effect(
            name="Ensure the host has its static address from the roster",
            settings=network_settings(host_settings(host)),
            current_address="192.168.50.200",
        )
    """
    found = host.get_fact(NetworkRenderer)
    layout = _layout_for(settings, found)
    configuring = host.get_fact(NetplanFilesConfiguring, interface=settings.interface) if layout.uses_netplan else []
    wanted = desired_files(settings, layout, found["cloud_init"], tuple(configuring))

    recovered = found.get("recovered")
    if recovered:
        yield from _report_recovered(recovered, current_address)
    unfinished = network_state.pending_changes(roster_path).get(host.name) if roster_path else None
    awaiting = awaiting_confirmation(unfinished, found.get("last_change"), current_address)
    if unfinished and not recovered and not awaiting:
        _report_unfinished(unfinished, found.get("last_change"), current_address)

    changed = [path for path, content in wanted.files.items()
               if host.get_fact(Sha256File, path=path) != sha256(content)]
    leftover = [path for path in wanted.superseded if host.get_fact(File, path=path)]
    if not changed and not leftover:
        yield from _settle_unchanged(wanted, layout, unfinished, recovered, roster_path, awaiting)
        return

    if state.config.DIFF:
        _show_planned_change(wanted, changed, leftover)
    yield from _launch_change(settings, layout, wanted, current_address, roster_path)


def _layout_for(settings: NetworkSettings, found: dict):
    """The layout the host's network manager calls for; a host roslab cannot configure fails here."""
    try:
        return choose_layout(settings.backend, found["renderer"])
    except ValueError as exc:
        raise OperationError(f"{host.name}: {exc}") from None


def _report_recovered(recovered: dict, current_address: str):
    """The host restarted during an earlier change's confirmation window: the boot unit
    put the previous configuration back, so it answers where it did before. Say so, once."""
    # The record is the host's: printable characters only reach the teacher's terminal.
    said = _printable(recovered.get("reason"))
    host.log_styled(
        f"roslab: network: found at {current_address}: {said or 'an unconfirmed change was undone at boot'}",
        fg="yellow", log_func=logger.warning,
    )
    yield StringCommand("rm", "-f", RECOVERED_PATH)  # reported once


def _report_unfinished(unfinished: dict, last_change: Status | None, current_address: str) -> None:
    """A change an earlier run launched and never saw end (its controller was killed): the host
    answers here now, so say what became of it. The boot unit's record already says it when the
    host restarted (the caller skips this then); this run's own change, or change_ended, clears
    the record."""
    host.log_styled(
        f"roslab: network: found at {current_address}: "
        f"{unfinished_change_words(unfinished, last_change)}",
        fg="yellow", log_func=logger.warning,
    )


def awaiting_confirmation(unfinished: dict | None, last_change: Status | None, current_address: str) -> bool:
    """Whether this run reached the host at the new address of the change an earlier (killed)
    run launched, while the host still waits for that change's confirmation."""
    return bool(unfinished and last_change is not None and last_change.state == apply.STATE_WAITING
                and unfinished.get("token") and last_change.token == unfinished.get("token")
                and unfinished.get("to") == current_address)


def _settle_unchanged(wanted, layout, unfinished: dict | None, recovered: dict | None, roster_path: str | None,
                      awaiting: bool = False):
    """The files are in place already: only their owner or mode, or an earlier run's record, may need work."""
    loose = [path for path in wanted.files if not _is_private(host.get_fact(File, path=path))]
    for path in loose:
        # Same content, wrong owner or mode: fix in place, nothing to apply.
        yield StringCommand("chown", "root:root", path, "&&", "chmod", "0600", path)
    if awaiting:  # confirmed by this run: the host keeps the change the killed run made
        assert unfinished is not None, "awaiting a confirmation needs the unfinished run's record"
        yield FunctionCommand(confirm_pending_change, (), {"token": unfinished["token"],
                                                            "new_address": unfinished["to"],
                                                            "roster_path": roster_path})
    elif unfinished:
        yield FunctionCommand(change_ended, (), {"roster_path": roster_path})
    elif not loose and not recovered:
        host.noop(f"network configuration already in place ({layout.reason})")


def _show_planned_change(wanted, changed: list[str], leftover: list[str]) -> None:
    """pyinfra's --diff: what the change writes (WiFi passwords masked) and which files it moves aside."""
    for path in changed:
        _print_masked_diff(path, wanted.files[path])
    for path in leftover:
        host.log(f"Will move {path} aside (kept under {BACKUP_ROOT})", logger.info)


def _launch_change(settings: NetworkSettings, layout, wanted, current_address: str, roster_path: str | None):
    """Ship the plan and the apply script, stage and launch the change on the host, then confirm it
    from the controller at the address the host will answer at (or learn that it rolled back)."""
    reach_address = str(settings.address.ip) if settings.address else current_address
    plan = Plan(
        token=uuid4().hex,
        layout=layout.name,
        interface=settings.interface,
        files=tuple(wanted.files),
        superseded=wanted.superseded,
        expect_address=str(settings.address) if settings.address else None,
        gateway=str(settings.gateway) if settings.gateway else None,
        confirm_timeout=settings.confirm_timeout,
        backups_keep=settings.backups_keep,
    )

    yield StringCommand("install", "-d", "-m", "0700", RUN_DIR, "&&",
                        "install", "-d", "-m", "0755", str(Path(SCRIPT_PATH).parent))
    yield FileUploadCommand(StringIO(plan.to_json()), PLAN_PATH)
    yield FileUploadCommand(str(APPLY_SCRIPT), SCRIPT_PATH)
    # The new files (a WiFi password among them) go on the stdin of the command that stages,
    # validates and launches: 0600 root's from their first byte, and removed whatever fails.
    # A validation failure shows the validator's message and stops here, nothing changed.
    yield StringCommand("python3", SCRIPT_PATH, "start", PLAN_PATH,
                        # pyinfra reads any _stdin with readlines() (connectors.util.write_stdin); its
                        # annotation names only text and lists of it.
                        _stdin=SecretStdin(json.dumps(wanted.files)))  # type: ignore[arg-type]
    # Validated and launched (a refused change ends above): pending until confirmed or undone.
    yield FunctionCommand(
        change_started, (),
        {"old_address": current_address, "new_address": reach_address,
         "confirm_timeout": settings.confirm_timeout, "roster_path": roster_path, "token": plan.token},
    )
    yield FunctionCommand(
        confirm_network_change,
        (),
        {
            "token": plan.token,
            "new_address": reach_address,
            "old_address": current_address,
            "confirm_timeout": settings.confirm_timeout,
            "roster_path": roster_path,
        },
    )


def _printable(text, limit: int = 300) -> str:
    """A host's words for the teacher's terminal: printable characters only, bounded."""
    return "".join(char for char in str(text or "") if char.isprintable())[:limit]


def unfinished_change_words(pending: dict, last_change: Status | None) -> str:
    """What became of a change the controller launched and did not see end (its record in
    `.roslab-state/pending-network.yaml`), from the host's status file of the change."""
    said = (f"the network change started {_printable(pending.get('started'), 40) or '?'} (from "
            f"{_printable(pending.get('from'), 60) or '?'} to {_printable(pending.get('to'), 60) or '?'}) "
            "was not seen to end: the controller stopped during it; ")
    token = pending.get("token")
    if last_change is None or (token and last_change.token != token):
        return said + "the host keeps no record of how it ended (it restarted since, or the change never began)"
    message = _printable(last_change.message)
    if last_change.state == apply.STATE_ROLLED_BACK:
        return said + f"the host rolled it back by itself ({message or 'no confirmation'})"
    if last_change.state == apply.STATE_CONFIRMED:
        return said + "the host kept it (it was confirmed)"
    if last_change.state == apply.STATE_WAITING:
        return said + "the host still waits for its confirmation and restores its previous settings by itself"
    return said + f"it ended on the host as {_printable(last_change.state, 40)}" + (f": {message}" if message else "")


def network_in_effect_reads(settings: NetworkSettings) -> list:
    """What `network_in_effect` reads on a host whose network is already in place (roslab.probe).

    The files it compares depend on the layout the host is found to use, so the reads cover
    every layout's files: one probe section each, instead of a command each on every run.
    """
    wanted = [NETPLAN_FILE, keyfile_path(settings), CLOUD_INIT_DISABLE_FILE]
    reads = [read(NetworkRenderer), read(NetplanFilesConfiguring, interface=settings.interface)]
    for path in wanted:
        reads += [read(Sha256File, path=path), read(File, path=path)]
    reads.append(read(File, path=CLOUD_INIT_FILE))
    return reads
