"""The on-host apply/rollback script, on files in a temporary directory.

The commands that touch the real network (netplan, networkctl, nmcli, ip) are
replaced by recorders; everything about files, backups, confirmation and
rollback runs for real.
"""

from __future__ import annotations

import json
import stat
import subprocess
import threading
import time
from pathlib import Path

import pytest

from roslab import network_apply

TOKEN = "0123456789abcdef"


@pytest.fixture
def host(tmp_path):
    """A fake host filesystem: an old cloud-init netplan file, a staged new one."""
    etc_netplan = tmp_path / "etc/netplan"
    etc_netplan.mkdir(parents=True)
    (etc_netplan / "50-cloud-init.yaml").write_text("old: dhcp\n")
    (etc_netplan / "01-keep.yaml").write_text("keep: me\n")
    run_dir = tmp_path / "run/roslab/network"
    new_file = str(etc_netplan / "60-roslab.yaml")
    disable_file = str(tmp_path / "etc/cloud/cloud.cfg.d/99-disable-network-config.cfg")
    plan = {
        "token": TOKEN,
        "layout": "netplan-networkd",
        "interface": "eth0",
        "netplan_dir": str(etc_netplan),
        "files": [new_file, disable_file],
        "superseded": [str(etc_netplan / "50-cloud-init.yaml")],
        "expect_address": "10.0.0.5/24",
        "gateway": "10.0.0.1",
        "confirm_timeout": 1,
        "backup_root": str(tmp_path / "var/backups/roslab/network"),
        "run_dir": str(run_dir),
    }
    for target, content in ((new_file, "new: static\n"), (disable_file, "network: {config: disabled}\n")):
        staged = network_apply.staged_path(plan, target)
        staged.parent.mkdir(parents=True, exist_ok=True)
        staged.write_text(content)
    return plan


@pytest.fixture
def network(monkeypatch):
    """Stand-ins for the commands that change the network; records what ran."""
    calls = {"apply": 0, "check": 0, "check_error": None}

    def apply_files(plan):
        calls["apply"] += 1

    def check_running(plan, wait):
        calls["check"] += 1
        if calls["check_error"]:
            raise network_apply.ApplyError(calls["check_error"])

    monkeypatch.setattr(network_apply, "apply_files", apply_files)
    monkeypatch.setattr(network_apply, "check_running", check_running)
    return calls


def status(plan):
    return json.loads((Path(plan["run_dir"]) / "status.json").read_text())


def confirm_soon(plan, token=TOKEN):
    def write():
        time.sleep(0.2)
        Path(plan["run_dir"], "confirmed").write_text(token)

    thread = threading.Thread(target=write)
    thread.start()
    return thread


def test_confirmed_change_keeps_new_files_and_backs_up_cloud_init(host, network):
    confirm_soon(host)
    assert network_apply.apply(host) == 0

    new_file, disable_file = map(Path, host["files"])
    assert new_file.read_text() == "new: static\n"
    assert stat.S_IMODE(new_file.stat().st_mode) == 0o600
    assert stat.S_IMODE(Path(disable_file).stat().st_mode) == 0o600
    assert not Path(host["superseded"][0]).exists()
    assert Path(host["netplan_dir"], "01-keep.yaml").exists()

    result = status(host)
    assert result["state"] == "confirmed"
    backup = Path(result["backup"])
    assert (backup / "files" / host["superseded"][0].lstrip("/")).read_text() == "old: dhcp\n"
    assert stat.S_IMODE(backup.stat().st_mode) == 0o700
    assert network["apply"] == 1


def test_no_confirmation_restores_every_file_and_reapplies(host, network):
    assert network_apply.apply(host) == 1

    assert Path(host["superseded"][0]).read_text() == "old: dhcp\n"
    for created in host["files"]:
        assert not Path(created).exists()
    result = status(host)
    assert result["state"] == "rolled-back"
    assert "did not confirm within 1 s" in result["message"]
    assert network["apply"] == 2  # the new configuration, then the old one again


def test_stale_or_foreign_confirmation_does_not_count(host, network):
    Path(host["run_dir"]).mkdir(parents=True, exist_ok=True)
    Path(host["run_dir"], "confirmed").write_text(TOKEN)  # left from an earlier run: removed first
    confirm_soon(host, token="another-run")
    assert network_apply.apply(host) == 1
    assert status(host)["state"] == "rolled-back"


def test_gateway_failure_rolls_back_at_once(host, network):
    network["check_error"] = "gateway 10.0.0.254 does not answer on eth0"
    host["confirm_timeout"] = 30
    started = time.monotonic()
    assert network_apply.apply(host) == 1
    assert time.monotonic() - started < 5
    result = status(host)
    assert result == {**result, "state": "rolled-back", "message": network["check_error"]}
    assert Path(host["superseded"][0]).read_text() == "old: dhcp\n"


def test_existing_file_is_restored_with_its_content_and_mode(host, network):
    replaced = Path(host["files"][0])
    replaced.write_text("previous roslab config\n")
    replaced.chmod(0o600)
    assert network_apply.apply(host) == 1
    assert replaced.read_text() == "previous roslab config\n"
    assert stat.S_IMODE(replaced.stat().st_mode) == 0o600


def test_failing_rollback_is_reported(host, network, monkeypatch):
    def broken_restore(plan, backup_dir):
        raise OSError("disk full")

    monkeypatch.setattr(network_apply, "restore", broken_restore)
    assert network_apply.apply(host) == 2
    assert status(host)["state"] == "rollback-failed"
    assert "disk full" in status(host)["message"]


def test_validation_root_has_the_future_netplan_directory(host):
    root = network_apply.validation_root(host)
    staged = root / host["netplan_dir"].lstrip("/")
    assert sorted(p.name for p in staged.iterdir()) == ["01-keep.yaml", "60-roslab.yaml"]


def test_validation_reports_netplan_message_without_staging_path(host, monkeypatch):
    def fake_run(command, timeout=60):
        root = command[-1]
        return subprocess.CompletedProcess(
            command, 1, "", f"{root}/etc/netplan/60-roslab.yaml:7:7: Error: unknown key 'adresses'\n"
        )

    monkeypatch.setattr(network_apply, "run", fake_run)
    [problem] = network_apply.validate(host)
    assert "unknown key 'adresses'" in problem
    assert problem.startswith("netplan generate rejected the new configuration")
    assert "/validate" not in problem


def test_apply_falls_back_from_netplan_apply_to_generate_and_networkctl(monkeypatch):
    ran = []

    def fake_run(command, timeout=60):
        ran.append(command)
        failed = command == ["netplan", "apply"]
        return subprocess.CompletedProcess(command, 1 if failed else 0, "", "udevadm trigger failed")

    monkeypatch.setattr(network_apply, "run", fake_run)
    network_apply.apply_files({"layout": "netplan-networkd", "interface": "eth0"})
    assert ran == [
        ["netplan", "apply"],
        ["netplan", "generate"],
        ["networkctl", "reload"],
        ["networkctl", "reconfigure", "eth0"],
    ]


def test_apply_error_names_each_failing_command(monkeypatch):
    def fake_run(command, timeout=60):
        failed = command[0] in ("netplan", "networkctl") and command[1] != "generate"
        failed = failed or command[0] == "systemctl"
        return subprocess.CompletedProcess(command, 1 if failed else 0, "", f"{command[0]} failed")

    monkeypatch.setattr(network_apply, "run", fake_run)
    with pytest.raises(network_apply.ApplyError) as caught:
        network_apply.apply_files({"layout": "netplan-networkd", "interface": "eth0"})
    assert str(caught.value) == (
        "could not apply the configuration: netplan apply: netplan failed; "
        "networkctl reload: networkctl failed; "
        "systemctl restart systemd-networkd: systemctl failed"
    )


def test_keyfile_layout_reloads_networkmanager_or_restarts_it():
    commands = network_apply.apply_commands({"layout": "networkmanager-keyfile", "interface": "wlan0"})
    assert commands == [
        [["nmcli", "connection", "reload"], ["nmcli", "device", "connect", "wlan0"]],
        [["systemctl", "restart", "NetworkManager"], ["nmcli", "--wait", "20", "device", "connect", "wlan0"]],
    ]


def test_netplan_networkmanager_fallback_restarts_networkmanager_that_netplan_apply_stopped():
    # Seen in the sandbox: `netplan apply` stops NetworkManager, its udev trigger fails, and
    # a fallback that only ran `nmcli connection reload` left the host with no address.
    commands = network_apply.apply_commands({"layout": "netplan-networkmanager", "interface": "eth0"})
    assert commands == [
        [["netplan", "apply"]],
        [["netplan", "generate"], ["systemctl", "restart", "NetworkManager"],
         ["nmcli", "--wait", "20", "device", "connect", "eth0"]],
    ]


def test_check_running_waits_for_the_address(monkeypatch):
    monkeypatch.setattr(network_apply, "interface_addresses", lambda interface: ["10.0.0.9/24"])
    plan = {"interface": "eth0", "expect_address": "10.0.0.5/24", "gateway": None}
    with pytest.raises(network_apply.ApplyError, match="eth0 did not get 10.0.0.5/24"):
        network_apply.check_running(plan, wait=0.2)


def test_usage_error_for_unknown_command(capsys):
    assert network_apply.main(["network_apply.py", "launch", "plan.json"]) == 64
