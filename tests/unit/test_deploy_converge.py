"""deploy.py on fake Ubuntu hosts: a first run converges, a second run changes nothing."""

from __future__ import annotations

import pytest
from fixtures.classroom import host_data, run_deploy_py, with_stand_in_deb
from fixtures.fake_host import plan
from fixtures.fake_ubuntu import FakeUbuntu


@pytest.mark.parametrize(
    ("codename", "role", "ros_packages"),
    [
        ("noble", "main", "ros-jazzy-desktop ros-dev-tools"),
        ("jammy", "robot", "ros-humble-ros-base ros-dev-tools"),
    ],
)
def test_first_run_converges_and_second_run_changes_nothing(tmp_path, codename, role, ros_packages):
    host = with_stand_in_deb(FakeUbuntu(codename), codename)
    data = host_data(tmp_path, codename, role)

    first = plan(run_deploy_py, host.facts(), data)
    assert not first.failed, first.errors
    install = first.changing()[next(name for name in first.changing() if "Ensure ROS 2" in name)]
    assert "apt-get -y -o DPkg::Lock::Timeout=600 " in install[0]
    assert f" install -- {ros_packages}; status=$?;" in install[0]
    assert f"/opt/ros/{ros_packages.split('-')[1]}/setup.bash" in host_bashrc_after(host, first)

    second = plan(run_deploy_py, host.facts(), data)
    assert second.changing() == {}
    assert "block (ROS 2 environment) in /home/student/.bashrc is already up to date" in second.noops
    assert f"{ros_packages.replace(' ', ', ')} are installed" in second.noops


def host_bashrc_after(host, result):
    host.apply(result)
    return "\n".join(host.files["/home/student/.bashrc"])


def test_a_new_domain_id_rewrites_only_the_block_and_shows_the_diff(tmp_path, caplog):
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), host_data(tmp_path)))
    bashrc_before = list(host.files["/home/student/.bashrc"])

    with caplog.at_level("INFO"):
        result = plan(run_deploy_py, host.facts(), host_data(tmp_path, ros_domain_id=42), diff=True)

    assert list(result.changing()) == [
        "The login user's shell sources ROS 2 with the team's domain and discovery settings"
        " | Ensure student's ~/.bashrc sets up the ROS 2 environment"
    ]
    printed = "\n".join(record.getMessage() for record in caplog.records)
    assert "- export ROS_DOMAIN_ID=11" in printed and "+ export ROS_DOMAIN_ID=42" in printed
    host.apply(result)
    after = host.files["/home/student/.bashrc"]
    assert after[:2] == bashrc_before[:2]  # the user's own lines
    assert sum(line.startswith("# BEGIN roslab") for line in after) == 1
    assert "export ROS_DOMAIN_ID=42" in after


def test_each_step_can_be_switched_off(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    switches = ["apt_cache", "apt_ready", "locale", "ros_apt_source", "ros_install", "rosdep", "shell_env", "ssh_identity",
                "ssh_hardening"]
    data = host_data(tmp_path, **{f"{name}_enabled": False for name in switches})
    result = plan(run_deploy_py, host.facts(), data)
    assert result.operations == [] and not result.failed


def test_a_deleted_end_marker_costs_no_user_line_over_two_runs(tmp_path, caplog):
    """Issue 9: the first run used to add a second block, the next deleted the lines between."""
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), host_data(tmp_path)))
    bashrc = host.files["/home/student/.bashrc"]
    bashrc.remove("# END roslab managed block (ROS 2 environment)")
    bashrc += ["source ~/my_ws/install/setup.bash", "alias ws='cd ~/my_ws'"]
    user_lines = [line for line in bashrc if not line.startswith(("# BEGIN roslab", "# END roslab"))]

    with caplog.at_level("WARNING"):
        first = plan(run_deploy_py, host.facts(), host_data(tmp_path))
    assert list(first.changing()) == [
        "The login user's shell sources ROS 2 with the team's domain and discovery settings"
        " | Ensure student's ~/.bashrc sets up the ROS 2 environment"
    ]
    assert any("repairs the markers" in r.getMessage() for r in caplog.records)
    host.apply(first)
    after = host.files["/home/student/.bashrc"]
    assert sum(line.startswith("# BEGIN roslab") for line in after) == 1
    assert sum(line.startswith("# END roslab") for line in after) == 1
    for line in user_lines:
        assert line in after, line
    assert after[-2:] == ["source ~/my_ws/install/setup.bash", "alias ws='cd ~/my_ws'"]

    assert plan(run_deploy_py, host.facts(), host_data(tmp_path)).changing() == {}


@pytest.mark.parametrize(("codename", "role"), [("noble", "main"), ("jammy", "robot")])
def test_a_first_run_updates_apt_once_and_a_noop_run_reads_the_host_in_two_commands(tmp_path, codename, role):
    host = with_stand_in_deb(FakeUbuntu(codename), codename)
    data = host_data(tmp_path, codename, role, teacher_ssh_keys=["ssh-ed25519 AAAAC3NzaC1lZDI1NTE5AAAAIteacher t@lab"])

    first = plan(run_deploy_py, host.facts(), data)
    assert not first.failed, first.errors
    changing = list(first.changing())
    updates = [name for name, commands in first.changing().items()
               if any("APT::Update::Error-Mode=any update" in command for command in commands)]
    # Both the Ubuntu sources and the ROS 2 source changed: one update, after both, before any install.
    assert len(updates) == 1, updates
    assert changing.index(updates[0]) > changing.index(next(n for n in changing if "ros2-apt-source" in n))
    assert changing.index(updates[0]) < changing.index(next(n for n in changing if "Ensure ROS 2" in n))

    host.apply(first)
    second = plan(run_deploy_py, host.facts(), data)
    assert second.changing() == {}
    # roslab.probe: the release and home, then everything else; a fact read on its own here
    # is a remote command per host on every no-op run (add it to its deploy's @probe.reader).
    assert second.facts_asked == ["HostProbe", "HostProbe"]


def turtlebot3_robot_data(tmp_path, lds_model="LDS-02", lds_usb_serial=None, **settings):
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    given = {"turtlebot3_model": "burger", "lds_model": lds_model}
    profile, problems = resolve_host(builtin_profiles()["turtlebot3"],
                                     {**given, **({"lds_usb_serial": lds_usb_serial} if lds_usb_serial else {})},
                                     distro="jazzy", role="robot")
    assert not problems
    return host_data(tmp_path, "noble", "robot", roslab_profile=profile,
                     nodes_launch=profile["launch"], ros_variant=profile["variant"], **settings)


def test_a_turtlebot3_robot_gets_its_packages_udev_rules_group_and_variables_then_nothing(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    first = plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path))
    assert not first.failed, first.errors
    changing = first.changing()
    install = next(commands for name, commands in changing.items() if "Ensure ROS 2" in name)
    assert (" install -- ros-jazzy-ros-base ros-dev-tools ros-jazzy-turtlebot3-bringup "
            "ros-jazzy-turtlebot3-node ros-jazzy-turtlebot3-description "
            "ros-jazzy-turtlebot3-msgs ros-jazzy-dynamixel-sdk ros-jazzy-hls-lfcd-lds-driver "
            "ros-jazzy-ld08-driver ros-jazzy-coin-d4-driver; status=$?;") in install[0]
    rules = first.uploads()["/etc/udev/rules.d/60-roslab-profile.rules"]
    assert 'ATTRS{idVendor}=="0483", ATTRS{idProduct}=="5740"' in rules and 'SYMLINK+="tb3_lidar"' in rules
    assert any("udevadm control --reload-rules" in " ".join(c) for n, c in changing.items() if "udev has read" in n)
    assert ["usermod -a -G dialout student"] in changing.values()
    bashrc = host_bashrc_after(host, first)
    assert "export TURTLEBOT3_MODEL=burger" in bashrc and "export LDS_MODEL=LDS-02" in bashrc

    second = plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path))
    assert second.changing() == {}
    assert "student is already in dialout" in second.noops


def test_another_lidar_changes_the_variable_only_and_the_lidars_serial_its_udev_rule(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path)))
    for lds_model in ("LDS-03", "LDS-01"):  # every LDS model's adapter is /dev/tb3_lidar
        result = plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path, lds_model=lds_model))
        assert [name.split(" | ")[1] for name in result.changing()] == [
            "Ensure student's ~/.bashrc sets up the ROS 2 environment"]
    result = plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path, lds_usb_serial="0001"))
    names = [name.split(" | ")[1] for name in result.changing()]
    assert names == ["Ensure 60-roslab-profile.rules holds robot profile turtlebot3's udev rules",
                     "Ensure udev has read the robot profile's rules"]
    assert 'ATTRS{serial}=="0001"' in result.uploads()["/etc/udev/rules.d/60-roslab-profile.rules"]


def test_an_opted_in_2_gb_robot_gets_the_e_manuals_tweaks_once_and_a_noop_reads_in_two_commands(tmp_path):
    host = with_stand_in_deb(FakeUbuntu())
    host.memory_mb = 1848  # a 2 GB Pi 4
    data = turtlebot3_robot_data(tmp_path, profile_os_tweaks=True)
    first = plan(run_deploy_py, host.facts(), data)
    assert not first.failed, first.errors
    names = [name.split(" | ")[1] for name in first.changing()]
    assert "Ensure /swapfile (2048 MiB) is in use as swap (robot profile turtlebot3)" in names
    assert "Ensure /etc/fstab turns /swapfile on at boot" in names
    host.apply(first)
    assert "sleep.target" in host.masked_units and host.swap_files["/swapfile"]["active"]
    assert "/swapfile none swap sw 0 0" in host.files["/etc/fstab"]

    second = plan(run_deploy_py, host.facts(), data)
    assert second.changing() == {}
    assert second.facts_asked == ["HostProbe", "HostProbe"]


def osr_robot_data(tmp_path, **given):
    from roslab.profiles.library import builtin_profiles
    from roslab.profiles.resolve import resolve_host

    profile, problems = resolve_host(builtin_profiles()["osr"], given, distro="jazzy", role="robot", board="pi4")
    assert not problems
    # The rover's venv and sources have their own converge tests (test_python_env.py,
    # test_sources.py): this host is about its boot config, services and groups.
    return host_data(tmp_path, "noble", "robot", roslab_profile=profile, python_env_enabled=False,
                     nodes_launch=profile["launch"], ros_variant=profile["variant"])


def test_an_osr_robot_gets_its_boot_config_once_records_the_reboot_and_then_nothing(tmp_path):
    from roslab.ops.boot_config import CMDLINE_TXT, CONFIG_TXT, REBOOT_RECORD

    host = with_stand_in_deb(FakeUbuntu())
    host.files[CONFIG_TXT] = ["[pi4]", "max_framebuffers=2", "[all]", "arm_64bit=1"]
    host.files[CMDLINE_TXT] = ["console=serial0,115200 console=tty1 root=LABEL=writable rootwait"]
    first = plan(run_deploy_py, host.facts(), osr_robot_data(tmp_path))
    assert not first.failed, first.errors
    names = [name.split(" | ")[1] for name in first.changing()]
    assert "Ensure the host records that the boot config waits for a reboot" in names
    assert "Ensure /etc/systemd/system/osr_startup.service exists" not in names
    assert first.uploads()["/etc/systemd/system/osr_startup.service"].count("Restart=always") == 1
    host.apply(first)
    assert host.files[CONFIG_TXT][:4] == ["[pi4]", "max_framebuffers=2", "[all]", "arm_64bit=1"]
    assert "enable_uart=1" in host.files[CONFIG_TXT]
    assert host.files[CMDLINE_TXT] == ["console=tty1 root=LABEL=writable rootwait"]
    assert host.files[REBOOT_RECORD][0] == "boot_id=boot-1"
    assert {"tty", "dialout", "input"} <= set(host.groups["student"])

    second = plan(run_deploy_py, host.facts(), osr_robot_data(tmp_path))
    assert second.changing() == {}
    assert second.facts_asked == ["HostProbe", "HostProbe"]
    assert any("osr_startup.service is installed but not enabled because osr_calibrated is false" in noop
               for noop in second.noops)

    host.boot_id = "boot-2"  # the teacher rebooted the rover
    third = plan(run_deploy_py, host.facts(), osr_robot_data(tmp_path))
    assert [name.split(" | ")[1] for name in third.changing()] == [
        "Ensure a reboot record from before the last reboot is gone"]


def test_a_team_switching_from_osr_to_demo_loses_the_rovers_unit_and_groups_says_what_stays_then_nothing(
        tmp_path, caplog):
    from roslab.ops.boot_config import CONFIG_TXT
    from roslab.ops.profile_record import PROFILE_RECORD

    host = with_stand_in_deb(FakeUbuntu())
    host.files[CONFIG_TXT] = ["[all]", "arm_64bit=1"]
    host.groups["student"] = ["student", "video"]  # video: the user's before roslab
    osr = plan(run_deploy_py, host.facts(), osr_robot_data(tmp_path, osr_calibrated="true"))
    assert not osr.failed, osr.errors
    host.apply(osr)
    assert "/etc/systemd/system/osr_startup.service" in host.files
    assert {"tty", "dialout", "input"} <= set(host.groups["student"])
    assert '"profile": "osr"' in host.files[PROFILE_RECORD][0]

    demo = host_data(tmp_path, "noble", "robot")
    caplog.clear()
    switch = plan(run_deploy_py, host.facts(), demo)
    assert not switch.failed, switch.errors
    changes = switch.changing()
    (gone,) = [commands for name, commands in changes.items() if "osr_startup.service of an earlier" in name]
    assert gone[0].startswith("systemctl disable --now osr_startup.service") and gone[-1] == "systemctl daemon-reload"
    (left,) = [commands for name, commands in changes.items() if "no longer in" in name]
    assert left == ["gpasswd -d student dialout >/dev/null", "gpasswd -d student input >/dev/null",
                    "gpasswd -d student tty >/dev/null"]
    said = [record.getMessage() for record in caplog.records if "robot profile osr -> demo" in record.getMessage()]
    assert len(said) == 1 and "removed osr_startup.service; student from groups dialout, input, tty" in said[0]
    assert f"kept its boot config block in {CONFIG_TXT}" in said[0] and "needs a reboot" in said[0]
    host.apply(switch)
    assert "/etc/systemd/system/osr_startup.service" not in host.files
    assert host.groups["student"] == ["student", "video"]  # the user's own group stays

    again = plan(run_deploy_py, host.facts(), demo)
    assert again.changing() == {}
    assert again.facts_asked == ["HostProbe", "HostProbe"]


def test_a_host_converged_before_the_record_existed_still_loses_the_old_profiles_unit(tmp_path, caplog):
    from roslab.ops.profile_record import PROFILE_RECORD

    host = with_stand_in_deb(FakeUbuntu())
    host.apply(plan(run_deploy_py, host.facts(), osr_robot_data(tmp_path, osr_calibrated="true")))
    del host.files[PROFILE_RECORD]  # an older roslab wrote the unit and kept no record
    switch = plan(run_deploy_py, host.facts(), host_data(tmp_path, "noble", "robot"))
    names = [name.split(" | ")[1] for name in switch.changing()]
    assert "Ensure osr_startup.service of an earlier robot profile is stopped, disabled and removed" in names
    assert not [name for name in names if "no longer in" in name]  # whose groups: unknown, they stay
    host.apply(switch)
    assert plan(run_deploy_py, host.facts(), host_data(tmp_path, "noble", "robot")).changing() == {}


def test_a_turtlebot3_team_switching_to_demo_is_told_its_masked_units_stay(tmp_path, caplog):
    host = with_stand_in_deb(FakeUbuntu())
    host.memory_mb = 1848
    host.apply(plan(run_deploy_py, host.facts(), turtlebot3_robot_data(tmp_path, profile_os_tweaks=True)))
    caplog.clear()
    switch = plan(run_deploy_py, host.facts(), host_data(tmp_path, "noble", "robot", profile_os_tweaks=True))
    said = [record.getMessage() for record in caplog.records if "robot profile turtlebot3 -> demo" in record.getMessage()]
    assert len(said) == 1 and "removed student from groups dialout" in said[0], said
    assert "the units its OS tweaks masked (hibernate.target" in said[0] and "systemctl unmask" in said[0]
    host.apply(switch)
    caplog.clear()
    again = plan(run_deploy_py, host.facts(), host_data(tmp_path, "noble", "robot", profile_os_tweaks=True))
    assert again.changing() == {}
    assert not [record for record in caplog.records if "->" in record.getMessage()]


def test_a_profile_switch_keeps_the_underlay_sourced_while_the_class_has_sources_and_says_so_only_when_not():
    from types import SimpleNamespace

    from deploy.profile_switch import kept_after_switch, underlay_sourced

    class_sources = SimpleNamespace(sources_enabled=True, roslab_sources=[{"path": "lab_tools"}])
    assert underlay_sourced(class_sources)  # the demo profile names none; the roster's workspace_sources do
    assert not underlay_sourced(SimpleNamespace(sources_enabled=True, roslab_sources=[]))
    assert not underlay_sourced(SimpleNamespace(sources_enabled=False, roslab_sources=[{"path": "lab_tools"}]))
    record = {"boot_config": [], "venv": None, "sources": True, "masked_units": []}
    assert not [line for line in kept_after_switch({"sources": True}, record) if "underlay" in line]
    (line,) = kept_after_switch({"sources": True}, {**record, "sources": False})
    assert "no longer source the build): delete it by hand" in line


def test_a_lock_taken_after_the_first_converge_pins_once_and_the_noop_still_reads_in_two_commands(tmp_path):
    from roslab import class_lock

    host = with_stand_in_deb(FakeUbuntu())
    data = host_data(tmp_path, roslab_roster_path=str(tmp_path / "classroom.yaml"))
    host.apply(plan(run_deploy_py, host.facts(), data))
    installed = {name: sorted(versions)[0] for name, versions in host.packages.items()}
    lock, _ = class_lock.merged(class_lock.ClassLock(), "jazzy/arm64", installed, {}, "2026-11-28T22:00:00Z",
                                "team1-main")
    (tmp_path / "classroom.lock").write_text(class_lock.render_lock(lock))

    pinned = plan(run_deploy_py, host.facts(), data)
    assert [name.split(" | ")[1] for name in pinned.changing()] == [
        f"Ensure apt installs the class lock's versions ({len(lock.groups['jazzy/arm64'].packages)} packages)"]
    host.apply(pinned)
    noop = plan(run_deploy_py, host.facts(), data)
    assert noop.changing() == {}
    assert noop.facts_asked == ["HostProbe", "HostProbe"]  # the lock adds no remote command
