"""The robot profile's opt-in OS tweaks (`profile_os_tweaks`): facts in, commands out.

TurtleBot3's e-Manual masks systemd-networkd-wait-online and the sleep targets and adds swap on
2 GB boards; roslab does it only where the roster opts in, and a second run changes nothing.
"""

from __future__ import annotations

from fixtures.fake_host import plan
from pyinfra.facts.files import File, FileContents

from deploy.robot_profile import robot_profile
from roslab.ops.memory import MemoryTotal, SwapFile
from roslab.ops.systemd import UnitsMasked
from roslab.profiles.library import builtin_profiles
from roslab.profiles.resolve import resolve_host

UNITS = ["systemd-networkd-wait-online.service", "sleep.target", "suspend.target",
         "hibernate.target", "hybrid-sleep.target"]
TWO_GIB = 2048 * 1024 * 1024


def turtlebot3_robot() -> dict:
    data, problems = resolve_host(builtin_profiles()["turtlebot3"],
                                  {"turtlebot3_model": "burger", "lds_model": "LDS-02"},
                                  distro="jazzy", role="robot")
    assert not problems
    return data


def facts(masked=(), memory=1848, swap=None, fstab=None):
    fstab_lines = fstab if fstab is not None else ["LABEL=writable / ext4 defaults 0 1"]
    return {
        UnitsMasked: lambda units: {unit: unit in masked for unit in units},
        MemoryTotal: memory,
        SwapFile: lambda path: swap or {"size": None, "active": False},
        FileContents: lambda path: fstab_lines if path == "/etc/fstab" else None,
        File: lambda path: ({"user": "root", "group": "root", "mode": 644}
                            if path == "/etc/fstab" else None),
    }


def run(host_facts, opted_in=True):
    profile = turtlebot3_robot()
    profile["udev_rules"] = ""  # this test is about the tweaks
    profile["groups"] = []
    return plan(robot_profile, host_facts,
                data={"roslab_profile": profile, "profile_os_tweaks": opted_in, "robot_profile_enabled": True})


def test_turtlebot3_declares_the_e_manuals_tweaks():
    assert turtlebot3_robot()["os_tweaks"] == {
        "mask_units": UNITS, "swap_mb": 2048, "swap_if_memory_mb_at_most": 2048}


def test_without_opting_in_nothing_of_the_os_is_read_or_changed():
    result = run(facts(), opted_in=False)
    assert result.changing() == {}
    assert not {"UnitsMasked", "MemoryTotal", "SwapFile"} & set(result.facts_asked)


def test_a_2_gb_robot_gets_the_units_masked_and_a_swap_file_kept_on_at_boot():
    changes = run(facts(memory=1848)).changing()
    (mask,) = [commands for name, commands in changes.items() if "masked" in name]
    assert mask == ["systemctl mask " + " ".join(UNITS)]
    (swap,) = [commands for name, commands in changes.items() if "in use as swap" in name]
    assert "fallocate -l 2048M /swapfile.roslab-new" in swap[0] and "umask 077" in swap[0]
    assert swap[0].endswith("mv -f -- /swapfile.roslab-new /swapfile && swapon /swapfile")
    assert " dd " not in swap[0]
    (fstab,) = [name for name in changes if "/etc/fstab" in name]
    assert "upload /etc/fstab" in changes[fstab][-1]


def test_a_4_gb_robot_gets_no_swap_file():
    changes = run(facts(memory=3794)).changing()
    assert not [name for name in changes if "swap" in name or "fstab" in name]
    assert [name for name in changes if "masked" in name]


def test_a_converged_robot_is_a_noop_saying_why():
    fstab = ["LABEL=writable / ext4 defaults 0 1",
             "# BEGIN roslab managed block (robot profile swap file)",
             "/swapfile none swap sw 0 0",
             "# END roslab managed block (robot profile swap file)"]
    result = run(facts(masked=UNITS, swap={"size": TWO_GIB, "active": True}, fstab=fstab))
    assert result.changing() == {}
    assert any("already masked" in reason for reason in result.noops)
    assert any("already in use as swap" in reason for reason in result.noops)


def test_only_the_missing_masks_and_a_swapon_are_planned_after_a_reboot_without_fstab_luck():
    changes = run(facts(masked=UNITS[1:], swap={"size": TWO_GIB, "active": False})).changing()
    (mask,) = [commands for name, commands in changes.items() if "masked" in name]
    assert mask == ["systemctl mask systemd-networkd-wait-online.service"]
    (swap,) = [commands for name, commands in changes.items() if "in use as swap" in name]
    assert swap == ["swapon /swapfile"]


def test_a_swap_file_of_another_size_is_switched_off_and_made_anew_after_the_room_check():
    changes = run(facts(masked=UNITS, swap={"size": 1024 * 1024 * 1024, "active": True})).changing()
    (swap,) = [commands for name, commands in changes.items() if "in use as swap" in name]
    (command,) = swap
    assert command.index("not enough room") < command.index("swapoff /swapfile") < command.index("mkswap")


def test_a_partial_file_left_beside_a_good_swap_file_is_removed_then_a_no_op():
    changes = run(facts(masked=UNITS, swap={"size": TWO_GIB, "active": True, "partial": True})).changing()
    (swap,) = [commands for name, commands in changes.items() if "in use as swap" in name]
    assert swap == ["rm -f -- /swapfile.roslab-new"]


def make_swap_locally(tmp_path, size_mb: int, margin_mb: int = 1, fallocate: str | None = None, old: bytes = b""):
    """Run the planned command in a shell on this machine, in tmp_path: swapon, swapoff and
    mkswap are stand-ins that log (the kernel's swap is not touched), df and fallocate are real
    unless `fallocate` replaces it."""
    import os
    import subprocess

    from fixtures.fake_host import plan as plan_op

    from roslab.ops.memory import swap_file_on

    target = tmp_path / "disk" / "swapfile"
    target.parent.mkdir()
    if old:
        target.write_bytes(old)
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name in ("swapon", "swapoff", "mkswap"):
        (stubs / name).write_text(f"#!/bin/sh\necho {name} \"$@\" >> {tmp_path}/log\n")
    if fallocate:
        (stubs / "fallocate").write_text(fallocate)
    for stub in stubs.iterdir():
        stub.chmod(0o755)
    result = plan_op(lambda: swap_file_on(name="swap", path=str(target), size_mb=size_mb, margin_mb=margin_mb),
                     {SwapFile: lambda path: {"size": None, "active": False, "partial": False}}, {})
    (command,) = [line for op in result.operations for line in op.text()]
    done = subprocess.run(["sh", "-c", command], capture_output=True, text=True,
                          env={**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}"})
    return done, target


def test_a_swap_file_is_made_under_a_temporary_name_and_renamed_when_complete(tmp_path):
    done, target = make_swap_locally(tmp_path, 2)
    assert done.returncode == 0, done.stderr
    assert target.stat().st_size == 2 * 1024 * 1024 and oct(target.stat().st_mode & 0o777) == "0o600"
    assert sorted(p.name for p in target.parent.iterdir()) == ["swapfile"]
    assert (tmp_path / "log").read_text().splitlines() == [
        f"mkswap {target}.roslab-new", f"swapon {target}"]


def test_too_little_room_is_refused_naming_needed_and_free_and_nothing_is_made(tmp_path):
    done, target = make_swap_locally(tmp_path, 64 * 1024 * 1024, old=b"old swap")  # 64 TiB
    assert done.returncode == 1
    line = done.stderr.strip()
    assert line.startswith(f"roslab: not enough room for {target}: 67108864 MiB and a margin of 1 MiB needed,")
    assert "MiB free: nothing was changed" in line
    assert target.read_bytes() == b"old swap"  # the old file is untouched
    assert sorted(p.name for p in target.parent.iterdir()) == ["swapfile"]


def test_a_failing_allocation_removes_its_partial_file(tmp_path):
    # a disk that fills during the allocation: half the file written, then the error
    fails = '#!/bin/sh\nhead -c 1024 /dev/zero > "$3"; echo "fallocate: No space left on device" >&2; exit 1\n'
    done, target = make_swap_locally(tmp_path, 2, fallocate=fails)
    assert done.returncode == 1
    assert "could not make" in done.stderr and "fallocate failed; the partial file was removed" in done.stderr
    assert list(target.parent.iterdir()) == []


def test_an_extending_profile_changes_one_tweak_and_keeps_the_others(tmp_path):
    from roslab.roster import load_roster

    roster = tmp_path / "roster.yaml"
    roster.write_text(
        "classroom:\n  ssh_user: ubuntu\n  ros_packages_check: false\nprofiles:\n  bigswap:\n"
        "    extends: turtlebot3\n    robot: {os_tweaks: {swap_mb: 4096}}\n"
        "  limitonly:\n    profile: limitonly\n    distros: [jazzy]\n"
        "    robot: {os_tweaks: {swap_if_memory_mb_at_most: 4096}}\n"
        "teams:\n  t1:\n    robot_profile: bigswap\n    turtlebot3_model: burger\n    lds_model: LDS-02\n"
        "    hosts:\n      t1-main: {role: main, address: 127.0.0.1}\n"
        "      t1-robot: {role: robot, address: 127.0.0.2}\n")
    try:
        load_roster(roster)
    except Exception as error:  # the unused limit-only profile is refused where it is defined
        text = str(error)
    else:
        text = ""
    assert "profiles.limitonly.robot.os_tweaks" in text and "no swap_mb" in text
    assert "bigswap" not in text


def test_hand_made_host_data_gets_the_same_allow_lists_as_a_profile():
    """The roster loader refuses these; host data written by hand (a group file, a test) meets the
    same allow-list in the operation, before any command is planned."""
    import pytest
    from pyinfra.api import OperationError
    from pyinfra.facts.server import Home, User

    from roslab.ops.users import UserGroups

    profile = turtlebot3_robot()
    profile["udev_rules"] = ""
    for changed, words in (({"os_tweaks": {"mask_units": ["ssh.service"]}, "groups": []},
                            "'ssh.service' is not a unit"),
                           ({"groups": ["sudo"]}, "'sudo' is not a hardware-access group")):
        with pytest.raises(OperationError, match=words):
            plan(robot_profile, {**facts(), User: "ubuntu", Home: lambda user: "/home/ubuntu",
                                 UserGroups: lambda user: ["ubuntu"]},
                 data={"roslab_profile": {**profile, **changed}, "profile_os_tweaks": True,
                       "robot_profile_enabled": True})
