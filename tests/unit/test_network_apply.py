"""The on-host apply/rollback script, on files in a temporary directory.

The commands that touch the real network (netplan, networkctl, nmcli, ip) are
replaced by recorders; everything about files, backups, confirmation and
rollback runs for real.
"""

from __future__ import annotations

import ast
import dataclasses
import json
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from roslab.network import apply as network_apply
from roslab.network.apply import NETPLAN_NETWORKD, NETPLAN_NM, NM_KEYFILE, Plan, Status

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
    plan = Plan(
        token=TOKEN,
        layout=NETPLAN_NETWORKD,
        interface="eth0",
        netplan_dir=str(etc_netplan),
        files=[new_file, disable_file],
        superseded=[str(etc_netplan / "50-cloud-init.yaml")],
        expect_address="10.0.0.5/24",
        gateway="10.0.0.1",
        confirm_timeout=1,
        backup_root=str(tmp_path / "var/backups/roslab/network"),
        run_dir=str(run_dir),
        state_dir=str(tmp_path / "var/lib/roslab/network"),
        systemd_dir=str(tmp_path / "etc/systemd/system"),
        script_path=str(tmp_path / "usr/local/lib/roslab/network_apply.py"),
    )
    Path(plan.script_path).parent.mkdir(parents=True)
    Path(plan.script_path).write_text("# the script's persistent copy\n")
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


def status(plan) -> Status:
    found = Status.from_json((Path(plan.run_dir) / "status.json").read_text(), plan.token)
    assert found is not None
    return found


def small_plan(layout=NETPLAN_NETWORKD, interface="eth0", **changes) -> Plan:
    fields = {"files": [], "superseded": [], "expect_address": None, "gateway": None, "confirm_timeout": 10}
    return Plan(token=TOKEN, layout=layout, interface=interface, **{**fields, **changes})


def confirm_soon(plan, token=TOKEN):
    def write():
        time.sleep(0.2)
        Path(plan.run_dir, "confirmed").write_text(token)

    thread = threading.Thread(target=write)
    thread.start()
    return thread


def test_confirmed_change_keeps_new_files_and_backs_up_cloud_init(host, network):
    confirm_soon(host)
    assert network_apply.apply(host) == 0

    new_file, disable_file = map(Path, host.files)
    assert new_file.read_text() == "new: static\n"
    assert stat.S_IMODE(new_file.stat().st_mode) == 0o600
    assert stat.S_IMODE(Path(disable_file).stat().st_mode) == 0o600
    assert not Path(host.superseded[0]).exists()
    assert Path(host.netplan_dir, "01-keep.yaml").exists()

    result = status(host)
    assert result.state == "confirmed"
    backup = Path(result.backup)
    assert (backup / "files" / host.superseded[0].lstrip("/")).read_text() == "old: dhcp\n"
    assert stat.S_IMODE(backup.stat().st_mode) == 0o700
    assert network["apply"] == 1


def test_no_confirmation_restores_every_file_and_reapplies(host, network):
    assert network_apply.apply(host) == 1

    assert Path(host.superseded[0]).read_text() == "old: dhcp\n"
    for created in host.files:
        assert not Path(created).exists()
    result = status(host)
    assert result.state == "rolled-back"
    assert "did not confirm within 1 s" in result.message
    assert network["apply"] == 2  # the new configuration, then the old one again


def test_stale_or_foreign_confirmation_does_not_count(host, network):
    Path(host.run_dir).mkdir(parents=True, exist_ok=True)
    Path(host.run_dir, "confirmed").write_text(TOKEN)  # left from an earlier run: removed first
    confirm_soon(host, token="another-run")
    assert network_apply.apply(host) == 1
    assert status(host).state == "rolled-back"


def old_backups(plan, count: int) -> list[Path]:
    """Backup directories of `count` earlier runs, oldest first, as backup() names them."""
    root = Path(plan.backup_root)
    made = []
    for day in range(1, count + 1):
        directory = root / f"202601{day:02d}T120000-run{day:05d}"
        (directory / "files").mkdir(parents=True)
        (directory / "manifest.json").write_text("{}")
        made.append(directory)
    return made


def test_backups_are_pruned_to_the_newest_few_this_runs_included(host, network):
    earlier = old_backups(host, 6)
    foreign = Path(host.backup_root) / "keep-me"  # not a backup of ours: never counted or removed
    foreign.mkdir()
    plan = dataclasses.replace(host, backups_keep=3)
    confirm_soon(plan)
    assert network_apply.apply(plan) == 0

    current = Path(status(plan).backup)
    left = sorted(path.name for path in Path(plan.backup_root).iterdir())
    assert left == sorted([earlier[-2].name, earlier[-1].name, current.name, "keep-me"])
    assert (current / "files" / plan.superseded[0].lstrip("/")).read_text() == "old: dhcp\n"


def test_a_rolled_back_change_keeps_its_backup_when_pruning(host, network):
    old_backups(host, 2)
    plan = dataclasses.replace(host, backups_keep=1)
    assert network_apply.apply(plan) == 1  # no confirmation: rolled back from this run's backup

    result = status(plan)
    assert result.state == "rolled-back"
    assert [path.name for path in Path(plan.backup_root).iterdir()] == [Path(result.backup).name]
    assert Path(plan.superseded[0]).read_text() == "old: dhcp\n"


def test_gateway_failure_rolls_back_at_once(host, network):
    network["check_error"] = "gateway 10.0.0.254 does not answer on eth0"
    host = dataclasses.replace(host, confirm_timeout=30)
    started = time.monotonic()
    assert network_apply.apply(host) == 1
    assert time.monotonic() - started < 5
    result = status(host)
    assert (result.state, result.message) == ("rolled-back", network["check_error"])
    assert Path(host.superseded[0]).read_text() == "old: dhcp\n"


def test_existing_file_is_restored_with_its_content_and_mode(host, network):
    replaced = Path(host.files[0])
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
    assert status(host).state == "rollback-failed"
    assert "disk full" in status(host).message


def test_validation_root_has_the_future_netplan_directory(host):
    root = network_apply.validation_root(host)
    staged = root / host.netplan_dir.lstrip("/")
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
    network_apply.apply_files(small_plan())
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
        network_apply.apply_files(small_plan())
    assert str(caught.value) == (
        "could not apply the configuration: netplan apply: netplan failed; "
        "networkctl reload: networkctl failed; "
        "systemctl restart systemd-networkd: systemctl failed"
    )


def test_keyfile_layout_reloads_networkmanager_or_restarts_it():
    commands = network_apply.apply_commands(small_plan(NM_KEYFILE, "wlan0"))
    assert commands == [
        [["nmcli", "connection", "reload"], ["nmcli", "device", "connect", "wlan0"]],
        [["systemctl", "restart", "NetworkManager"], ["nmcli", "--wait", "20", "device", "connect", "wlan0"]],
    ]


def test_netplan_networkmanager_fallback_restarts_networkmanager_that_netplan_apply_stopped():
    # Seen in the sandbox: `netplan apply` stops NetworkManager, its udev trigger fails, and
    # a fallback that only ran `nmcli connection reload` left the host with no address.
    commands = network_apply.apply_commands(small_plan(NETPLAN_NM))
    assert commands == [
        [["netplan", "apply"]],
        [["netplan", "generate"], ["systemctl", "restart", "NetworkManager"],
         ["nmcli", "--wait", "20", "device", "connect", "eth0"]],
    ]


def test_check_running_waits_for_the_address(monkeypatch):
    monkeypatch.setattr(network_apply, "interface_addresses", lambda interface: ["10.0.0.9/24"])
    plan = small_plan(expect_address="10.0.0.5/24")
    with pytest.raises(network_apply.ApplyError, match="eth0 did not get 10.0.0.5/24"):
        network_apply.check_running(plan, wait=0.2)


def test_usage_error_for_unknown_command(capsys):
    assert network_apply.main(["network_apply.py", "launch", "plan.json"]) == 64


# The plan and the status: defined once, here, and checked when read.


@pytest.mark.parametrize(
    "changes, words",
    [
        ({"layout": "netplan"}, "layout 'netplan' is not one of"),
        ({"interface": "-eth0"}, "not an interface name"),
        ({"interface": "eth0\nx"}, "not an interface name"),
        ({"files": ["etc/netplan/x.yaml"]}, "not an absolute path"),
        ({"superseded": ["/etc/netplan/../shadow"]}, "not an absolute path"),
        ({"token": "$(reboot)"}, "not a token"),
        ({"confirm_timeout": 0}, "not a number of seconds"),
        ({"backups_keep": 0}, "backups_keep 0 is not a positive number"),
        ({"backups_keep": True}, "is not a positive number"),
    ],
)
def test_plan_refuses_what_the_script_must_not_act_on(host, changes, words):
    with pytest.raises(ValueError, match="bad plan") as caught:
        dataclasses.replace(host, **changes)
    assert words in str(caught.value)


def test_plan_reads_back_and_refuses_unknown_or_missing_fields(host, tmp_path):
    assert Plan.from_json(host.to_json()) == host
    data = json.loads(host.to_json())
    with pytest.raises(ValueError, match="unknown fields"):
        Plan.from_json(json.dumps({**data, "layuot": NETPLAN_NM}))
    del data["interface"]
    with pytest.raises(ValueError, match="bad plan"):
        Plan.from_json(json.dumps(data))
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(data))
    assert network_apply.main(["network_apply.py", "validate", str(plan_path)]) == 65


def test_status_of_another_run_or_garbage_is_none():
    text = Status("t0k", "confirmed", backup="/b").to_json()
    assert Status.from_json(text, "t0k") == Status("t0k", "confirmed", "", "/b")
    assert Status.from_json(text, "other") is None
    for garbage in (None, "", "{", "[]", '{"token": "t0k"}', '{"token": "t0k", "state": "x", "extra": 1}'):
        assert Status.from_json(garbage, "t0k") is None


def test_script_is_standalone():
    # Uploaded and run with the host's python3: standard library only, no roslab.
    source = Path(network_apply.__file__)
    imported = set()
    for node in ast.walk(ast.parse(source.read_text())):
        if isinstance(node, ast.Import):
            imported.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            imported.add(node.module.split(".")[0])
    assert imported <= set(sys.stdlib_module_names) | {"__future__"}, imported
    # Isolated mode, from another directory: no site-packages, no repository on sys.path.
    result = subprocess.run([sys.executable, "-I", str(source)], capture_output=True, text=True, cwd="/")
    assert result.returncode == 64 and "usage:" in result.stderr


def test_layout_and_state_names_are_written_only_in_the_script():
    # The controller's modules import them from roslab.network.apply instead.
    names = [*network_apply.LAYOUTS, network_apply.STATE_APPLYING, network_apply.STATE_WAITING,
             *network_apply.FINAL_STATES]
    root = Path(network_apply.__file__).resolve().parents[2]
    controller = [path for path in (root / "roslab/network").glob("*.py") if path.name != "apply.py"]
    for path in [*controller, root / "deploy/network.py"]:
        text = path.read_text()
        for name in names:
            assert f'"{name}"' not in text and f"'{name}'" not in text, (path.name, name)
