"""The settings schema, table-driven: every setting refuses a wrong type, every format a bad value.

Each case writes a real roster, loads it through `inventories/lab.py` exactly as
`pyinfra inventories/lab.py deploy.py` does, with every outgoing connection made to
fail the test, and asserts the one-line message (file:line, team, host, field) and the
exit before any host is contacted.
"""

from __future__ import annotations

import ast
import json
import runpy
from pathlib import Path

import pytest

from roslab import quoting, settings
from roslab.roster import RosterError, load_roster

REPO = Path(__file__).resolve().parents[2]
LAB_INVENTORY = REPO / "inventories" / "lab.py"

ROSTER = """\
classroom:
  ssh_user: ubuntu{classroom}
teams:
  team1:
    ros_domain_id: 11{team}
    hosts:
      team1-main:
        role: main{host}
"""
LINE_OF_LEVEL = {"classroom": 3, "team": 6, "host": 9}

# A value of the wrong type for each kind of setting.
WRONG_TYPE = {str: 5, int: "ten", bool: "yes", list: "updates", dict: ["noble"]}

NEWLINE, SUBSHELL, BACKTICKS, HEX_QUOTE = "x\ny", "$(touch /tmp/pwned)", "`id`", "\\x27"
# At least one bad value for every setting that has a format; hostile classes where
# the value reaches a shell, a path, a unit file, an apt source or a template.
BAD_VALUES: dict[str, list] = {
    "name": [NEWLINE],
    "secrets_file": [NEWLINE],
    "role": ["pilot"],
    "address": ["host name", "10.0.0.1\n", "123"],
    "ssh_user": ["-oProxyCommand=x", "Root", SUBSHELL],
    "ssh_port": [0, 70000],
    "ssh_key": ["missing/key", NEWLINE],
    "ssh_known_hosts_file": [NEWLINE],
    "ssh_strict_host_key_checking": ["maybe"],
    "sudo_password_secret": ["../etc/passwd", NEWLINE],
    "login_user": [SUBSHELL, "a b", "-r"],
    "apt_lock_timeout": [-1, 10**9],
    "run_lock_wait": [-1, 10**9],
    "apt_extra_suites": [["updates\nTrusted: yes"], ["-updates"], ["up dates"]],
    "apt_cache_max_age": [-5],
    "locale": ["C", "en_US.UTF-8\nLANG=C", "en_US.UTF-8 $(id)"],
    "timezone": ["Europe/Berlin\n", "../etc/passwd", "Europe/Berlin; id", "/Etc/UTC"],
    "ros_apt_source_mode": ["mirrors"],
    "ros_apt_source_version": ["1.2.0\n", "latest", "1.2.0; rm -rf /"],
    "ros_apt_source_sha256": [{"noble": "abc"}, {"bionic": "0" * 64}],
    "ros_apt_source_url": ["ftp://x/y.deb", "https://x/{evil}.deb", "https://x/a b.deb",
                           "https://x/y.deb\nTrusted: yes"],
    "ros_apt_source_cache_dir": [NEWLINE],
    "ros_apt_mirror_url": ["http://mirror/ros2\nTrusted: yes", "file:///etc", "mirror/ros2",
                           "http://mirror/ros2 http://evil/"],
    "ros_apt_mirror_key_file": ["no/such.asc"],
    "ros_apt_snapshot": ["latest", "2026-02-30", "2026-W32-5", "2026-08-07\nTrusted: yes", "2026-08-07/../x", "20260807"],
    "ros_apt_snapshot_url": ["http://snapshots.ros.org\nTrusted: yes", "file:///etc", "snapshots.ros.org"],
    "ros_apt_snapshot_key_file": ["no/such.asc"],
    "ubuntu_release": ["20.04", "24.04\n"],
    "ros_distro": ["rolling", "jazzy\n"],
    "ros_variant": ["ros-desktop", "desktop; id"],
    "ros_variant_main": ["gui"],
    "ros_variant_robot": ["tiny"],
    "ros_extra_packages": [["-o APT::Get::Trivial-Only=false"], ["-oDebug::pkgProblemResolver=1"],
                           ["ros-{distro}-turtlesim\nros-evil"], ["Turtle"], ["ros-{evil}"]],
    "rosdep_package": ["-y", "python3 rosdep"],
    "rosdep_sources_list_url": ["ssh://x/list", "https://x/l\n"],
    "rosdistro_index_url": ["file:///tmp/index.yaml", "https://x/i yaml", "https://x/i.yaml\nX: y"],
    "rosdep_update_max_age": [-1],
    "rosdep_cache_dir": [NEWLINE],
    "python_index_url": ["file:///srv/simple", "https://x/simple\nX: y", "https://x/a b"],
    "python_wheelhouse_dir": [NEWLINE, "/etc/wheels"],
    "python_sdist_build_packages": [["-y"], ["gcc; id"], ["Python3-dev"]],
    "apt_cache_host": ["team1 main", "team1-main\n", "-oProxy", SUBSHELL, "a.b"],
    "underlay_builder": ["team1 main", "team1-main\n", "-oProxy", SUBSHELL, "a.b", "../x"],
    "apt_cache_port": [0, 65536],
    "apt_cache_upstream_ports": [[0], [80, 70000]],
    "ros_domain_id": [102, -1, 214, 233],
    "ros_automatic_discovery_range": ["subnet", "LAN"],
    "ros_static_peers": [["10.0.0.1;10.0.0.2"], ["peer\n"], [SUBSHELL]],
    "ros_middleware": ["rmw_connextdds", "fastdds", "RMW_FASTRTPS_CPP", "rmw_zenoh_cpp\n"],
    "ros_discovery_mode": ["Static", "server", "multicast;id", "none"],
    "ros_discovery_server_port": [0, 80, 65536],
    "ros_zenoh_router_port": [1023, 70000],
    "teacher_ssh_keys": [["no/such.pub"], ["ssh-ed25519 AAAA teacher\nssh-rsa AAAA evil"]],
    "network_backend": ["ifupdown"],
    "network_interface": ["-eth0", "eth0\n", "a-very-long-interface", "eth0; id"],
    "network_kind": ["bluetooth"],
    "network_method": ["manual"],
    "network_address": ["10.0.0.300/24", "10.0.0.5/24\n"],
    "network_prefix": [4, 33],
    "network_gateway": ["router"],
    "network_nameservers": [["dns.example"], ["1.1.1.1\n"]],
    "network_ipv6": ["on"],
    "wifi_ssid": ["lab\nnetwork", "x" * 33],
    "wifi_password_secret": ["../x", "a b"],
    "wifi_regulatory_domain": ["de", "XX", "DEU", "D\u0395", "GB\n"],
    "console_password_secret": ["../x", "a b"],
    "network_confirm_timeout": [5, 100000],
    "network_backups_keep": [0, 101],
    "ssh_permit_root_login": ["yes", "without-password", "No"],
    "workspace_dir": ["ros2_ws", "/etc", "~/../../etc", "~/ws/../..", "~/ws$(id)", "~/`id`",
                      "~", "~/ws\nExecStartPre=/bin/sh", "~/" + HEX_QUOTE, "~/-ws"],
    "workspace_nodes_dir": ["no/such/dir"],
    "workspace_colcon_args": [["--event-handlers", "console_direct+ $(id)"], ["a\nb"], ["'"]],
    "nodes_launch_main": ["roslab_bringup", "roslab_bringup main.launch.py\nExecStartPre=/bin/sh",
                          "roslab_bringup ../main.launch.py", "roslab_bringup main.launch.py x:=1",
                          "roslab_bringup main.launch.py; id", "Roslab main.launch.py"],
    "nodes_launch_robot": ["roslab_bringup robot.launch.py %n", "$(id) robot.launch.py"],
    "nodes_launch": ["turtlebot3_bringup", "turtlebot3_bringup robot.launch.py\nUser=root",
                     "turtlebot3_bringup robot.launch.py LDS_MODEL:=x", "$(id) robot.launch.py"],
    "nodes_verify_topic": ["chatter topic", "/chatter\n", "/$(id)"],
    "nodes_verify_type": ["LaserScan", "sensor_msgs/msg/LaserScan;id", "sensor_msgs/msg/Laser Scan", "Sensor/msg/X"],
    "nodes_verify_timeout": [0, 10**6],
    "workspace_sources": [["../x.repos"], ["missing.repos"], ["lab.yaml"], ["/etc/x.repos"], [NEWLINE],
                          ["a$(id).repos"]],
    "source_pins": [["osr-rover-code"], {"../x": "v1.0"}, {"/abs": "v1.0"}, {"osr-rover-code": "master"},
                    {"osr-rover-code": "jazzy"}, {"osr-rover-code": "4f436e5"}, {"x": "v1\nrm -rf /"},
                    {"x": 1.5}],
    "source_url_rewrites": [{"https://github.com/": "ssh://mirror/"}, {"git@github.com:": "http://m/"},
                            {"https://github.com/": "http://user:pw@m/"}, {"https://github.com/": "http://m/\nx"}],
    "sources_cache_dir": [NEWLINE, "/etc/roslab"],
    "class_lock_debs_dir": [NEWLINE, "/etc/roslab", "~/.ssh/debs"],
    "sources_underlay_dir": ["/opt/underlay", "~/../../etc", "~/u$(id)", "~"],
    "sources_fetch_timeout": [0, 10**6],
    "robot_profile": ["TurtleBot3", "turtle bot", "tb3;id", "../demo", ""],
    "board": ["pi6", "Pi4", "raspberry"],
    "ros_environment": [{"ROS_DOMAIN_ID": "3"}, {"A B": "x"}, {"X": "a\nb"}, {"PATH": "/tmp"},
                        {"LD_PRELOAD": "/tmp/x.so"}, {"X": 1}, {"9X": "y"}, {"X": ""}],
}


def roster_with(tmp_path: Path, level: str, key: str, value) -> tuple[Path, int]:
    """A roster setting `key` at `level`; returns its path and the line of the key."""
    indent = {"classroom": "  ", "team": "    ", "host": "        "}[level]
    text = f"\n{indent}{key}: {json.dumps(value, ensure_ascii=False)}"
    parts = {"classroom": "", "team": "", "host": ""}
    parts[level] = text
    if key == "role":
        parts["host"] = text  # replaces the host's own role below
        roster = ROSTER.replace("\n        role: main", "").format(**parts)
        line = LINE_OF_LEVEL["host"] - 1
    else:
        roster = ROSTER.format(**parts)
        line = LINE_OF_LEVEL[level]
    path = tmp_path / "lab.yaml"
    path.write_text(roster, encoding="utf-8")
    return path, line


def level_of(setting: settings.Setting) -> str:
    return "host" if "host" in setting.levels else setting.levels[-1]


def expected_prefix(level: str, line: int, key: str) -> str:
    where = {"classroom": "", "team": "team 'team1', ", "host": "team 'team1', host 'team1-main', "}
    return f"lab.yaml:{line}: {where[level]}field '{key}': "


def inventory_refuses(path: Path, monkeypatch, capsys) -> str:
    """Load the roster through inventories/lab.py; assert it exits 2 and return stderr."""
    monkeypatch.setenv("ROSLAB_ROSTER", str(path))
    monkeypatch.chdir(path.parent)
    with pytest.raises(SystemExit) as exited:
        runpy.run_path(str(LAB_INVENTORY))
    assert exited.value.code == 2
    return capsys.readouterr().err


def test_every_setting_with_a_format_has_bad_values_listed():
    formatted = {s.key for s in settings.SCHEMA if s.check is not None}
    assert sorted(formatted - set(BAD_VALUES)) == []
    assert sorted(set(BAD_VALUES) - set(settings.SETTINGS)) == []


@pytest.mark.parametrize("setting", settings.SCHEMA, ids=lambda s: s.key)
def test_a_value_of_the_wrong_type_stops_before_any_host_is_contacted(
        setting, tmp_path, monkeypatch, capsys, no_connections):
    level = level_of(setting)
    path, line = roster_with(tmp_path, level, setting.key, WRONG_TYPE[setting.kind])
    err = inventory_refuses(path, monkeypatch, capsys)
    assert "no host was touched" in err
    assert expected_prefix(level, line, setting.key) + "must be " in err
    assert no_connections == []


@pytest.mark.parametrize(
    "key, value",
    [(key, value) for key, values in BAD_VALUES.items() for value in values],
    ids=lambda item: item if isinstance(item, str) and item in settings.SETTINGS else repr(item)[:40])
def test_a_bad_value_stops_before_any_host_is_contacted(key, value, tmp_path, monkeypatch, capsys,
                                                         no_connections):
    setting = settings.SETTINGS[key]
    level = level_of(setting)
    path, line = roster_with(tmp_path, level, key, value)
    err = inventory_refuses(path, monkeypatch, capsys)
    assert expected_prefix(level, line, key) in err, err
    assert no_connections == []


def test_a_secret_value_never_appears_in_a_message(tmp_path):
    secret = "hunter2-PLANTED-secret"
    (tmp_path / "secrets.yaml").write_text(f"lab_wifi: [{secret}\n")  # broken YAML
    (tmp_path / "secrets.yaml").chmod(0o600)
    path, _ = roster_with(tmp_path, "host", "wifi_password_secret", "lab_wifi")
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert secret not in str(raised.value)
    assert "secrets.yaml" in str(raised.value)


@pytest.mark.parametrize("content, message", [
    (b"\xff\xfeclassroom: {}\n", "is not UTF-8 text"),
    (b"classroom:\x00\x01\x02\n", "is a binary file"),
    (b"[" * 5000 + b"]" * 5000, "nested too deeply"),
])
def test_unreadable_files_are_one_line_errors(tmp_path, content, message):
    path = tmp_path / "lab.yaml"
    path.write_bytes(content)
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert len(raised.value.problems) == 1
    assert message in str(raised.value)


def test_an_alias_bomb_is_refused_quickly(tmp_path):
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for level in range(1, 10):
        previous = f"*a{level - 1}"
        lines.append(f"a{level}: &a{level} [{', '.join([previous] * 10)}]")
    path = tmp_path / "lab.yaml"
    path.write_text("classroom:\n  bomb:\n" + "\n".join("    " + line for line in lines) + "\n")
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert "aliases" in str(raised.value)


def big_roster(path, teams: int):
    lines = []
    for team in range(teams):
        hosts = "\n".join(
            f"      t{team}-h{host}: {{role: {'main' if host == 0 else 'robot'}, "
            f"address: 10.{team // 250}.{team % 250}.{host + 1}}}" for host in range(50))
        lines.append(f"  t{team}:\n    ros_domain_id: {team}\n    hosts:\n{hosts}")
    path.write_text("classroom: {name: big}\nteams:\n" + "\n".join(lines) + "\n")
    return path


def test_a_big_roster_is_checked_in_time_linear_in_its_hosts(tmp_path):
    import time

    # CPU time, not wall time: on a machine busy with sandbox classes the wall clock measures
    # the others' work (35 s of wall for 1.7 s of CPU, seen). Quadratic checks took minutes at
    # 5,000 hosts; here 2,500 hosts against 500: linear is 5 times the cost (less, with the
    # fixed start), a check over pairs of hosts 25 times.
    cost = {}
    for teams in (10, 50, 10):  # the small one twice: the first also warms the profile cache
        path = big_roster(tmp_path / f"lab-{teams}.yaml", teams)
        started = time.process_time()
        assert len(load_roster(path).hosts) == teams * 50
        cost[teams] = time.process_time() - started
    assert cost[50] < 15
    assert cost[50] < 12 * cost[10], cost


def test_legal_awkward_values_are_written_as_they_are():
    word = "it's a \"quoted\" $(value) with `ticks` and \\x27 and 100%"
    # A shell reads the word back unchanged.
    import subprocess

    echoed = subprocess.run(["bash", "-c", f"printf %s {quoting.shell_word(word)}"],
                            capture_output=True, text=True, check=True).stdout
    assert echoed == word
    # systemd's own quoting rules: each special character escaped.
    assert quoting.systemd_word("a%b$c\\d\"e") == '"a%%b$$c\\\\d\\"e"'
    for writer in (quoting.shell_word, quoting.systemd_word, quoting.deb822_value):
        with pytest.raises(ValueError):
            writer("two\nlines")
    with pytest.raises(ValueError):
        quoting.apt_arguments(["-oAPT::Foo=1"])


def test_roslab_never_imports_deploy():
    offenders = []
    shipped = REPO / "roslab" / "data"  # the deploy and nodes roslab ships (roslab.packaged), not its code
    for path in (REPO / "roslab").rglob("*.py"):
        if shipped in path.parents:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            offenders += [f"{path.relative_to(REPO)}: {name}" for name in names
                          if name == "deploy" or name.startswith("deploy.")]
    assert offenders == []


def test_each_deploys_defaults_are_its_concern_in_the_schema():
    import importlib

    for concern in settings.DEPLOY_CONCERNS:
        module = importlib.import_module(f"deploy.{concern}")
        assert module.DEFAULTS == settings.defaults(concern), concern


@pytest.mark.parametrize("value, hint", [
    ("yes", 'YAML 1.1 reads yes as true, other YAML readers as text: quote it, "yes"'),
    ("true", "YAML reads yes/no/on/off/true/false as true or false: quote it"),
    ("1234", 'YAML reads 1234 as a number: quote it, "1234"'),
])
def test_an_ssid_yaml_reads_as_something_else_says_to_quote_it(tmp_path, value, hint):
    path = tmp_path / "lab.yaml"
    path.write_text(ROSTER.format(classroom="", team="", host=f"\n        wifi_ssid: {value}"))
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert "lab.yaml:9: team 'team1', host 'team1-main', field 'wifi_ssid': " in str(raised.value)
    assert hint in str(raised.value)


@pytest.mark.parametrize("name", ["1234", '"team1-main\\n"', '"-main"', '"a.b"', "'x y'"])
def test_host_names_that_cannot_be_hostnames_are_refused(tmp_path, name):
    path = tmp_path / "lab.yaml"
    path.write_text(ROSTER.replace("      team1-main:", f"      {name}:").format(classroom="", team="", host=""))
    with pytest.raises(RosterError) as raised:
        load_roster(path)
    assert "lab.yaml:7: team 'team1'" in str(raised.value)
    assert "is not a valid hostname" in str(raised.value)
