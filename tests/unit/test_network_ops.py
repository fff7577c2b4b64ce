"""The network deploy and operation, facts in, commands out; and the controller's confirmation."""

from __future__ import annotations

import hashlib
import json
import logging
from types import SimpleNamespace

import pytest
import yaml
from pyinfra.api import FunctionCommand, StringCommand
from pyinfra.facts.files import File, Sha256File

from deploy.network import network
from roslab.network import confirm as network_confirm
from roslab.network import state as network_state
from roslab.network.apply import NETPLAN_NM, NM_KEYFILE, Plan, Status
from roslab.network.operation import MaskedFileContents, NetplanFilesConfiguring, NetworkRenderer
from roslab.network.render import RendererFacts
from roslab import settings as schema
from roslab.secrets import Secret
from fixtures.fake_host import plan

NETPLAN = "/etc/netplan/60-roslab.yaml"
CLOUD_INIT = "/etc/netplan/50-cloud-init.yaml"
DISABLE = "/etc/cloud/cloud.cfg.d/99-disable-network-config.cfg"
KEYFILE = "/etc/NetworkManager/system-connections/roslab-eth0.nmconnection"
STAGED = "/run/roslab/network/staging"
PASSWORD = "wifi-pass-1234"

SERVER_2404 = {"renderer": RendererFacts(networkd_active=True, ubuntu_version="24.04"), "cloud_init": True}
DESKTOP_2204 = {
    "renderer": RendererFacts(networkmanager_active=True, netplan_nm_renderer=True, ubuntu_version="22.04"),
    "cloud_init": False,
}

HOST_DATA = {
    "ssh_hostname": "10.0.0.200",
    "network_address": "10.0.0.11/24",
    "network_gateway": "10.0.0.1",
    "roslab_team": "team1",
}


def facts(renderer=SERVER_2404, files=None, modes=None):
    """Host facts: `files` maps path -> content present on the host."""
    files = files or {}
    modes = modes or {}

    def sha(path):
        return hashlib.sha256(files[path].encode()).hexdigest() if path in files else None

    def stat(path):
        if path not in files:
            return None
        return {"user": "root", "group": "root", "mode": modes.get(path, 600)}

    return {
        NetworkRenderer: renderer,
        Sha256File: sha,
        File: stat,
        MaskedFileContents: lambda path: files.get(path),
        # The host parses its netplan files; here a file "configures" the interface when
        # it has it under ethernets/wifis (the tests' files are simple YAML).
        NetplanFilesConfiguring: lambda interface: sorted(
            path for path, content in files.items()
            if path.startswith("/etc/netplan/") and f"\n    {interface}:" in content
        ),
    }


def run_network(data=None, **fact_args):
    return plan(network, facts(**fact_args), data={**HOST_DATA, **(data or {})})


def reaching_host(result) -> dict[str, str]:
    """What reaches the host: uploaded files, and the staged files (by their staging path)
    that the `start` command gets on its stdin."""
    out = result.uploads()
    for op in result.operations:
        for command in op.commands:
            stdin = getattr(command, "connector_arguments", {}).get("_stdin")
            if stdin is not None:
                [line] = stdin.readlines()
                out.update({STAGED + path: content for path, content in json.loads(line).items()})
    return out


def text(operation):
    """The operation's commands as text; the controller-side callback by name."""
    return [
        command.function.__name__ if isinstance(command, FunctionCommand)
        else f"upload {command.dest}" if not isinstance(command, StringCommand)
        else command.get_raw_value()
        for command in operation.commands
    ]


def the_operation(result):
    [operation] = [op for op in result.operations if op.commands]
    return operation


def test_first_run_stages_validates_and_launches_detached_apply():
    result = run_network(files={CLOUD_INIT: "network: {version: 2}\n"})
    operation = the_operation(result)
    assert operation.name.endswith("| Ensure the host's ethernet network is configured and it answers at 10.0.0.11")
    commands = text(operation)
    assert commands[0] == "install -d -m 0700 /run/roslab/network && install -d -m 0755 /usr/local/lib/roslab"
    # The new files (they may hold a WiFi password) are never uploaded: they reach the
    # host on the stdin of the command that stages them 0600, validates and launches.
    assert set(operation_uploads := result.uploads()) == {
        "/run/roslab/network/plan.json", "/usr/local/lib/roslab/network_apply.py",
    }
    start = "python3 /usr/local/lib/roslab/network_apply.py start /run/roslab/network/plan.json"
    assert start in commands
    [start_command] = [c for c in operation.commands if isinstance(c, StringCommand) and c.get_raw_value() == start]
    assert "***" in repr(start_command.connector_arguments["_stdin"])
    staged = reaching_host(result)
    assert set(staged) - set(operation_uploads) == {STAGED + NETPLAN, STAGED + DISABLE}
    assert yaml.safe_load(staged[STAGED + NETPLAN])["network"]["ethernets"]["eth0"]["addresses"] == ["10.0.0.11/24"]
    # The plan is one the on-host script accepts (Plan.from_json checks every field).
    plan_file = Plan.from_json(staged["/run/roslab/network/plan.json"])
    assert plan_file.files == (NETPLAN, DISABLE)
    assert plan_file.superseded == (CLOUD_INIT,)
    assert plan_file.expect_address == "10.0.0.11/24" and plan_file.gateway == "10.0.0.1"
    # The change runs outside the SSH session, after everything is staged.
    # Then the controller notes the change as pending (a run killed now leaves the record the next
    # run's failure names), and confirms it.
    assert commands.index(start) == len(commands) - 3
    pending = operation.commands[-2]
    assert isinstance(pending, FunctionCommand) and pending.kwargs["new_address"] == "10.0.0.11"
    confirm = operation.commands[-1]
    assert isinstance(confirm, FunctionCommand)
    assert confirm.kwargs["new_address"] == "10.0.0.11"
    assert confirm.kwargs["old_address"] == "10.0.0.200"
    assert confirm.kwargs["token"] == plan_file.token


@pytest.mark.parametrize("data, kept", [({}, 5), ({"network_backups_keep": 2}, 2)])
def test_the_roster_says_how_many_backups_the_host_keeps(data, kept):
    uploads = reaching_host(run_network(data=data, files={CLOUD_INIT: "x"}))
    assert Plan.from_json(uploads["/run/roslab/network/plan.json"]).backups_keep == kept


def test_second_run_changes_nothing():
    first = reaching_host(run_network(files={CLOUD_INIT: "x"}))
    in_place = {NETPLAN: first[STAGED + NETPLAN], DISABLE: first[STAGED + DISABLE]}
    result = run_network(files=in_place)
    assert [op.name for op in result.operations if op.commands] == []
    assert any("network configuration already in place" in noop for noop in result.noops)


@pytest.mark.parametrize("renderer", [SERVER_2404, DESKTOP_2204], ids=["netplan", "keyfile"])
def test_a_network_in_place_is_read_by_the_probe_alone(renderer):
    # Issue 11: on a no-op run the step's reads come from the host's one probe command;
    # a fact read on its own would be one more remote command per host on every run.
    from deploy.network import network_reads
    from roslab.probe import read_ahead

    first = reaching_host(run_network(renderer=renderer, files={CLOUD_INIT: "x"}))
    in_place = {path[len(STAGED):]: content for path, content in first.items() if path.startswith(STAGED)}

    def probed_then_network():
        read_ahead(network_reads())
        network()

    result = plan(probed_then_network, facts(renderer=renderer, files=in_place),
                  data={**schema.defaults("network"), **HOST_DATA})
    assert [op.name for op in result.operations if op.commands] == []
    assert result.facts_asked == ["HostProbe"]


def test_leftover_cloud_init_file_alone_triggers_a_change():
    first = reaching_host(run_network(files={CLOUD_INIT: "x"}))
    files = {NETPLAN: first[STAGED + NETPLAN], DISABLE: first[STAGED + DISABLE], CLOUD_INIT: "x"}
    assert Plan.from_json(reaching_host(run_network(files=files))["/run/roslab/network/plan.json"]).superseded == (CLOUD_INIT,)


def test_other_netplan_files_for_the_interface_are_superseded_not_merged():
    # netplan merges files: a Desktop profile that sets eth0's old address would keep
    # that address beside the new one. A file that only names the renderer stays.
    desktop_2404 = {
        "renderer": RendererFacts(
            networkmanager_active=True, netplan_installed=True, netplan_nm_renderer=True,
            ubuntu_version="24.04",
        ),
        "cloud_init": False,
    }
    files = {
        "/etc/netplan/01-network-manager-all.yaml": "network:\n  renderer: NetworkManager\n",
        "/etc/netplan/90-NM-1234.yaml": "network:\n  ethernets:\n    eth0:\n      addresses: [10.0.0.200/24]\n",
    }
    plan_file = Plan.from_json(
        reaching_host(run_network(renderer=desktop_2404, files=files))["/run/roslab/network/plan.json"]
    )
    assert plan_file.layout == NETPLAN_NM
    assert plan_file.superseded == ("/etc/netplan/90-NM-1234.yaml",)


def test_same_content_wrong_mode_is_fixed_without_applying():
    first = reaching_host(run_network(files={CLOUD_INIT: "x"}))
    files = {NETPLAN: first[STAGED + NETPLAN], DISABLE: first[STAGED + DISABLE]}
    result = run_network(files=files, modes={NETPLAN: 644})
    assert text(the_operation(result)) == [f"chown root:root {NETPLAN} && chmod 0600 {NETPLAN}"]


def test_desktop_2204_gets_a_networkmanager_keyfile():
    result = run_network(renderer=DESKTOP_2204)
    uploads = reaching_host(result)
    assert STAGED + KEYFILE in uploads and STAGED + NETPLAN not in uploads
    assert "address1=10.0.0.11/24,10.0.0.1" in uploads[STAGED + KEYFILE]
    assert Plan.from_json(uploads["/run/roslab/network/plan.json"]).layout == NM_KEYFILE


def test_host_without_network_address_is_left_alone():
    result = run_network(data={"network_address": None})
    assert result.operations == [] and not result.failed


def test_network_disabled_does_nothing():
    result = run_network(data={"network_enabled": False})
    assert result.operations == [] and not result.failed


def test_bad_setting_stops_only_this_host_naming_host_team_and_field(monkeypatch):
    stopped = []
    monkeypatch.setattr("deploy.network.stop_host", stopped.append)
    result = run_network(data={"network_gateway": "10.9.9.1"})
    assert result.operations == []
    [error] = stopped
    assert "host pi (team team1)" in error
    assert "field 'network_gateway'" in error and "outside the subnet 10.0.0.0/24" in error


WIFI = {
    "network_kind": "wifi",
    "wifi_ssid": "robolab",
    "wifi_password_secret": "lab_wifi",
    "wifi_password": Secret(PASSWORD),
}


def test_wifi_password_only_in_the_staged_file_never_in_commands_or_plan():
    result = run_network(data=WIFI)
    operation = the_operation(result)
    uploads = reaching_host(result)
    assert PASSWORD in uploads[STAGED + NETPLAN]
    assert PASSWORD not in uploads["/run/roslab/network/plan.json"]
    for command in operation.commands:
        if isinstance(command, StringCommand):
            assert PASSWORD not in command.get_raw_value()
        if isinstance(command, FunctionCommand):
            assert PASSWORD not in repr(command)


def test_diff_shows_the_change_with_the_password_masked(caplog):
    old = "network:\n  wifis:\n    wlan0:\n      access-points:\n        robolab:\n          password: ********\n"
    with caplog.at_level(logging.INFO, logger="pyinfra"):
        plan(network, facts(files={NETPLAN: old}), data={**HOST_DATA, **WIFI}, diff=True)
    printed = caplog.text
    assert "60-roslab.yaml" in printed
    assert '+         - "10.0.0.11/24"' in printed
    assert "********" in printed
    assert PASSWORD not in printed


# The controller's side: confirm at the new address, or report the rollback.


class FakeConnector:
    """pyinfra's SSH connector for a host that answers at `reachable` addresses."""

    def __init__(self, reachable, statuses):
        self.data = {"ssh_hostname": "10.0.0.200"}
        self.client = SimpleNamespace(close=lambda: None)
        self.reachable = reachable
        self.statuses = statuses
        self.connected_at = []

    def disconnect(self):
        pass

    def connect(self):
        address = self.data["ssh_hostname"]
        if not self.reachable(address):
            raise network_confirm.ConnectError(f"no route to {address}")
        self.connected_at.append(address)
        self.client = SimpleNamespace(close=lambda: None)


class FakeHost:
    name = "team1-main"

    def __init__(self, connector):
        self.connector = connector
        self.commands = []
        self.messages = []

    def run_shell_command(self, command, **arguments):
        text = command.get_raw_value()
        self.commands.append((self.connector.data["ssh_hostname"], text))
        if text.startswith("cat "):
            status = self.connector.statuses(self.connector.data["ssh_hostname"], self.commands)
            return status is not None, SimpleNamespace(stdout=json.dumps(status))
        return True, SimpleNamespace(stdout="")

    def log_styled(self, message, **kwargs):
        self.messages.append(message)


@pytest.fixture
def quick(monkeypatch):
    monkeypatch.setattr(network_confirm, "ROLLBACK_GRACE", 2)
    monkeypatch.setattr(network_confirm, "OLD_ADDRESS_PROBE_INTERVAL", 0)
    monkeypatch.setattr(network_confirm.time, "sleep", lambda seconds: None)
    monkeypatch.setattr(network_confirm, "op_connector_arguments", lambda state, host: {"_sudo": True})


def confirm(host, tmp_path, timeout=1):
    return network_confirm.confirm_network_change(
        None, host, token="t0k", new_address="10.0.0.11", old_address="10.0.0.200",
        confirm_timeout=timeout, roster_path=str(tmp_path / "roster.yaml"),
    )


def test_confirmation_moves_the_connection_and_records_the_address(quick, tmp_path):
    def statuses(address, commands):
        confirmed = any(text.endswith("/run/roslab/network/confirmed") for _, text in commands)
        state = "confirmed" if confirmed else "waiting-for-confirmation"
        return {"token": "t0k", "state": state, "backup": "/var/backups/roslab/network/x"}

    connector = FakeConnector(lambda address: address == "10.0.0.11", statuses)
    host = FakeHost(connector)
    assert confirm(host, tmp_path) is True
    assert connector.data["ssh_hostname"] == "10.0.0.11"
    assert ("10.0.0.11", "printf %s t0k > /run/roslab/network/confirmed") in host.commands
    assert network_state.last_known_address(tmp_path / "roster.yaml", "team1-main") == "10.0.0.11"
    assert "confirmed: reachable at 10.0.0.11" in host.messages[-1]


def test_unreachable_new_address_reports_the_rollback_at_the_old_address(quick, tmp_path):
    def statuses(address, commands):
        return {"token": "t0k", "state": "rolled-back",
                "message": "the controller did not confirm within 1 s"}

    connector = FakeConnector(lambda address: address == "10.0.0.200", statuses)
    host = FakeHost(connector)
    assert confirm(host, tmp_path) is False
    assert connector.data["ssh_hostname"] == "10.0.0.200"
    assert not any(text.startswith("printf") for _, text in host.commands)
    assert host.messages[-1].startswith("Network change rolled back: the controller did not confirm")
    assert "reachable again at 10.0.0.200" in host.messages[-1]
    assert network_state.last_known_address(tmp_path / "roster.yaml", "team1-main") is None


def test_status_of_an_earlier_run_is_not_mistaken_for_this_one(quick, tmp_path):
    connector = FakeConnector(
        lambda address: address == "10.0.0.200",
        lambda address, commands: {"token": "older", "state": "rolled-back", "message": "old news"},
    )
    host = FakeHost(connector)
    assert confirm(host, tmp_path) is False
    assert "old news" not in host.messages[-1]


def test_host_gone_everywhere_says_where_to_look(quick, tmp_path):
    host = FakeHost(FakeConnector(lambda address: False, lambda address, commands: None))
    assert confirm(host, tmp_path) is False
    assert "does not answer at 10.0.0.200 either" in host.messages[-1]
    assert "journalctl -u roslab-network-apply" in host.messages[-1]


def test_host_that_gives_up_by_itself_is_reported_without_a_confirmation(quick, tmp_path):
    def statuses(address, commands):
        return {"token": "t0k", "state": "rolled-back",
                "message": "gateway 10.0.0.254 does not answer on eth0"}

    connector = FakeConnector(lambda address: True, statuses)
    host = FakeHost(connector)
    assert confirm(host, tmp_path, timeout=30) is False
    assert not any(text.startswith("printf") for _, text in host.commands)
    assert connector.data["ssh_hostname"] == "10.0.0.200"
    assert "rolled back: gateway 10.0.0.254 does not answer on eth0" in host.messages[-1]


def test_a_change_undone_at_boot_is_reported_once_in_one_printable_line(caplog):
    record = {"token": "t", "reason": "the host restarted before the network change of X was confirmed\x1b[2J"}
    renderer = {**SERVER_2404, "recovered": record}
    with caplog.at_level(logging.WARNING):
        result = run_network(renderer=renderer, files={CLOUD_INIT: "x"})
    (line,) = {r.getMessage() for r in caplog.records if "found at" in r.getMessage()}
    assert "roslab: network: found at 10.0.0.200: the host restarted before the network change of X" in line
    assert "\x1b[2J" not in line
    commands = text(the_operation(result))
    assert commands[0] == "rm -f /var/lib/roslab/network/recovered.json"


def test_a_started_change_is_pending_until_it_ends_and_stays_pending_when_the_host_is_gone(quick, tmp_path):
    roster = tmp_path / "roster.yaml"

    def started():
        network_confirm.change_started(None, FakeHost(None), old_address="10.0.0.200", new_address="10.0.0.11",
                                       confirm_timeout=1, roster_path=str(roster))
        assert network_state.pending_changes(roster)["team1-main"]["to"] == "10.0.0.11"

    started()
    gone = FakeHost(FakeConnector(lambda address: False, lambda address, commands: None))
    assert confirm(gone, tmp_path) is False
    assert "team1-main" in network_state.pending_changes(roster)  # the next run's failure names it

    def rolled_back(address, commands):
        return {"token": "t0k", "state": "rolled-back", "message": "not confirmed"}

    started()
    assert confirm(FakeHost(FakeConnector(lambda address: address == "10.0.0.200", rolled_back)), tmp_path) is False
    assert network_state.pending_changes(roster) == {}


# A controller killed during a change (issue 28): the next run that finds the host says what
# became of the change, from the host's own status file, and then goes on.

def pending_from_a_killed_run(tmp_path, token="t0k") -> str:
    roster = tmp_path / "roster.yaml"
    network_state.record_pending(roster, "pi", "10.0.0.200", "10.0.0.11", 40, "2026-11-26 10:00:00 UTC",
                                 token=token)
    return str(roster)


def found_lines(caplog) -> list[str]:
    """The distinct "found at" lines (the harness runs an operation's body to plan and to execute)."""
    return sorted({record.getMessage() for record in caplog.records if "found at" in record.getMessage()})


@pytest.mark.parametrize("last_change, words", [
    (Status("t0k", "rolled-back", "the controller did not confirm within 40 s"),
     "the host rolled it back by itself (the controller did not confirm within 40 s)"),
    (Status("t0k", "confirmed"), "the host kept it (it was confirmed)"),
    (Status("t0k", "waiting-for-confirmation"), "the host still waits for its confirmation"),
    (Status("t0k", "rollback-failed", "netplan apply failed\x1b[2J"),
     "it ended on the host as rollback-failed: netplan apply failed[2J"),
    (Status("an-earlier-run", "rolled-back", "not this change"), "the host keeps no record of how it ended"),
    (None, "the host keeps no record of how it ended (it restarted since"),
])
def test_a_change_whose_controller_was_killed_is_named_once_with_what_the_host_says(
        caplog, tmp_path, last_change, words):
    roster = pending_from_a_killed_run(tmp_path)
    with caplog.at_level(logging.WARNING):
        result = run_network(data={"roslab_roster_path": roster}, renderer={**SERVER_2404, "last_change": last_change},
                             files={CLOUD_INIT: "network: {version: 2}\n"})
    (line,) = found_lines(caplog)
    assert ("roslab: network: found at 10.0.0.200: the network change started 2026-11-26 10:00:00 UTC (from "
            "10.0.0.200 to 10.0.0.11) was not seen to end: the controller stopped during it; ") in line
    assert words in line and "\x1b" not in line
    # and the change is made again: a new record (its own token) replaces the old one when it starts
    operation = the_operation(result)
    [started] = [command for command in operation.commands
                 if isinstance(command, FunctionCommand) and command.function.__name__ == "change_started"]
    assert started.kwargs["token"] and started.kwargs["token"] != "t0k"
    started.function(None, SimpleNamespace(name="pi"), *started.args, **started.kwargs)
    assert network_state.pending_changes(roster)["pi"]["token"] == started.kwargs["token"]


def test_a_killed_runs_change_the_host_kept_is_named_then_cleared_and_the_next_run_is_a_noop(caplog, tmp_path):
    roster = pending_from_a_killed_run(tmp_path)
    in_place = {path: content for path, content in reaching_host(run_network()).items() if path.startswith(STAGED)}
    files = {path[len(STAGED):]: content for path, content in in_place.items()}
    renderer = {**SERVER_2404, "last_change": Status("t0k", "confirmed")}
    with caplog.at_level(logging.WARNING):
        result = run_network(data={"roslab_roster_path": roster}, renderer=renderer, files=files)
    (line,) = found_lines(caplog)
    assert "the host kept it (it was confirmed)" in line
    operation = the_operation(result)
    assert text(operation) == ["change_ended"]  # nothing reaches the host
    [ended] = operation.commands
    ended.function(None, SimpleNamespace(name="pi"), *ended.args, **ended.kwargs)
    assert network_state.pending_changes(roster) == {}
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        again = run_network(data={"roslab_roster_path": roster}, renderer=renderer, files=files)
    assert found_lines(caplog) == [] and [op for op in again.operations if op.commands] == []


def test_a_rerun_in_a_killed_runs_confirmation_window_reaching_the_new_address_confirms_the_change(caplog, tmp_path):
    roster = pending_from_a_killed_run(tmp_path)
    in_place = {path: content for path, content in reaching_host(run_network()).items() if path.startswith(STAGED)}
    files = {path[len(STAGED):]: content for path, content in in_place.items()}
    renderer = {**SERVER_2404, "last_change": Status("t0k", "waiting-for-confirmation")}
    with caplog.at_level(logging.WARNING):
        result = run_network(data={"roslab_roster_path": roster, "ssh_hostname": "10.0.0.11"},
                             renderer=renderer, files=files)
    assert found_lines(caplog) == []  # the confirmation says what happened, once it is known
    operation = the_operation(result)
    assert text(operation) == ["confirm_pending_change"]
    [confirm] = operation.commands
    assert confirm.kwargs == {"token": "t0k", "new_address": "10.0.0.11", "roster_path": roster}
    # At the old address (not the change's), or for another change, the host is not confirmed.
    for address, token in (("10.0.0.200", "t0k"), ("10.0.0.11", "another")):
        renderer = {**SERVER_2404, "last_change": Status(token, "waiting-for-confirmation")}
        other = run_network(data={"roslab_roster_path": roster, "ssh_hostname": address}, renderer=renderer,
                            files=files)
        assert "confirm_pending_change" not in [name for op in other.operations for name in text(op)]


def test_the_inventory_reaches_a_host_in_a_killed_runs_change_where_it_answers():
    from roslab.network.state import address_during_change

    pending = {"from": "10.0.0.200", "to": "10.0.0.11"}
    asked = []

    def answering(*up):
        return lambda address, port: asked.append(address) or address in up

    assert address_during_change("10.0.0.200", pending, 22, answering("10.0.0.11")) == "10.0.0.11"
    assert address_during_change("10.0.0.200", pending, 22, answering("10.0.0.200")) == "10.0.0.200"
    assert address_during_change("10.0.0.200", pending, 22, answering()) == "10.0.0.200"  # its line names it
    asked.clear()
    assert address_during_change("10.0.0.200", None, 22, answering()) == "10.0.0.200" and asked == []


def test_the_hosts_status_of_its_last_change_is_read_with_the_renderer():
    fact = NetworkRenderer()
    assert "/run/roslab/network/status.json" in fact.command()
    status = json.dumps({"token": "t0k", "state": "rolled-back", "message": "m", "backup": None})
    assert fact.process(["networkd=active", f"last_change={status}"])["last_change"] == Status(
        "t0k", "rolled-back", "m", None)
    for garbage in ("{", "[]", '{"token": "t", "unknown": 1}'):
        assert fact.process(["networkd=active", f"last_change={garbage}"])["last_change"] is None
    assert fact.process(["networkd=active"])["last_change"] is None
