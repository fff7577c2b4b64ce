"""`roslab sandbox up --roster FILE`: the sandbox's hosts and roster from a class's own roster
(no host is booted: the plan and the roster the sandbox would write)."""

from __future__ import annotations

from ipaddress import IPv4Network
from types import SimpleNamespace

import pytest
from test_profiles import _in_tmp, rosdistro_url, write  # noqa: F401  (fixtures)

from roslab.roster import load_roster
from roslab.sandbox import class_roster, lifecycle
from roslab.sandbox.instance import Instance

SANDBOX_SETTINGS = {"rosdistro_index_url": "http://10.213.163.1:8080/rosdistro/index-v4.yaml",
                    "ros_middleware": "rmw_cyclonedds_cpp"}


def teachers_class(tmp_path, url):
    secrets = tmp_path / "secrets.yaml"
    secrets.write_text("sudo: not-a-real-password\n")
    secrets.chmod(0o600)
    return write(tmp_path, f"""\
        classroom:
          name: Robotics 1
          ssh_user: teacher
          ros_middleware: rmw_fastrtps_cpp
          rosdistro_index_url: {url}
          rosdep_cache_dir: cache
          sudo_password_secret: sudo
          nodes_verify_timeout: 30
        teams:
          blue:
            ubuntu_release: "24.04"
            robot_profile: turtlebot3
            turtlebot3_model: burger
            lds_model: LDS-03
            ros_domain_id: 21
            hosts:
              blue-main: {{role: main, address: 192.168.50.11}}
              blue-robot: {{role: robot, address: 192.168.50.12, network_address: 192.168.50.112/24}}
          green:
            ubuntu_release: "22.04"
            robot_profile: turtlebot3
            turtlebot3_model: waffle_pi
            lds_model: LDS-01
            hosts:
              green-main: {{role: main, address: 192.168.50.21}}
              green-robot: {{role: robot, address: 192.168.50.22}}
          sim1:
            ubuntu_release: "24.04"
            robot_profile: sim
            hosts:
              sim1-main: {{role: main, address: 192.168.50.31}}
        """)


def planned(tmp_path, url):
    path = teachers_class(tmp_path, url)
    members, notes = class_roster.members(load_roster(path))
    instance = Instance("try-class", IPv4Network("10.213.163.0/24"))
    return path, instance, instance.plan_members(members), notes


def test_the_sandbox_hosts_are_the_rosters_hosts(tmp_path, rosdistro_url):
    _, instance, hosts, notes = planned(tmp_path, rosdistro_url)
    assert [(h.name, h.team, h.role, h.release, h.address) for h in hosts] == [
        ("blue-main", "blue", "main", "24.04", "10.213.163.11"),
        ("blue-robot", "blue", "robot", "24.04", "10.213.163.12"),
        ("green-main", "green", "main", "22.04", "10.213.163.13"),
        ("green-robot", "green", "robot", "22.04", "10.213.163.14"),
        ("sim1-main", "sim1", "main", "24.04", "10.213.163.15"),
    ]
    assert notes == []
    # What sandbox.json keeps: `status` and `ssh` then use the roster's names.
    again = instance.plan_members([{"name": h.name, "team": h.team, "role": h.role, "release": h.release}
                                   for h in hosts])
    assert again == hosts
    assert lifecycle.Classroom(instance, hosts).host("green-robot").address == "10.213.163.14"


def test_the_class_settings_are_kept_where_the_sandbox_can_serve_them(tmp_path, rosdistro_url):
    path, instance, hosts, _ = planned(tmp_path, rosdistro_url)
    published = SimpleNamespace(roster_settings=lambda: dict(SANDBOX_SETTINGS))
    base = lifecycle.roster(lifecycle.Classroom(instance, hosts, path), published)
    roster, notes = class_roster.sandbox_roster(path, base, {h.name: h.address for h in hosts},
                                                {h.name: h.release for h in hosts})

    assert roster["classroom"]["ssh_user"] == base["classroom"]["ssh_user"] != "teacher"
    assert roster["classroom"]["ros_middleware"] == "rmw_cyclonedds_cpp"
    assert roster["classroom"]["rosdistro_index_url"] == SANDBOX_SETTINGS["rosdistro_index_url"]
    assert roster["classroom"]["nodes_verify_timeout"] == 30  # the class's own
    assert roster["classroom"]["name"].endswith("(Robotics 1)")
    assert "sudo_password_secret" not in roster["classroom"]
    blue = roster["teams"]["blue"]
    assert (blue["robot_profile"], blue["turtlebot3_model"], blue["lds_model"], blue["ros_domain_id"]) == (
        "turtlebot3", "burger", "LDS-03", 21)
    assert blue["hosts"]["blue-robot"] == {"role": "robot", "address": "10.213.163.12", "ubuntu_release": "24.04"}
    assert roster["teams"]["green"]["hosts"]["green-main"]["ubuntu_release"] == "22.04"
    assert roster["teams"]["sim1"]["robot_profile"] == "sim"
    assert notes == [
        "classroom: ssh_user: the sandbox's own connection is used",
        "classroom: ros_middleware rmw_fastrtps_cpp: the sandbox's real ROS runtime serves rmw_cyclonedds_cpp "
        "only (its Humble has no Fast DDS); the sandbox runs that",
        "classroom: rosdistro_index_url: the sandbox serves its own",
        "classroom: rosdep_cache_dir: cache is relative to your roster's folder, not the sandbox's",
        "classroom: sudo_password_secret: the sandbox has no secrets (no WiFi, no sudo password)",
        "blue-robot: network_address: the sandbox's hosts keep its subnet's addresses",
    ]


@pytest.mark.parametrize(("served", "noted"), [
    ({"ros_middleware": "rmw_cyclonedds_cpp"}, True),  # the real runtime: Cyclone DDS only
    ({}, False),  # stand-ins only: roslab's default, as the class has it
])
def test_a_class_on_the_default_middleware_is_told_when_the_sandbox_runs_another(tmp_path, rosdistro_url,
                                                                                 served, noted):
    path = teachers_class(tmp_path, rosdistro_url)
    path.write_text(path.read_text().replace("  ros_middleware: rmw_fastrtps_cpp\n", ""))  # the default
    members, _ = class_roster.members(load_roster(path))
    instance = Instance("try-class", IPv4Network("10.213.163.0/24"))
    hosts = instance.plan_members(members)
    published = SimpleNamespace(roster_settings=lambda: {
        "rosdistro_index_url": SANDBOX_SETTINGS["rosdistro_index_url"], **served})
    base = lifecycle.roster(lifecycle.Classroom(instance, hosts, path), published)
    roster, notes = class_roster.sandbox_roster(path, base, {h.name: h.address for h in hosts},
                                                {h.name: h.release for h in hosts})
    said = [note for note in notes if "ros_middleware" in note]
    assert said == ([
        "classroom: ros_middleware (not set: roslab's default rmw_fastrtps_cpp): the sandbox's real ROS "
        "runtime serves rmw_cyclonedds_cpp only (its Humble has no Fast DDS); the sandbox runs that",
    ] if noted else [])
    assert roster["classroom"].get("ros_middleware") == served.get("ros_middleware")


def test_a_release_the_sandbox_does_not_emulate_is_a_note(tmp_path, rosdistro_url):
    classroom = load_roster(teachers_class(tmp_path, rosdistro_url))
    classroom.hosts[0].ubuntu_release = "20.04"  # as a roster of another time might say
    members, notes = class_roster.members(classroom)
    assert members[0]["release"] == class_roster.DEFAULT_RELEASE
    assert notes == ["blue-main: Ubuntu 20.04 is not a release the sandbox emulates: it runs 24.04"]


def test_hosts_and_roster_cannot_be_asked_together(tmp_path):
    with pytest.raises(lifecycle.SandboxError, match="--hosts and --roster"):
        lifecycle.up(4, Instance("try-class", IPv4Network("10.213.163.0/24")), class_roster=tmp_path / "x.yaml")


def test_up_again_without_options_keeps_a_class_sandbox(tmp_path, rosdistro_url, monkeypatch):
    path, instance, hosts, _ = planned(tmp_path, rosdistro_url)
    running = lifecycle.Classroom(instance, hosts, path)
    monkeypatch.setattr(lifecycle, "file_lock", lambda path: __import__("contextlib").nullcontext())
    monkeypatch.setattr(lifecycle, "load", lambda instance: running)
    monkeypatch.setattr(lifecycle, "_healthy", lambda classroom: True)
    assert lifecycle.up(instance=instance) is running  # nothing to do
    with pytest.raises(lifecycle.SandboxError, match="running with other hosts"):
        lifecycle.up(4, instance=instance)


def test_up_again_with_an_edited_roster_follows_it_and_says_what_changed(tmp_path, rosdistro_url, monkeypatch):
    # The sandbox runs the class; the teacher edits the roster: a setting, a team gone, a host new.
    from roslab.sandbox import instance as instance_module

    monkeypatch.setattr(instance_module, "STATE_ROOT", tmp_path / "run")
    path, instance, hosts, _ = planned(tmp_path, rosdistro_url)
    running = lifecycle.Classroom(instance, hosts, path)
    instance.state_dir.mkdir(parents=True)
    (instance.state_dir / "sandbox.json").write_text(__import__("json").dumps(
        {"members": lifecycle._members_state(hosts), "class_roster": str(path), "desktop": [],
         "ros_apt_source_sha256": {"noble": "0" * 64, "jammy": "1" * 64}, "ros": {}, "real_repositories": []}))
    key = tmp_path / "key.asc"
    key.write_text("key")
    __import__("subprocess").run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-f",
                                  str(instance.state_dir / "id_ed25519")], check=True)
    monkeypatch.setattr(lifecycle.upstream, "ros_key", lambda: SimpleNamespace(armored=key))
    monkeypatch.setattr(lifecycle, "file_lock", lambda path: __import__("contextlib").nullcontext())
    monkeypatch.setattr(lifecycle, "load", lambda instance: running)
    monkeypatch.setattr(lifecycle, "_healthy", lambda classroom: True)
    done = []
    monkeypatch.setattr(lifecycle, "_remove_host", lambda instance, host: done.append(("removed", host.name)))
    monkeypatch.setattr(lifecycle, "_boot_new", lambda instance, new, rootfs, keyring: done.append(
        ("booted", [(host.name, host.address) for host in new])))
    monkeypatch.setattr(lifecycle.image, "base_image", lambda: tmp_path)
    monkeypatch.setattr(lifecycle.upstream, "ubuntu_key", lambda: SimpleNamespace(keyring=key))
    assert lifecycle.up(instance=instance, class_roster=path) is not running  # the first look: unchanged
    assert done == []
    first = instance.roster_path.read_text()
    lines = []
    monkeypatch.setattr(lifecycle.log, "warning", lambda text, *args: lines.append(text % args))

    text = path.read_text().replace("turtlebot3_model: burger", "turtlebot3_model: waffle")
    green = text.index("  green:\n")
    text = text[:green] + text[text.index("  sim1:\n"):]  # team green is gone
    text += "  sim2:\n    ubuntu_release: \"24.04\"\n    robot_profile: sim\n    hosts:\n" \
            "      sim2-main: {role: main, address: 192.168.50.41}\n"
    path.write_text(text)
    address = {host.name: host.address for host in hosts}
    classroom = lifecycle.up(instance=instance, class_roster=path)
    now = {host.name: host.address for host in classroom.hosts}
    # Kept hosts keep their address; the new one takes the first free address (green-main's).
    assert now == {"blue-main": address["blue-main"], "blue-robot": address["blue-robot"],
                   "sim1-main": address["sim1-main"], "sim2-main": address["green-main"]}
    assert done == [("removed", "green-main"), ("removed", "green-robot"),
                    ("booted", [("sim2-main", address["green-main"])])]
    assert 'turtlebot3_model: waffle' in instance.roster_path.read_text() != first
    assert any(line.endswith("setting teams.blue.turtlebot3_model: \"burger\" -> \"waffle\"") for line in lines), lines
    assert any(line.endswith("removed green-robot (no longer in the roster)") for line in lines), lines
    assert any("added sim2-main (sim2 main, Ubuntu 24.04" in line for line in lines), lines
    assert not any("setting teams.green" in line for line in lines), [l for l in lines if "green" in l]
    # The state remembers each host's address for the next `load`.
    reloaded = instance.plan_members(__import__("json").loads(
        (instance.state_dir / "sandbox.json").read_text())["members"])
    assert {host.name: host.address for host in reloaded} == now


def test_a_secret_setting_that_changed_is_named_without_its_value():
    lines = lifecycle.roster_changes("classroom: {wifi_password: old1234567}\n",
                                     "classroom: {wifi_password: new7654321}\n", [], [])
    assert lines == ["setting classroom.wifi_password: (hidden) -> (hidden)"]
    assert lifecycle.roster_changes("a: 1\n", "a: 1\n", [], []) == ["the roster is unchanged: nothing to do"]


def test_a_class_on_a_ros_snapshot_gets_the_sandboxs_stand_in_snapshot(tmp_path, rosdistro_url):
    """snapshots.ros.org is out of the sandbox's reach: a class in snapshot mode is tried on the
    sandbox's stand-in snapshot server, and each of its snapshot settings is a note."""
    path, instance, hosts, _ = planned(tmp_path, rosdistro_url)
    text = path.read_text().replace("  nodes_verify_timeout: 30\n", "  nodes_verify_timeout: 30\n"
                                    "  ros_apt_source_mode: snapshot\n  ros_apt_snapshot: '2026-08-07'\n"
                                    "  ros_apt_snapshot_key_file: ros-snapshots.asc\n")
    path.write_text(text)
    served = {"ros_apt_snapshot": "2026-11-29", "ros_apt_snapshot_url": "http://10.213.163.1:8080/ros-snapshots",
              "ros_apt_snapshot_key_file": "/run/roslab/sandbox/try-class/ros-archive-key.asc"}
    published = SimpleNamespace(roster_settings=lambda: dict(SANDBOX_SETTINGS))
    base = lifecycle.roster(lifecycle.Classroom(instance, hosts, path), published)
    roster, notes = class_roster.sandbox_roster(path, base, {h.name: h.address for h in hosts},
                                                {h.name: h.release for h in hosts}, snapshot=served)

    assert roster["classroom"]["ros_apt_source_mode"] == "snapshot"
    assert {key: roster["classroom"][key] for key in served} == served
    assert "classroom: ros_apt_snapshot: the sandbox serves its own" in notes
    assert "classroom: ros_apt_snapshot_key_file: the sandbox serves its own" in notes

    path.write_text(text.replace("  ros_apt_source_mode: snapshot\n", ""))  # package mode: nothing replaced
    roster, _ = class_roster.sandbox_roster(path, base, {h.name: h.address for h in hosts},
                                            {h.name: h.release for h in hosts}, snapshot=served)
    assert roster["classroom"]["ros_apt_snapshot"] == "2026-08-07" and "ros_apt_snapshot_url" not in roster["classroom"]
