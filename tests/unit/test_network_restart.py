"""A host that restarts (a power cut) before its network change is confirmed comes back on
its previous configuration: the pending record is persistent and the boot unit undoes the change.
Also: the new files are staged root's and 0600 from their first byte, and never left behind."""

from __future__ import annotations

import io
import json
import os
import stat
from pathlib import Path

import pytest

from roslab.network import apply as network_apply
from roslab.network.apply import BOOT_UNIT, PENDING_FILE, RECOVERED_FILE, STATE_CONFIRMED, STATE_ROLLED_BACK

from test_network_apply import TOKEN, confirm_soon, host, network, status  # noqa: F401 (fixtures)


def restart(plan):
    """What the boot unit runs after a power cut (/run is empty again)."""
    import shutil

    shutil.rmtree(plan.run_dir, ignore_errors=True)
    return network_apply.main(["network_apply.py", "recover", plan.state_dir])


def applied_not_confirmed(plan):
    """apply() as far as the power cut lets it get: backed up, armed, installed."""
    backup_dir = network_apply.backup(plan)
    network_apply.arm_boot_rollback(plan, backup_dir)
    network_apply.install(plan)
    return backup_dir


def test_a_restart_before_the_confirmation_restores_the_previous_files(host, monkeypatch):
    generated = []
    monkeypatch.setattr(network_apply, "run",
                        lambda command, timeout=60: generated.append(command) or
                        network_apply.subprocess.CompletedProcess(command, 0, "", ""))
    new_file, disable_file = host.files
    [cloud_init] = host.superseded
    applied_not_confirmed(host)
    assert Path(new_file).exists() and not Path(cloud_init).exists()
    pending = Path(host.state_dir) / PENDING_FILE
    assert stat.S_IMODE(pending.stat().st_mode) == 0o600

    assert restart(host) == 0
    assert Path(cloud_init).read_text() == "old: dhcp\n"
    assert not Path(new_file).exists() and not Path(disable_file).exists()
    assert generated == [["netplan", "generate"]]  # before the renderer starts, from the old files
    assert not pending.exists()
    recovered = json.loads((Path(host.state_dir) / RECOVERED_FILE).read_text())
    assert recovered["token"] == TOKEN and "restarted before the network change" in recovered["reason"]
    # A controller still waiting for this change reads that it was rolled back.
    assert status(host).state == STATE_ROLLED_BACK
    assert restart(host) == 0  # nothing pending any more: the unit does nothing


def test_the_boot_unit_is_enabled_and_runs_before_the_network(host):
    applied_not_confirmed(host)
    unit = Path(host.systemd_dir) / f"{BOOT_UNIT}.service"
    text = unit.read_text()
    assert f"ConditionPathExists={host.state_dir}/{PENDING_FILE}" in text
    assert f"ExecStart=/usr/bin/python3 {host.script_path} recover {host.state_dir}" in text
    assert "DefaultDependencies=no" in text and "Before=sysinit.target network-pre.target systemd-networkd" in text
    wants = Path(host.systemd_dir) / "sysinit.target.wants" / unit.name
    assert os.readlink(wants) == str(unit)


def test_a_confirmed_change_is_no_longer_pending(host, network):
    confirm_soon(host)
    assert network_apply.apply(host) == 0
    assert status(host).state == STATE_CONFIRMED
    assert not (Path(host.state_dir) / PENDING_FILE).exists()
    assert restart(host) == 0
    assert Path(host.files[0]).read_text() == "new: static\n"  # a later restart keeps it


def test_a_rolled_back_change_is_no_longer_pending_and_leaves_no_staged_file(host, network):
    assert network_apply.apply(host) == 1
    assert not (Path(host.state_dir) / PENDING_FILE).exists()
    assert not (Path(host.run_dir) / "staging").exists()


def test_start_stages_private_files_validates_and_launches(host, monkeypatch, tmp_path):
    ran = []

    def fake_run(command, timeout=60):
        ran.append(command)
        return network_apply.subprocess.CompletedProcess(command, 0, "", "")

    monkeypatch.setattr(network_apply, "run", fake_run)
    seen_modes = []
    real_write = network_apply._write_private

    def watching(path, data, mode=0o600):
        real_write(path, data, mode)
        seen_modes.append(stat.S_IMODE(path.stat().st_mode))

    monkeypatch.setattr(network_apply, "_write_private", watching)
    files = {target: f"secret for {target}\n" for target in host.files}
    assert network_apply.start(host, "/plan.json", io.StringIO(json.dumps(files))) == 0
    assert seen_modes == [0o600, 0o600]
    for target in host.files:
        assert network_apply.staged_path(host, target).read_text() == files[target]
    assert any(command[0] == "systemd-run" and command[-2:] == ["apply", "/plan.json"] for command in ran)


@pytest.mark.parametrize("problem", ["validation", "launch", "garbage"])
def test_start_leaves_no_staged_file_when_it_stops(host, monkeypatch, problem):
    def fake_run(command, timeout=60):
        failing = (problem == "validation" and command[0] == "netplan") or \
                  (problem == "launch" and command[0] == "systemd-run")
        return network_apply.subprocess.CompletedProcess(command, 1 if failing else 0, "", "no")

    monkeypatch.setattr(network_apply, "run", fake_run)
    import shutil

    shutil.rmtree(Path(host.run_dir) / "staging")
    files = json.dumps({target: "wifi password\n" for target in host.files})
    stdin = io.StringIO(files[:-5] if problem == "garbage" else files)
    assert network_apply.start(host, "/plan.json", stdin) != 0
    assert not (Path(host.run_dir) / "staging").exists()
    assert not (Path(host.run_dir) / "validate").exists()
